"""`d2spo reproduce`: the paper's tables and figures, one command each.

A *target* (table2, table3, fig2 … fig5) is a list of runs (``RunSpec``: learner, task, layout,
preset, seed, episodes) plus a renderer that reads the finished run directories. Runs live in
``OUT/runs/NAME`` with the ordinary run-directory layout (``d2spo.runio``), so a finished run is
reused, an interrupted one resumes from its checkpoint, and any of them can be inspected with
``d2spo eval``. The runs are executed by a backend:

* ``local`` (default): in this process; the seeds of one setting run together as one program,
  ``jax.vmap`` over seeds (``d2spo.train.train_seeds``), or one after another with
  ``--no-vmap-seeds``;
* ``ray``: one Ray task per run on a cluster (``--address``) or a local Ray instance; every task
  writes the same run directory (the output directory must be shared by the workers).

``render`` hands each target's run directories to its renderer, which reads only the directories:
``d2spo.tables`` writes ``OUT/table2.md`` / ``.csv`` etc., ``d2spo.plots`` draws ``OUT/figN.png``;
``d2spo report OUT`` gathers them into one page.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable, Iterable
from datetime import date
from pathlib import Path

from d2spo import compile_cache, tables
from d2spo.config import config_from_dict
from d2spo.config_diff import config_differences
from d2spo.errors import ConfigError, RunInUseError, UserError
from d2spo.progress import train_seeds_with_progress, train_with_progress
from d2spo.run import GROUP_PREFIX, group_dir
from d2spo.runio import atomic_write_json, make_run_dir, read_json, run_holder
from d2spo.targets import METHODS, TABLE_SETTING, TARGETS, RunSpec, expand, is_finished, run_dir, runs_for
from d2spo.train import train_seeds


# ------------------------------------------------------------------------------------ running
def train_one(spec: RunSpec, out: str, progress: bool = False) -> dict:
    """Train (or resume, or reuse) one run; returns its summary. Also the body of a Ray task."""
    d = run_dir(Path(out), spec)
    if not (d / "summary.json").is_file():
        if (d / "config.json").is_file():
            old = read_json(d / "config.json", "the run's config")
            if old.get("episodes") != spec.episodes or old.get("algo") != spec.algo:
                raise UserError(f"{d}: holds a different run (episodes {old.get('episodes')}); "
                                f"use another --out or remove it")
        resume = d if (d / "checkpoint.json").is_file() else None
        if resume is None:
            _discard_unstarted(d)
        rc = train_with_progress(spec.config(), d, resume, progress)
        if rc != 0:
            raise UserError(f"{d}: training failed")
    return read_json(d / "summary.json", "the run's summary")


def stale_runs(out: Path, specs: Iterable[RunSpec]) -> dict[str, list[str]]:
    """Runs in OUT (finished or not) whose config.json differs from the config ``reproduce`` would
    train today, e.g. after a default changed: name -> ``'setting: theirs -> today's'``. Only
    settings that can change the run (``config_diff.effective_config``)."""
    found: dict[str, list[str]] = {}
    for s in specs:
        path = run_dir(out, s) / "config.json"
        if not path.is_file():
            continue
        try:
            old = config_from_dict(read_json(path, "the run's config"))
        except ConfigError as e:
            found[s.name] = [f"unreadable config: {e}"]
            continue
        diffs = config_differences(old, s.config())
        if diffs:
            found[s.name] = diffs
    return found


def _rendered_history(out: Path, targets: list[str], seeds: int, episodes: int, methods: list[str],
                      stale: dict[str, list[str]] | None = None) -> dict:
    """How each table or figure in OUT was last rendered (seeds, episodes, runs finished, date), kept
    across invocations so `d2spo report` can say it per section; earlier entries survive."""
    old: dict = {}
    path = out / "reproduce.json"
    if path.is_file():
        try:
            old = dict(json.loads(path.read_text()).get("rendered", {}))
        except (ValueError, AttributeError):
            old = {}
    for t in targets:
        specs = runs_for(t, seeds, episodes, methods)
        some = t in ("table2", "table3", "fig2") and list(methods) != list(METHODS)
        old[t] = {"seeds": seeds, "episodes": episodes, "methods": list(methods) if some else None,
                  "finished": sum(is_finished(out, s) for s in specs), "runs": len(specs),
                  "stale": sum(s.name in (stale or {}) for s in specs), "date": date.today().isoformat()}
    return old


def _discard_unstarted(*dirs: Path) -> None:
    """Run directories without a checkpoint to resume from are started again from scratch. A finished
    one is kept: another ``reproduce`` on the same OUT may have finished it since this one listed
    what to train. If another process is training any of them (before its first checkpoint), none
    is touched: RunInUseError."""

    unstarted = [Path(d) for d in dirs if Path(d).exists() and not (Path(d) / "summary.json").is_file()]
    for d in unstarted:
        holder = run_holder(d)
        if holder is not None:
            raise RunInUseError(f"{d}: in use by another training ({holder})")
    for d in unstarted:
        shutil.rmtree(d)


def _fresh_or_resumable(out: Path, spec: RunSpec) -> bool:
    """True unless the run has its own checkpoint (it was started alone: it resumes alone)."""
    return not (run_dir(out, spec) / "checkpoint.json").is_file()


def started_groups(out: Path, specs: list[RunSpec]) -> list[list[RunSpec]]:
    """Groups of seeds an earlier call started together (a ``.group-…`` directory in OUT/runs) that
    hold a run of ``specs`` and are not finished: each resumes as the group it was, with all its
    members, so every seed continues the program it started in (a seed's own checkpoint, written
    by the group, would resume it alone, which rounds differently). A group whose members have all
    finished is a leftover of a stop just before its removal, and is removed."""

    runs = Path(out) / "runs"
    mine = {s.name: s for s in specs}
    found = []
    for d in sorted(runs.glob(GROUP_PREFIX + "*")) if runs.is_dir() else []:
        names = d.name[len(GROUP_PREFIX):].split("+")
        template = next((mine[n] for n in names if n in mine), None)
        if template is None:
            continue  # another target's or setting's group: not ours to touch
        members = []
        for n in names:
            seed = n.rpartition("-s")[2]
            member = dataclasses.replace(template, seed=int(seed)) if seed.isdigit() else None
            if member is None or member.name != n:
                break
            members.append(member)
        else:
            if group_dir([run_dir(out, m) for m in members]) != d:
                continue
            if all(is_finished(out, m) for m in members):
                shutil.rmtree(d, ignore_errors=True)
            else:
                found.append(members)
    return found


def train_group(specs: list[RunSpec], out: Path, progress: bool = False) -> list[dict]:
    """Seeds of one (algo, task, layout, …) trained together, ``jax.vmap`` over seeds."""
    outs = [run_dir(out, s) for s in specs]
    group = group_dir(outs)
    if not (group / "checkpoint.json").is_file():
        _discard_unstarted(*outs)
    cfgs = [s.config() for s in specs]
    if progress:
        return train_seeds_with_progress(cfgs, outs, True)
    return train_seeds(cfgs, outs)


def run_local(specs: list[RunSpec], out: Path, progress: bool = True, log: Callable[[str], None] = print,
              vmap_seeds: bool = True) -> None:
    """Train the unfinished runs in this process. With ``vmap_seeds`` the seeds of one setting run
    together as one program (``d2spo.train.train_seeds``); a run that already has a checkpoint of
    its own resumes alone."""
    todo = [s for s in specs if not is_finished(out, s)]
    groups: dict[RunSpec, list[RunSpec]] = {}
    for members in started_groups(out, specs):  # resumed as they were, even with --no-vmap-seeds
        groups[members[0]] = members
    grouped = {m for members in groups.values() for m in members}
    resumed = sum(1 for s in todo if s in grouped or not _fresh_or_resumable(out, s))
    log(f"{len(specs) - len(todo)} of {len(specs)} runs already finished in {out}; training {len(todo)}"
        + (f" ({resumed} resuming from a checkpoint an interrupted call left)" if resumed else ""))
    for s in todo:
        if s in grouped:
            continue
        together = vmap_seeds and _fresh_or_resumable(out, s)
        key = dataclasses.replace(s, seed=-1) if together else s
        groups.setdefault(key, []).append(s)
    busy = 0
    for i, members in enumerate(groups.values(), 1):
        m = members[0]
        seeds = ", ".join(str(x.seed) for x in members)
        log(f"[{i}/{len(groups)}] {m.algo} {m.task} {m.layout}{f' ({m.preset})' if m.preset else ''}, "
            f"seed{'s' if len(members) > 1 else ''} {seeds} ({m.episodes} episodes)")
        if all(is_finished(out, x) for x in members):  # another process on the same OUT finished them
            log("  finished meanwhile (another process on the same OUT): reused")
            continue
        try:
            if len(members) == 1:
                train_one(m, str(out), progress)
            else:
                train_group(members, out, progress)
        except RunInUseError as e:  # another process on the same OUT is training it: leave it to that one
            busy += 1
            log(f"  skipped: {e}")
    if busy:
        log(f"{busy} group{'s' if busy > 1 else ''} skipped, being trained by another process; "
            "once it ends, run the same command again to train what is left and render the rest")


def _train_one_in_worker(spec: RunSpec, out: str, progress: bool = False) -> dict:
    """``train_one`` in a Ray worker process, with the commands' compilation cache (a worker is a
    fresh interpreter: d2spo/compile_cache.py)."""
    compile_cache.enable()
    return train_one(spec, out, progress)


def run_ray(specs: list[RunSpec], out: Path, address: str | None = None, num_cpus: int | None = None,
            log: Callable[[str], None] = print) -> None:
    """One Ray task per unfinished run. ``address=None`` starts a local Ray instance."""
    try:
        import ray
    except ImportError:
        raise UserError("--backend ray needs Ray: pip install 'd2spo[cluster]'") from None
    todo = [s for s in specs if not is_finished(out, s)]
    tasks = f"{len(todo)} Ray task{'s' if len(todo) != 1 else ''}"
    log(f"{len(specs) - len(todo)} of {len(specs)} runs already finished in {out}; {tasks}")
    if not todo:
        return
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                 ignore_reinit_error=True)
    try:
        task = ray.remote(num_cpus=1)(_train_one_in_worker)
        refs = {task.remote(s, str(Path(out).resolve()), False): s for s in todo}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                summary = ray.get(ref)
                log(f"finished {refs[ref].name}: safety {summary['safety_rate']:.4f}, "
                    f"completion {summary['completion_rate']:.4f}")
    finally:
        if started:
            ray.shutdown()


# ------------------------------------------------------------------------- tables and figures
FIG3_PANELS = ((("td3", "tlgrl"), "(a) RL vs TLGRL, open layout"), (("sl", "d2spo"), "(b) SL vs D²SPO, paper layout"))


def runs_by(out: Path, specs: Iterable[RunSpec], label: Callable[[RunSpec], str]) -> dict[str, list[Path]]:
    """The run directories of ``specs`` grouped under ``label(spec)``, in the order of ``specs``."""
    groups: dict[str, list[Path]] = {}
    for s in specs:
        groups.setdefault(label(s), []).append(run_dir(out, s))
    return groups


def render(target: str, out: Path, seeds: int, episodes: int, methods: Iterable[str] = METHODS) -> Path:
    """Write OUT/TARGET.md and .csv (``d2spo.tables``) or OUT/TARGET.png (``d2spo.plots``) from the
    runs in OUT that the target needs (a missing or unfinished run is left out or shown as not run)."""
    out = Path(out)
    specs, path = runs_for(target, seeds, episodes, methods), out / f"{target}.png"
    if target in TABLE_SETTING:
        return tables.write_table(out, target, runs_by(out, specs, lambda s: s.algo), *TABLE_SETTING[target], episodes)
    from d2spo import plots  # matplotlib: imported only to draw a figure

    if target == "fig2":
        return plots.reward_figure(path, [
            (title, runs_by(out, runs_for(t, seeds, episodes, methods), lambda s: tables.METHOD_NAMES.get(s.algo, s.algo)))
            for t, title in (("table2", "(a) ϕ1"), ("table3", "(b) relaxed ϕ1"))])
    if target == "fig3":  # per panel: the two methods on ϕ1, then on ϕ2
        return plots.reward_figure(path, [
            (title, runs_by(out, [s for t in ("phi1", "phi2") for s in specs if s.algo in algos and s.task == t],
                            lambda s: f"{tables.METHOD_NAMES[s.algo]}-{s.task}"))
            for algos, title in FIG3_PANELS])
    if target == "fig4":
        dirs = [run_dir(out, s) for s in specs]
        if not any((d / "checkpoint.json").is_file() for d in dirs):  # h is in the networks, not the files
            kept = [d for d in dirs if (d / "summary.json").is_file()]
            why = (f"its {len(kept)} finished run{'s' * (len(kept) != 1)} in {out / 'runs'} hold no checkpoint "
                   "(published or shared without them)" if kept else f"no run of it in {out / 'runs'} has been trained")
            raise UserError(f"fig4 draws each run's learned barrier h, from its checkpoint: {why}; "
                            "train them (without --no-train), into a new --out for published runs")
        return plots.cbf_figure(path, [(s.layout, d) for s, d in zip(specs, dirs)])
    d = run_dir(out, specs[0])
    if not (d / "checkpoint.json").is_file():
        raise UserError(f"{d}: fig5's run has not been trained")
    return plots.snapshot_figure(path, d)


def reproduce(targets: Iterable[str], out: Path, seeds: int = 3, episodes: int = 20_000, backend: str = "local",
              address: str | None = None, methods: Iterable[str] = METHODS, progress: bool = True,
              log: Callable[[str], None] = print, train: bool = True, vmap_seeds: bool = True,
              allow_stale: bool = False) -> list[Path]:
    """Train what is missing for ``targets`` (unless ``train`` is False) and render them.

    Returns the written files. Tables count the seeds that have finished, so ``train=False``
    renders whatever is there. Runs in OUT trained with other settings than today's (``stale_runs``)
    are refused, so a table never mixes two rewards silently; ``allow_stale`` uses them as they are
    and the report says how many there were."""
    if seeds < 1:
        raise UserError(f"--seeds must be >= 1, got {seeds}")
    if episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {episodes}")
    methods = list(methods)
    if not methods:  # `--methods` with nothing after it: no row to train or draw
        raise UserError(f"--methods names no method; name one or more of {', '.join(METHODS)}, or leave it out for all")
    for m in methods:
        if m not in METHODS:
            raise UserError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    if backend not in ("local", "ray"):  # before anything is written
        raise UserError(f"unknown backend {backend!r}; choose local or ray")
    targets = expand(targets)
    if not targets:
        raise UserError(f"name at least one target: {', '.join(TARGETS)} or all")
    out = Path(out)
    make_run_dir(out)  # a file in the way is one line, exit 2 (as `train --out`)
    specs: list[RunSpec] = []
    for t in targets:
        for s in runs_for(t, seeds, episodes, methods):
            if s not in specs:
                specs.append(s)
    stale = stale_runs(out, specs)
    if stale:
        name, diffs = next(iter(stale.items()))
        more = f" (and {len(diffs) - 1} more settings)" if len(diffs) > 1 else ""
        what = f"{len(stale)} run{'s' if len(stale) > 1 else ''} in {out / 'runs'} {'were' if len(stale) > 1 else 'was'}"
        if not allow_stale:
            raise UserError(f"{what} trained with other settings than today's, e.g. {name}: {diffs[0]}{more}; "
                            f"use a new --out, or --allow-stale to use them as they are")
        log(f"warning: {what} trained with other settings than today's (--allow-stale), e.g. "
            f"{name}: {diffs[0]}{more}")
    if not train:
        log(f"{sum(is_finished(out, s) for s in specs)} of {len(specs)} runs finished in {out}; rendering only")
    elif backend == "local":
        run_local(specs, out, progress, log, vmap_seeds)
    else:
        run_ray(specs, out, address, log=log)
    written = [render(t, out, seeds, episodes, methods) for t in targets]
    meta = {"targets": targets, "seeds": seeds, "finished": sum(is_finished(out, s) for s in specs), "train": train,
            "episodes": episodes, "methods": methods, "backend": backend, "runs": [dataclasses.asdict(s) for s in specs],
            "stale": stale, "rendered": _rendered_history(out, targets, seeds, episodes, methods, stale)}
    atomic_write_json(out / "reproduce.json", meta)
    for p in written:
        log(f"wrote {p}")
    return written
