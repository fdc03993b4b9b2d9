"""The one resolved configuration of a run: a frozen dataclass the CLI is built from.

``config.json`` in a run directory is ``config_to_dict(cfg)``; ``config_from_dict`` reads it
back (unknown keys are an error; missing keys take today's defaults, or, for a setting whose
default changed, the old one: ``FORMER_DEFAULTS``).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import tyro

from d2spo.algos import (
    has_runtime_filter,
    known_algos,
    learner_anneals,
    reward_mode,
)
from d2spo.algos.cpo import CPOConfig
from d2spo.algos.d2spo import D2SPOConfig
from d2spo.algos.ppo_lag import PPOLagConfig
from d2spo.algos.rcrl import RCRLConfig
from d2spo.algos.sac_lag import SACLagConfig
from d2spo.algos.td3 import DEFAULT_WIDTHS, TD3Config
from d2spo.algos.td3_lag import TD3LagConfig
from d2spo.envs import EnvConfig
from d2spo.envs.dynamics import Preset
from d2spo.errors import ConfigError, json_trouble
from d2spo.fields import check_fields
from d2spo.inputs import read_regular
from d2spo.ltl.anneal import AnnealConfig
from d2spo.ltl.buchi_task import task_is_recurrence
from d2spo.ltl.tasks import MAX_PATROLS
from d2spo.memory import check_memory
from d2spo.safety.cbf import BATCH_SIZE, ONE_LAYOUT_BATCH_SIZE, RECURRENCE_UPDATE_STEPS, UPDATE_STEPS, CBFConfig

PAPER_EPISODES = 20_000
"""Training episodes of a run on one layout (the paper's)."""
GENERALIST_EPISODES = 4_000
"""Training episodes of a generalist (``--generalist``); docs/config.md says why."""
GENERALIST_TASKS = 16
"""Random reach-avoid sequences a generalist trains on beside ``--task`` (``generalist_tasks``);
docs/config.md says why."""
FAST_SETTINGS: dict[str, Any] = {"num_envs": 32, "td3.hidden": (64, 64)}
"""What ``--fast`` gives D²SPO and SL on one layout (``TrainConfig.fast``): half the TD3 updates per
transition, with a quarter of their arithmetic; docs/config.md gives its gain and its price."""
DEFAULT_SETTINGS: dict[str, Any] = {"num_envs": 16, "td3.hidden": DEFAULT_WIDTHS}
"""The same settings without ``--fast``, for every learner on one layout."""
GENERALIST_SETTINGS: dict[str, Any] = {"num_envs": 16, "td3.hidden": (256, 256)}
"""The same for the generalist (``--generalist``): wider TD3 networks, for its zero-shot patrols at
about 1.5x the training time; docs/config.md gives the measurements."""
CBF_FILLED_FIELDS = ("updates_per_iter", "nominal_updates_per_iter", "batch_size")
"""The ``cbf`` fields ``TrainConfig`` fills where unset from the task, the robot, --fast and
--generalist (``_resolve_cbf_fields``): UPDATE(Ω, Θ)'s two step counts and its minibatch. A
--dynamics file (another robot) and --no-fast fill them again (``cli``)."""
WANDB_FORBIDDEN = "/\\#?%:"
"""Characters a W&B project name may not hold (``--wandb-project``)."""
VALIDATION_SEED = 50_000
"""First seed of the generalist's validation layouts (training uses WORLD:0 .., the benchmark
random:100000 ..)."""
REDRAW_SEED = 10_000_000
"""First seed of the layouts a generalist's bank is redrawn with (``generalist_redraw``)."""
GENERALIST_WORLDS = ("world", "random")
"""Layout families a generalist trains on (``generalist_world``): ``world:SEED`` (``envs.world``:
rectangular arenas of 5-20 m, boxes and pillars, 4-12 labelled areas, ZoneEnv's zones among them)
or ``random:SEED`` (``envs.generator``: square 5-10 m arenas of boxes, areas A1..A4)."""


@dataclass(frozen=True)
class TrainConfig:
    """A training run: the learner, the task, the environment and every hyper-parameter."""

    algo: str = "d2spo"
    """Learner: d2spo, sl (D²SPO, sparse reward), tlgrl (TD3 + Eq. (8)),
    td3 (sparse), td3-lag, sac-lag, rcrl, ppo-lag, cpo."""
    task: str = "phi1"
    """Task name (phi1, phi2, relaxed, ...) or LTL formula."""
    episodes: int | None = None
    """Episodes; None: 20000, or 4000 with --generalist."""
    seed: int = 0
    """Random seed; a seed and a config give one run, always."""
    num_envs: int | None = None
    """Parallel environments; None: 16, or 32 with --fast."""
    fast: bool = False
    """D²SPO and SL on one layout: 32 envs, 64-64 TD3 networks (unless given); faster, more collisions."""
    chunk_steps: int = 250
    """Vectorised steps per jitted chunk (one host sync each)."""
    checkpoint_every: int = 1_000
    """Write a checkpoint every this many episodes (at the end of the first chunk past each multiple)."""
    window: int = 2_000
    """Safety and completion rates cover the last N episodes."""
    snapshots: tuple[int, ...] = ()
    """Also save policy-N.msgpack after N episodes, for each N."""
    eval_episodes: int = 100
    """Episodes of the final deterministic evaluation."""
    generalist: bool = False
    """Train one d2spo policy for a bank of random layouts."""
    generalist_layouts: int = 256
    """With --generalist: train on layouts WORLD:0..N-1 (WORLD: ``generalist_world``)."""
    generalist_redraw: int = 0
    """With --generalist: after every chunk, this many bank slots no environment is in get fresh
    layouts (WORLD:REDRAW_SEED ..., each keeping its slot's task); 0: the bank stays fixed."""
    generalist_pairings: int = 1
    """With --generalist: slots per layout, each paired with the next task of the mixture in turn
    (layout n runs tasks n*P .. n*P+P-1 modulo the mixture's size), so a layout is seen with P tasks
    and a task with P times as many layouts; the bank has generalist_layouts * P slots."""
    generalist_world: str = "world"
    """With --generalist: the layout family it trains and validates on: world (rectangular arenas to
    20 m, pillars, 4-12 labelled areas, ZoneEnv's zones among them) or random (square 5-10 m, A1..A4)."""
    generalist_tasks: int | None = None
    """With --generalist: also train on N random reach-avoid tasks; 0: --task alone. None: 16."""
    generalist_patrols: int = 0
    """With --generalist: also train on N random patrols and responses (``ltl.tasks.patrol_tasks``;
    never the suite's patrol2, patrol3, respond), scored by their accepting visits; 0: none."""
    validation_layouts: int = 16
    """With --generalist: keep the policy that does best on N held-out layouts; 0: the last."""
    validation_episodes: int = 256
    """With --generalist: episodes of each validation."""
    validate_every: int = 250
    """With --generalist, or a patrol's --patrol-validation: validate every N training episodes (at the
    end of the first chunk past each multiple)."""
    patrol_validation: int = 32
    """One layout, a recurrence task (a patrol, scored by its accepting visits): every validate_every
    episodes, run the policy for N deterministic episodes on the training layout and keep the one that
    visits most as policy-best.msgpack, which `d2spo eval` and summary.json's eval_best use (a patrol's
    last policy can visit far less often than its training episodes did); 0: the last policy."""
    eval_untrained: bool = False
    """Also evaluate the untrained policy (summary.json's eval_untrained); not with --resume."""
    wandb: bool = False
    """Also log the TensorBoard scalars to Weights & Biases (pip install 'd2spo[wandb]'; WANDB_MODE=offline
    logs without an account); a resume continues the same W&B run."""
    wandb_project: str = "d2spo"
    """With --wandb: the W&B project (its entity: WANDB_ENTITY, or your account's default)."""
    env: Annotated[EnvConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=EnvConfig)
    """Environment (its flags carry no prefix: --layout, --preset, --dt, ...)."""
    td3: TD3Config = field(default_factory=TD3Config)
    """TD3 (the RL policy pi_rl of td3, tlgrl, d2spo and sl)."""
    anneal: AnnealConfig = field(default_factory=AnnealConfig)
    """Annealed subtask radius (Sec. IV-C); only used with the progress reward."""
    cbf: CBFConfig = field(default_factory=CBFConfig)
    """Data-driven CBF, nominal model and the executed policy pi_Omega (d2spo, sl)."""
    d2spo: D2SPOConfig = field(default_factory=D2SPOConfig)
    """D²SPO's schedule: safety updates, cautious start, filter (d2spo, sl)."""
    td3_lag: TD3LagConfig = field(default_factory=TD3LagConfig)
    """TD3-Lagrangian (td3-lag): TD3, cost critics, Lagrange multiplier."""
    sac_lag: SACLagConfig = field(default_factory=SACLagConfig)
    """SAC-Lagrangian (sac-lag): SAC, cost critics, Lagrange multiplier."""
    rcrl: RCRLConfig = field(default_factory=RCRLConfig)
    """RCRL (rcrl): SAC, safety value Q_h, multiplier network lambda(s)."""
    ppo_lag: PPOLagConfig = field(default_factory=PPOLagConfig)
    """PPO-Lagrangian (ppo-lag): PPO-clip, reward and cost critics, multiplier."""
    cpo: CPOConfig = field(default_factory=CPOConfig)
    """CPO (cpo): trust region step, linearised cost constraint."""

    @property
    def layout(self) -> str:
        return self.env.layout

    def env_config(self) -> EnvConfig:
        """The env config with the reward mode this learner uses (``d2spo.algos.LEARNERS``)."""
        mode = reward_mode(self.algo)
        return dataclasses.replace(self.env, reward=dataclasses.replace(self.env.reward, mode=mode))

    def __post_init__(self) -> None:
        if self.algo not in known_algos():
            raise ConfigError("algo", f"unknown algorithm {self.algo!r}; choose one of {list(known_algos())}")
        if self.generalist and self.algo != "d2spo":
            raise ConfigError("generalist", f"the generalist is trained with --algo d2spo, not {self.algo!r}")
        if self.episodes is None:  # the paper's 20000 for one layout; the generalist's own default
            object.__setattr__(self, "episodes", GENERALIST_EPISODES if self.generalist else PAPER_EPISODES)
        self._resolve_speed_settings()
        if self.generalist_tasks is None:
            object.__setattr__(self, "generalist_tasks", GENERALIST_TASKS if self.generalist else 0)
        check_fields(self, count=("episodes", "num_envs", "chunk_steps", "checkpoint_every", "window",
                                  "generalist_layouts", "generalist_pairings", "validation_episodes",
                                  "validate_every"),
                     seed=("seed",), counts=("snapshots",),
                     natural=("eval_episodes", "generalist_tasks", "generalist_patrols", "validation_layouts",
                              "patrol_validation"),
                     flag=("fast", "wandb"))
        late = [n for n in self.snapshots if n > self.episodes]
        if late:  # it would never be written, and the figure that wants it would fail at the end
            raise ConfigError("snapshots", f"{late[0]} is past the run's {self.episodes} episodes; a snapshot is "
                              "taken after that many episodes")
        if self.generalist_patrols and not self.generalist:
            raise ConfigError("generalist_patrols", "trains the generalist's task mixture; add --generalist")
        if self.generalist_patrols > MAX_PATROLS:
            raise ConfigError("generalist_patrols", f"at most {MAX_PATROLS} distinct patrols exist over A1..A4, "
                              f"got {self.generalist_patrols}")
        project = self.wandb_project
        if not (isinstance(project, str) and 0 < len(project) <= 128) or set(project) & set(WANDB_FORBIDDEN):
            raise ConfigError("wandb_project", f"a W&B project name is 1 to 128 characters without "
                              f"{' '.join(WANDB_FORBIDDEN)}, got {self.wandb_project!r}")
        if self.generalist_world not in GENERALIST_WORLDS:
            raise ConfigError("generalist_world", f"expected one of {', '.join(GENERALIST_WORLDS)}, "
                              f"got {self.generalist_world!r}")
        slots = self.generalist_layouts * self.generalist_pairings
        if not 0 <= self.generalist_redraw <= slots:
            raise ConfigError("generalist_redraw", f"expected 0 .. the bank's slots (generalist_layouts * "
                              f"generalist_pairings = {slots}), got {self.generalist_redraw}")
        mixture = 1 + self.generalist_tasks + self.generalist_patrols
        if self.generalist and self.generalist_pairings > mixture:
            raise ConfigError("generalist_pairings", f"at most the mixture's {mixture} tasks (--task, "
                              f"generalist_tasks, generalist_patrols), got {self.generalist_pairings}")
        if self.generalist and self.generalist_layouts > VALIDATION_SEED:
            raise ConfigError("generalist_layouts", f"at most {VALIDATION_SEED}: the layouts from "
                              f"{self.generalist_world}:{VALIDATION_SEED} on are the validation set")
        if self.d2spo.actor_through_safety is None:  # on for one layout, off for the generalist
            object.__setattr__(self, "d2spo", dataclasses.replace(self.d2spo, actor_through_safety=not self.generalist))
        self._resolve_cbf_fields()
        if self.td3.forward_only is None:  # on for the generalist, off for one layout
            td3 = copy.copy(self.td3)  # checked when it was made: only the None is filled in
            object.__setattr__(td3, "forward_only", self.generalist)
            object.__setattr__(self, "td3", td3)
        if not isinstance(self.task, str) or not self.task.strip():
            raise ConfigError("task", f"expected a task name or an LTL formula, got {self.task!r}")

    def _resolve_cbf_fields(self) -> None:
        """Fill the unset step counts of UPDATE(Ω, Θ) (``cbf.updates_per_iter``, ``cbf.nominal_updates_per_iter``):
        ``RECURRENCE_UPDATE_STEPS`` for a recurrence (a patrol) on one layout with the default robot
        (preset "default", none of its fields set: no --dynamics file, no --v-gain, ...) without
        --fast, where half the count made more accepting visits; ``UPDATE_STEPS`` everywhere else.
        Half the count was every one-layout task's default from 2026-11-30 to 2026-12-04: on ϕ1,
        vmapped seeds 0-5 then completed 98.70-99.95% of their last 2000 episodes, four under
        Table II's 99.5%, against 99.80-100% with 10 and 10 (bench/RESULTS.md,
        "2026-12-04, late morning"); --fast's ϕ1 seed 0 85.20% against 99.70% (2026-12-01).
        config.json records them; the names filled here are kept in ``filled_cbf_fields`` (not a
        field), so that a --dynamics file applied after the flags decides them again
        (``cli.TrainCmd.config``). The minibatch (``cbf.batch_size``) likewise, where unset:
        ``ONE_LAYOUT_BATCH_SIZE`` for a task that is not a recurrence, on one layout, with the default
        robot, without --fast; ``BATCH_SIZE`` elsewhere. Since 2026-12-04 (afternoon), for ϕ1 in 3
        minutes with the tables held (bench/RESULTS.md); ``filled_cbf_fields`` names it too."""
        default_robot = self.env.preset == "default" and all(
            getattr(self.env, f.name) is None for f in dataclasses.fields(Preset))
        ours = not (self.generalist or self.fast) and default_robot
        recurrence = task_is_recurrence(self.task)
        steps = RECURRENCE_UPDATE_STEPS if ours and recurrence is True else UPDATE_STEPS
        batch = ONE_LAYOUT_BATCH_SIZE if ours and recurrence is False else BATCH_SIZE
        unset = {name: value for name, value in zip(CBF_FILLED_FIELDS, (steps, steps, batch))
                 if getattr(self.cbf, name) is None}
        if unset:
            object.__setattr__(self, "cbf", dataclasses.replace(self.cbf, **unset))
        object.__setattr__(self, "filled_cbf_fields", tuple(unset))

    def _resolve_speed_settings(self) -> None:
        """Fill ``num_envs`` and ``td3.hidden`` where None: ``FAST_SETTINGS`` with ``fast`` (D²SPO and SL
        on one layout only), ``GENERALIST_SETTINGS`` with ``generalist``, else ``DEFAULT_SETTINGS``.
        config.json records the values, so a run made before a default changed reads back as it ran."""
        if self.fast and (self.generalist or not has_runtime_filter(self.algo)):
            raise ConfigError("fast", f"is for d2spo and sl on one layout, not {self.algo}"
                              f"{' --generalist' if self.generalist else ''}; leave it out (over the --config "
                              "file of a --fast run: --no-fast)")
        table = FAST_SETTINGS if self.fast else GENERALIST_SETTINGS if self.generalist else DEFAULT_SETTINGS
        if self.num_envs is None:
            object.__setattr__(self, "num_envs", table["num_envs"])
        if self.td3.hidden is None:
            object.__setattr__(self, "td3", dataclasses.replace(self.td3, hidden=table["td3.hidden"]))

    def check(self, seeds: int = 1) -> TrainConfig:
        """This config, if this machine can hold a run of it (``seeds`` vmapped together): every field
        is checked when it is made (``__post_init__``), the memory its arrays need here, from the
        config alone (``d2spo.memory``), before anything is built. A config.json that is read back
        (to evaluate a run) is not held to this machine's memory, nor to the check below, which
        came after generalists had been trained with the anneal settings recorded.

        The generalist draws each episode's layout with its areas' true radii
        (``envs.generalist``), so ``--anneal.*`` would change nothing there, nor ``--layout`` (it
        trains on generated layouts): refused, not ignored."""
        if self.generalist and self.env.layout != EnvConfig().layout:  # it was recorded, and unused
            raise ConfigError("env.layout", "has no effect with --generalist: it trains on generated layouts "
                              f"({self.generalist_world}:0..{self.generalist_layouts - 1}); to run it on your "
                              "layout, train first, then `d2spo eval RUN --layout FILE --task ...` (zero-shot)")
        if not self.generalist and self.env.forbidden_range is not None:
            raise ConfigError("env.forbidden_range", "is what a generalist observes of a forbidden area; without "
                              "--generalist it has no effect: leave it out")
        if self.generalist and self.anneal != AnnealConfig():
            raise ConfigError("anneal", "has no effect with --generalist: every layout it draws is labelled "
                              "with its areas' true radii (docs/config.md); leave --anneal.* out")
        if self.env.label_radius is not None:
            if self.generalist:
                raise ConfigError("label_radius", "has no effect with --generalist: every layout it draws is "
                                  "labelled with its areas' true radii; leave --label-radius out")
            if self.anneal.enabled and learner_anneals(self.algo):
                raise ConfigError("label_radius", f"is a fixed relaxed radius for a learner that does not anneal; "
                                  f"{self.algo} anneals its labelling radius from d_bar / k1 (Sec. IV-C): set that "
                                  "with --anneal.d-bar and --anneal.k1, or turn annealing off with "
                                  "--anneal.no-enabled to use --label-radius")
        check_memory(self, seeds)
        return self


def config_to_dict(obj: Any) -> Any:
    """Plain JSON-able dict of a (nested) config dataclass."""
    if dataclasses.is_dataclass(obj):
        return {f.name: config_to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [config_to_dict(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _build(cls: type, data: dict, where: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(where.rstrip(".") or "config", f"expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        close = difflib.get_close_matches(unknown[0], sorted(names), n=1, cutoff=0.6)
        raise ConfigError(f"{where}{unknown[0]}", "unknown field" + (f" (did you mean {close[0]!r}?)" if close else ""))
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        while typing.get_origin(tp) is Annotated:
            tp = typing.get_args(tp)[0]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = _build(tp, value, f"{where}{name}.")
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


FORMER_DEFAULTS: dict[tuple[str, ...], Any] = {
    ("env", "reward", "shaping_clearance"): None,  # the default became 0.3 after the field was added
    ("env", "reward", "shaping_metric"): "geodesic",  # geodesic-per-state became the default on 2026-11-23
    ("anneal", "relax"): "all",  # the field came with the option "targets", which became the default
    ("validation_layouts",): 0,  # generalists trained before validation kept their last policy
    ("patrol_validation",): 0,  # patrols on one layout kept their last policy until 2026-11-30
    ("generalist_world",): "random",  # generalists trained on random:SEED until 2026-11-26
    ("td3", "recurrence_noise_final"): None,  # a patrol's exploration noise was constant until 2026-11-30
    ("td3_lag", "td3", "recurrence_noise_final"): None,  # td3-lag's, until 2026-12-02 (written as null before)
    ("env", "recurrence_max_steps"): 0,  # a recurrence's unset limit was the route rule's alone until 2026-11-30
    ("env", "base_max_steps"): 200,  # an unset max_steps gave 200 steps until 2026-11-25
    ("env", "reward", "shaping_clearance_cost"): 10.0,  # the per-state field's clearance band cost 10x until 2026-11-25
    ("env", "reward", "shaping_collide_cost"): 10.0,
    ("env", "observe_path"): False,  # the observation had no path direction until 2026-11-25
    ("td3", "forward_only"): False,  # the generalist's actor could propose reverse until 2026-11-27
    ("cbf", "updates_per_iter"): 10,  # every config.json names it; 10 was the default until 2026-11-30
    ("cbf", "nominal_updates_per_iter"): 10,
    ("env", "distance_obs"): "capped",  # a generalist saw every distance beyond 20 m as 20 m until 2026-11-27
    ("ppo_lag", "scale_cost_advantage"): True,  # PPO-Lagrangian standardised its cost advantages until 2026-12-02
}
"""Settings whose default has changed, with the value a config.json that does not mention them was
trained with (the field did not exist yet, and its old behaviour is this value)."""


def _with_former_defaults(data: dict) -> dict:
    data = dict(data)
    for path, value in FORMER_DEFAULTS.items():
        node = data
        for k in path[:-1]:
            if not isinstance(node.get(k), dict):
                break
            node[k] = node = dict(node[k])
        else:
            node.setdefault(path[-1], value)
    return data


def config_from_dict(data: dict) -> TrainConfig:
    """The config a config.json describes: missing keys take today's defaults, except settings whose
    default changed since (``FORMER_DEFAULTS``), which take the value the run was trained with."""
    return _build(TrainConfig, _with_former_defaults(data), "")


def config_file(path: Path) -> TrainConfig:
    """The config a config.json file describes (as a run directory holds it: ``config_to_dict``); a
    missing file, a file that is not JSON or a wrong field is a ConfigError naming the file."""
    def fail(message: str) -> ConfigError:
        return ConfigError("config", f"{path}: {message}")

    text = read_regular(path, lambda message: ConfigError("config", message))  # its messages name the file
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise fail(f"not valid JSON ({e.msg}: line {e.lineno}, column {e.colno})") from None
    except (RecursionError, ValueError) as e:
        raise fail(f"not valid JSON ({json_trouble(e)})") from None
    try:
        return config_from_dict(data)
    except ConfigError as e:
        raise fail(str(e)) from None
