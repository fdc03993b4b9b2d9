"""`d2spo report OUT`: one markdown page with every table and figure that `d2spo reproduce` wrote."""

from __future__ import annotations

import json
import os
import platform
from datetime import date
from pathlib import Path

import jax

from d2spo.compile_cache import usable_cpus
from d2spo.errors import RunDirError, json_trouble
from d2spo.inputs import read_regular
from d2spo.targets import METHODS

SECTIONS = (
    ("table2", "md", "Table II: ϕ1"),
    ("table3", "md", "Table III: relaxed ϕ1"),
    ("fig2", "png", "Fig. 2: reward curves (mean and a band of ± 1 std over seeds)"),
    ("fig3", "png", "Fig. 3: (a) RL vs TLGRL without obstacles, (b) SL vs D²SPO"),
    ("fig4", "png", "Fig. 4: the learned CBF on the physical layouts (TurtleBot preset), heading 0"),
    ("fig5", "png", "Fig. 5: trajectories of the executed policy during training"),
)


def cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's model name with its family and model numbers where Linux gives them (XLA compiles
    for the CPU it runs on, so the same seed can round differently on another CPU type), else
    ``platform.processor()``."""
    fields: dict[str, str] = {}
    try:
        with open(cpuinfo) as f:
            for line in f:
                key, sep, value = line.partition(":")
                if not sep:
                    if fields:
                        break  # the first processor's block is enough
                    continue
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    name = fields.get("model name") or platform.processor() or "unknown CPU"
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def machine() -> str:
    """The machine in one line: the CPU type, the CPUs this process may use (XLA compiles for those:
    d2spo/compile_cache.py), jax and its device, Python."""
    usable, total = usable_cpus(), os.cpu_count()
    cores = f"{total} CPU cores" if usable == total else f"{usable} of {total} CPU cores usable"
    return (f"{platform.machine()}, {cpu_model()}, {cores}, jax {jax.__version__} on "
            f"{jax.devices()[0].platform}, Python {platform.python_version()}")


def provenance(name: str, how: dict) -> str:
    """One line saying how a section was rendered: the command, seeds and runs finished."""
    methods = f" --methods {' '.join(how['methods'])}" if how.get("methods") else ""
    return (f"*Rendered {how.get('date', '?')} by `d2spo reproduce {name} --seeds {how.get('seeds')} "
            f"--episodes {how.get('episodes')}{methods}`: {how.get('finished', '?')} of {how.get('runs', '?')} "
            f"runs finished{_stale(how)}.*")


def _stale(how: dict) -> str:
    n = how.get("stale", 0)
    return f"; {n} of them trained with other settings than the defaults of the day (`--allow-stale`)" if n else ""


_META_TYPES = {"targets": list, "seeds": int, "episodes": int, "runs": list, "finished": int, "train": bool,
               "backend": str, "methods": list, "stale": dict, "rendered": dict}
"""The fields of reproduce.json the report reads, with their types; the first four are in every
version's file."""


def read_meta(path: Path) -> dict:
    """reproduce.json, as `d2spo reproduce` wrote it; a damaged one (cut short, not UTF-8, not an
    object with the fields of ``_META_TYPES``) is a RunDirError in one line."""
    def damaged(why: str) -> RunDirError:
        return RunDirError(f"{path}: damaged ({why}); `d2spo reproduce ... --no-train --out {path.parent}` "
                           "writes it again")

    try:
        meta = json.loads(read_regular(path, RunDirError))
    except json.JSONDecodeError as e:
        raise damaged(f"not valid JSON: {e.msg} (line {e.lineno})") from None
    except (RecursionError, ValueError) as e:  # not UTF-8, nested too deeply, a number too long to read
        raise damaged(json_trouble(e)) from None
    if not isinstance(meta, dict):
        raise damaged(f"a JSON {_JSON_NAMES.get(type(meta), 'value')}, not an object")
    for i, (key, kind) in enumerate(_META_TYPES.items()):
        if key not in meta and i < 4:
            raise damaged(f"no {key!r}")
        if key in meta and (not isinstance(meta[key], kind) or (kind is int and isinstance(meta[key], bool))):
            raise damaged(f"{key!r} is not a JSON {_JSON_NAMES[kind]}")
    if not all(isinstance(t, str) for t in meta["targets"]):
        raise damaged("'targets' holds something else than names")
    for name, how in meta.get("rendered", {}).items():
        methods = how.get("methods") or [] if isinstance(how, dict) else None
        if not isinstance(methods, list) or not all(isinstance(m, str) for m in methods):
            raise damaged(f"'rendered.{name}' is not an object with a list of methods")
    return meta


_JSON_NAMES = {list: "list", int: "integer", float: "number", bool: "boolean", str: "string", dict: "object",
               type(None): "null"}


def build_report(out: Path) -> Path:
    """Write OUT/report.md from what is in OUT; raises RunDirError if nothing is there."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunDirError(f"{out}: is a file; give the directory `d2spo reproduce --out` wrote")
    if not out.is_dir():
        raise RunDirError(f"{out}: no such directory; run `d2spo reproduce ... --out {out}` first")
    meta_path = out / "reproduce.json"
    if not meta_path.exists() and (out / "config.json").is_file():  # a training's run, not reproduce's OUT
        raise RunDirError(f"{out}: a run directory of `d2spo train`; `d2spo report` reads the folder `d2spo "
                          "reproduce --out OUT` wrote (its tables and figures); for one run, `d2spo eval "
                          f"{out}` and its summary.json")
    meta = read_meta(meta_path) if meta_path.exists() else {}
    parts = ["# d2spo: reproduction report", ""]
    if meta:
        chosen = meta.get("methods")  # a subset of the methods (`--methods cpo d2spo`) is part of the command
        methods = (f" --methods {' '.join(chosen)}" if isinstance(chosen, list) and chosen
                   and chosen != list(METHODS) else "")
        parts += [f"Last command: `d2spo reproduce {' '.join(meta.get('targets', []))} --seeds {meta.get('seeds')} "
                  f"--episodes {meta.get('episodes')}{methods} --out {out}{'' if meta.get('train', True) else ' --no-train'}` "
                  f"(backend {meta.get('backend')}); "
                  f"{meta.get('finished', '?')} of {len(meta.get('runs', []))} runs finished. Report written {date.today().isoformat()} on {machine()}.", ""]
    found = 0
    for name, kind, title in SECTIONS:
        path = out / f"{name}.{kind}"
        if not path.is_file():
            continue
        found += 1
        if kind == "md":
            try:
                parts += [read_regular(path, RunDirError).decode("utf-8").rstrip(), ""]
            except UnicodeDecodeError:
                raise RunDirError(f"{path}: not UTF-8 text; `d2spo reproduce {name} --no-train --out {out}` "
                                  "writes it again") from None
        else:
            parts += [f"### {title}", "", f"![{name}]({path.name})", ""]
        how = meta.get("rendered", {}).get(name)
        if how:
            parts += [provenance(name, how), ""]
    if not found:
        raise RunDirError(f"{out}: holds no tables or figures of `d2spo reproduce` (the paper's tasks and layouts), which "
                          f"`d2spo report` gathers; `d2spo reproduce all --out {out}` writes them. Runs of your own "
                          "`d2spo train` are read from each run's summary.json and episodes.csv (docs/runs.md)")
    report = out / "report.md"
    report.write_text("\n".join(parts))
    return report
