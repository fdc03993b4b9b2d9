"""Where an evaluation's result goes: the file name of ``d2spo eval``'s JSON in the run directory,
one name for every distinct evaluation (layout, dynamics, task, episode limit, seed, forbidden range,
policy, runtime filter), and its atomic write. ``d2spo.evaluate`` computes the result; this module
only names and writes it, so that a cached evaluation is found again (``bench/buchi_zero_shot.py``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from d2spo.envs.layouts import layout_file, random_seed
from d2spo.errors import ConfigError, NaNError
from d2spo.inputs import sha256_of
from d2spo.ltl.tasks import TASKS
from d2spo.runio import atomic_write_json


def task_tag(task: str) -> str:
    """A file-name-safe name of a task: its name, or ``f-`` and a hash of the formula."""
    if task in TASKS:
        return task
    return "f-" + hashlib.sha256(task.encode()).hexdigest()[:10]


def number_tag(value: float) -> str:
    """A number's part of an evaluation's file name: as ``:g`` writes it (``1.2``, ``0.05``, ``inf``)
    where that reads back as the same number, else its shortest exact form (``1.2000001``), so that
    two values that agree to six digits never share a file."""
    short = f"{value:g}"
    return short if float(short) == float(value) else repr(float(value))


def layout_sha256(layout: str) -> str | None:
    """SHA-256 of the layout file ``layout`` names; None for a built-in or procedural layout."""
    file = layout_file(layout)
    return None if file is None else sha256_of(file, lambda message: ConfigError("layout", message))


def layout_tag(layout: str, sha256: str | None = None) -> str:
    """The layout's part of an evaluation's file name, another for every other layout: a built-in
    name as it is, ``random:S`` as ``randomS``, ``random5:S`` as ``random5-S``, a file as its stem
    and the first 12 hex digits of its content's SHA-256 (``sha256``), e.g. ``lab-3f9a0c2b71de``."""
    seeded = random_seed(layout)
    if seeded is not None:
        kind, seed = seeded
        return f"random{seed}" if kind == "random" else f"{kind}-{seed}"
    return f"{Path(layout).stem}-{sha256[:12]}" if sha256 else Path(layout).stem.replace(":", "")


def evaluation_path(run_dir: Path, res: dict) -> Path:
    """Where ``write_evaluation`` puts ``res``: RUN_DIR/eval-LAYOUT[xN]-DYNAMICS[-TASK][-TSTEPS][-sSEED][-rR][-best]
    [-filter-aA-iN].json, LAYOUT as ``layout_tag`` writes it, TSTEPS an episode limit asked for,
    SEED another ``--seed`` than 0 (other episodes: another evaluation), R a forbidden range asked for
    (``rinf``: none)."""
    n = len(res["per_layout"])  # random:0 over 3 layouts is another evaluation than random:0 alone
    tag = f"{layout_tag(res['layout'], res.get('layout_sha256'))}{f'x{n}' if n > 1 else ''}-{res['dynamics']}"
    if res.get("task_given"):
        tag += f"-{task_tag(res['task'])}"
    if res.get("max_steps_given"):  # another episode limit than the run's: another evaluation
        tag += f"-T{res['max_steps']}"
    if res.get("seed", 0) != 0:
        tag += f"-s{res['seed']}"
    if res.get("forbidden_range_given"):  # what the generalist sees of a forbidden area: another evaluation
        tag += f"-r{number_tag(res['forbidden_range'] if res['forbidden_range'] is not None else float('inf'))}"
    if str(res.get("policy", "")).startswith("best"):  # a validated run's kept policy
        tag += "-best"
    if res["runtime_filter"]:
        tag += f"-filter-a{number_tag(res['filter_alpha'])}-i{res['filter_iters']}"
    return Path(run_dir) / f"eval-{tag}.json"


def write_evaluation(run_dir: Path, res: dict) -> Path:
    """Write ``evaluate_run``'s result into the run directory (``evaluation_path``); returns the path.
    Raises NaNError, leaving any earlier file as it was, when a mean rate is not finite."""
    path = evaluation_path(run_dir, res)
    means = [res[k] for k in ("safety_rate", "completion_rate", "mean_return", "mean_distance")]
    if not all(np.isfinite(means)):  # never replace an earlier result with a broken one
        raise NaNError(f"{run_dir}: the evaluation gave non-finite rates {means}; {path.name} left as it was")
    atomic_write_json(path, res)
    return path
