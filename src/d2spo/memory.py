"""The memory a training config will need, estimated from the config alone (no layout loaded,
nothing built or compiled), so that a size beyond the machine (a replay buffer of 1e11
transitions, hidden layers 1e7 wide, 5e7 environments, 1e8 evaluation episodes) is refused in one
line before training, instead of ending minutes later in an overflow, an allocation failure or a
hang. ``TrainConfig.check`` calls ``check_memory``.

Every term is a lower bound: float32 arrays; the observation at its smallest (the lidar rays, the
pose, one area, one automaton state); the shortest episode limit (``base_max_steps``); a network
counted once, with Adam's two moments, whatever copies (targets, twin critics) the learner keeps. A
config refused here cannot fit; one accepted may still not.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING

from d2spo.algos import config_sections
from d2spo.errors import ConfigError

if TYPE_CHECKING:
    from d2spo.config import TrainConfig

FLOAT_BYTES = 4
MAX_BUFFER = 2**31 - 1
"""Largest replay buffer or dataset capacity: its write index is a 32-bit integer."""
CHUNK_LOG_FLOATS = 9
"""Floats per (step, env) of a chunk's episode log (``algos.base.ChunkLog``)."""


def machine_memory() -> int | None:
    """This machine's physical memory in bytes; None where the system does not say."""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None
    return pages * size if pages > 0 and size > 0 else None


def _fields(obj, where: str):
    """(path, value) of every field of the (nested) config dataclass ``obj``."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _fields(value, f"{where}{f.name}.")
        else:
            yield f"{where}{f.name}", value


def _mlp_params(widths: tuple[int, ...], inputs: int, outputs: int) -> int:
    sizes = (inputs, *widths, outputs)
    return sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))


def needs(cfg: TrainConfig, seeds: int = 1) -> list[tuple[int, str, str]]:
    """(bytes, field, what) of each large array a run of ``cfg`` holds, ``seeds`` vmapped together."""
    env = cfg.env
    obs = env.n_rays + 7  # lidar, pose (4), one area (2), one automaton state
    steps = env.max_steps or env.base_max_steps
    per_entry = {"buffer_size": (2 * obs + 5, "replay buffer", "transitions"),  # s, a, r, c, s', done
                 "transitions_capacity": (obs + 11, "CBF dataset T", "transitions"),
                 "p_exp_capacity": (obs + 11, "CBF dataset P_exp", "transitions"),
                 "unsafe_capacity": (env.n_rays + 1, "CBF dataset X_L", "features"),
                 "rollout_steps": (cfg.num_envs * (3 * obs + 11), "on-policy rollout", "steps")}
    out = [(seeds * cfg.num_envs * cfg.chunk_steps * CHUNK_LOG_FLOATS * FLOAT_BYTES, "num_envs",
            f"the episode log of a chunk ({cfg.num_envs:,} envs x {cfg.chunk_steps:,} steps)")]
    for section in config_sections(cfg.algo):
        for path, value in _fields(getattr(cfg, section), f"{section}."):
            name = path.rsplit(".", 1)[-1]
            if name in per_entry and isinstance(value, int):
                floats, what, unit = per_entry[name]
                out.append((seeds * value * floats * FLOAT_BYTES, path, f"the {what} ({value:,} {unit} of "
                                                                        f"{floats:,} floats)"))
            elif (name == "hidden" or name.endswith("_hidden")) and isinstance(value, tuple) and value:
                params = _mlp_params(value, obs, 2)
                out.append((seeds * 3 * params * FLOAT_BYTES, path,
                            f"a network of {params:,} weights, with Adam's moments"))
    rollouts = [("eval_episodes", cfg.eval_episodes, "the final evaluation")]
    if cfg.generalist and cfg.validation_layouts:
        rollouts.append(("validation_episodes", cfg.validation_episodes, "each validation"))
    for name, episodes, what in rollouts:
        out.append((rollout_bytes(env, episodes), name, f"{what} ({episodes:,} episodes of {steps} steps in parallel)"))
    return out


def rollout_bytes(env, episodes: int) -> int:
    """``episodes`` episodes of the EnvConfig ``env`` run in parallel: every episode's poses [T + 1, 3]
    and observation."""
    return episodes * (((env.max_steps or env.base_max_steps) + 1) * 3 + env.n_rays + 7) * FLOAT_BYTES


def check_eval_memory(env, episodes: int, limit: int | None = None) -> None:
    """ConfigError on ``episodes`` when that many evaluation episodes of ``env``, run in parallel (``d2spo
    eval``), would need more memory than ``limit`` bytes (default: this machine's): refused at once
    instead of hanging for hours or failing in an allocation."""
    n, limit = rollout_bytes(env, episodes), machine_memory() if limit is None else limit
    if limit is not None and n > limit:
        raise ConfigError("episodes", f"{episodes:,} evaluation episodes of {env.max_steps or env.base_max_steps} "
                          f"steps in parallel need at least {size_text(n)} of memory, more than this machine's "
                          f"{size_text(limit)}; make it smaller")


def size_text(n: float) -> str:
    """``n`` bytes, e.g. ``18.0 TiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError  # pragma: no cover


def check_memory(cfg: TrainConfig, seeds: int = 1, limit: int | None = None) -> None:
    """ConfigError, naming the field of the largest array, when a run of ``cfg`` would need more
    memory than ``limit`` bytes (default: this machine's, ``machine_memory``)."""
    parts = needs(cfg, seeds)
    limit = machine_memory() if limit is None else limit
    total = sum(n for n, _, _ in parts)
    if limit is not None and total > limit:
        n, field, what = max(parts)
        raise ConfigError(field, f"a run of this config needs at least {size_text(total)} of memory, {size_text(n)} "
                          f"of it for {what}: more than this machine's {size_text(limit)}; make it smaller")
    for section in config_sections(cfg.algo):
        for path, value in _fields(getattr(cfg, section), f"{section}."):
            if path.endswith(("buffer_size", "_capacity")) and isinstance(value, int) and value > MAX_BUFFER:
                raise ConfigError(path, f"at most {MAX_BUFFER} (a buffer's index is a 32-bit integer), got {value}")
