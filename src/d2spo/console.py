"""What the command line shows, apart from training progress (``d2spo.progress``): the tables of
``d2spo eval`` and ``d2spo certify``, and errors and warnings as single lines on stderr.

The library (``d2spo.evaluate``, ``d2spo.certify``, ...) returns data; only this module, the CLI
and ``d2spo.progress`` print.
"""

from __future__ import annotations

import re
import sys
import warnings
from importlib import metadata
from pathlib import Path

from rich.console import Console
from rich.table import Table

from d2spo import __version__
from d2spo.errors import D2SPOWarning


def error(msg: str) -> None:
    """One ``d2spo: error:`` line on stderr."""
    print(f"d2spo: error: {msg}", file=sys.stderr)


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` for the CLI: a D2SPOWarning (RunDirWarning, TaskWarning) is one line on stderr."""
    if issubclass(category, D2SPOWarning):
        print(f"d2spo: warning: {message}", file=sys.stderr)
    elif str(message).startswith(_CACHE_READ_ERROR):  # JAX's line when a cache entry cannot be read
        detail = str(message)[len(_CACHE_READ_ERROR):].strip()
        what = ("the compilation cache could not be used" if _CACHE_SETUP.search(detail)
                else "a damaged compilation cache entry was ignored")  # a missing package is not damage
        print(f"d2spo: warning: {what} and the program compiled afresh ({detail})", file=sys.stderr)
    else:
        _PLAIN_SHOWWARNING(message, category, filename, lineno, file, line)


_PLAIN_SHOWWARNING = warnings.showwarning
_CACHE_READ_ERROR = "Error reading persistent compilation cache entry for"
_CACHE_SETUP = re.compile(r"[Pp]lease install|No module named")

_BOX = re.compile(r"[╭╮╰╯│─]+")
_CONFIG_ERROR = re.compile(r"^Error parsing [^-\s]\S*: ")
_MISPLACED = "Unrecognized or misplaced options:"
_APPLIED = re.compile(r" \(applied to ([^()]*)\)$")


def tyro_error_line(text: str, args: list[str] = ()) -> str:
    """Condense tyro's boxed error message into one line. Its suggestions for a misspelled flag are
    kept ("did you mean --episodes?"), only those of the subcommand in ``args`` when it names one."""
    # With a terminal (or UTF-8) tyro draws a box; otherwise a title line underlined with dashes.
    lines = [_BOX.sub(" ", ln).strip() for ln in text.splitlines() if ln.strip()]
    title = lines[0] if lines else ""
    body: list[str] = []
    similar: dict[str, dict[str, list[str]]] = {}  # misspelled flag ("" = unnamed) -> flag -> subcommands
    section: dict[str, list[str]] | None = None
    flag = ""
    for stripped in lines[1:]:
        if set(stripped) <= set("-+ "):  # a rule (empty: a rule of box characters)
            if body and section is None:
                section = {}  # past the first block: only suggestions are read from here on
            continue
        m = re.match(r"(?:Perhaps you meant|Arguments similar to (\S+)):$", stripped)
        if m:
            section = similar.setdefault(m.group(1) or "", {})
        elif section is not None and stripped.startswith("-"):
            flag = stripped.split()[0]
            section.setdefault(flag, [])
        elif section is not None and flag in section and re.fullmatch(r"in .+ --help", stripped):
            section[flag].append(stripped[3:-7])
        elif section is None:
            body.append(stripped)
    # A flag of another subcommand: tyro lists it as "misplaced", each word with "(applied to d2spo
    # env check)"; said as for any unknown flag ("Unrecognized options: --label-mode, step")
    # (tyro's note under them, "Arguments are applied to ...", left out)
    misplaced = [_APPLIED.sub("", b) for b in body[1:] if _APPLIED.search(b)] if body[:1] == [_MISPLACED] else []
    subcommand = "this command"
    if misplaced:
        if applied := _APPLIED.search(body[1]):
            subcommand = applied.group(1)
        body = [f"Unrecognized options: {', '.join(misplaced)}"]
    msg = " ".join(body) or "invalid command line"
    if _CONFIG_ERROR.match(msg):  # a config dataclass refused a value: its own message names the field
        return _CONFIG_ERROR.sub("", msg)
    command = " ".join(["d2spo", *[a for a in args if not a.startswith("-")]])
    hints, elsewhere = [], []
    for typo, flags in similar.items():
        ok = [f for f, where in flags.items() if not where or any(command.startswith(w) for w in where)]
        if ok:
            hints.append(" or ".join(ok[:3]) + (f" for {typo}" if typo else ""))
        elsewhere += [f"{f} is a flag of {_listed(where)}, not of {subcommand}" for f, where in flags.items()
                      if f in misplaced and where and f not in ok]
    if hints:
        msg += f" (did you mean {'; '.join(hints)}?)"
    if elsewhere:
        msg += f" ({'; '.join(elsewhere)})"
    return f"{title}: {msg}" if title and not msg.startswith(title) else msg


def _listed(words: list[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return " and ".join([", ".join(words[:-1]), words[-1]] if len(words) > 1 else words)


def as_typed(msg: str, args: list[str] = ()) -> str:
    """A ConfigError's line ("td3.batch_size: must be ...") naming the flag as the user typed it
    ("--td3.batch-size: must be ..."), when ``args`` holds that flag; else unchanged (a value from
    a config file or a run's config.json keeps its field's name). A section the command line
    flattens ("env.reward.r_goal" is ``--r-goal``) is matched by the field's path's shortest tail."""
    field, sep, rest = msg.partition(": ")
    if not sep or not re.fullmatch(r"[a-z0-9_.]+", field):
        return msg
    parts = field.split(".")
    for k in range(len(parts)):  # the whole path first, then without its leading sections
        head = ".".join(parts[k:-1])
        for stem in ("", "no_"):
            flag = f"--{head}{'.' if head else ''}{stem}{parts[-1]}".replace("_", "-")
            if any(a == flag or a.startswith(flag + "=") for a in args):
                return f"{flag}: {rest}"
    # a section nested in a learner's (``--td3-lag.td3.actor-lr`` raises as ``td3.actor_lr``): the typed
    # flag whose path ends with the field's
    tail = "." + field.replace("_", "-")
    typed = [a.split("=", 1)[0] for a in args if a.startswith("--") and a.split("=", 1)[0].endswith(tail)]
    return f"{typed[0]}: {rest}" if len(typed) == 1 else msg


def flag_of_value(value: str, args: list[str] = ()) -> str | None:
    """The flag ``value`` was typed after ("--task" in ``--task 'F (A1'`` or ``--task='F (A1'``, also as
    the second value of a list flag), or None when the command line does not hold it (a tasks file's)."""
    flag = None
    for a in args:
        if a.startswith("--"):
            flag, eq, typed = a.partition("=")
            if eq and typed == value:
                return flag
        elif a == value:
            return flag
    return None


# ------------------------------------------------------------------------------------ d2spo eval
def forbidden_note(res: dict) -> str:
    """What an evaluation's generalist saw of a forbidden area, for its titles: within R m (asked with
    --forbidden-range R, as trained, or the robot's lidar range, ``zero_shot.seen_forbidden_range``),
    always (``--forbidden-range inf`` asked), else nothing (a specialist, or an evaluation made before
    2026-12-03 of a generalist as trained)."""
    if res.get("forbidden_range") is not None:  # a generalist seeing a forbidden area only near it
        return f", forbidden area seen within {res['forbidden_range']:g} m"
    return ", forbidden area always seen" if res.get("forbidden_range_given") else ""


def print_evaluation(res: dict, path: Path, filter_asked: bool | None) -> None:
    """``d2spo.evaluate.evaluate_run``'s result as a table (a row per layout when there are several),
    then where it was written. ``filter_asked``: the --runtime-filter flag (None: not given)."""
    filt = ""
    if res["runtime_filter"] is not None:
        filt = ", runtime filter " + ("on" if res["runtime_filter"] else "off")
        if res["runtime_filter"] and filter_asked is None:
            why = "a generalist's default" if res.get("generalist") else "not the training layout/dynamics"
            filt += f" ({why}; --runtime-filter False for π_Ω alone)"
    task = f", task {res['task']!r} (zero-shot)" if res.get("task_given") else ""
    if not task and res.get("generalist"):  # its training mixture's task: say which one ran
        task = f", task {res['task']!r}"
    which = f", {res['policy']} policy" if str(res.get("policy", "")).startswith("best") else ""
    task += forbidden_note(res)
    # the limit always: under other dynamics (--dt, --v-max, a file) the default follows the evaluated
    # robot's speed, as training's does, and differs from the trained one
    limit = "" if res.get("max_steps") is None else (
        f" of {'up to ' if len(res['per_layout']) > 1 and not res.get('max_steps_given') else ''}{res['max_steps']} steps")
    t = Table(title=f"{res['run']}{which} on {res['layout']} / {res['dynamics']} ({res['episodes']} episodes{limit}{filt}{task})")
    recurrence = "accepting_visits_per_episode" in res  # a patrol completes nothing: its visits instead
    score = "visits / optimum" if recurrence else "completed"
    for name in ("layout", "safe", score, "mean return", "distance driven"):
        t.add_column(name, justify="left" if name == "layout" else "right")

    def visits(r: dict) -> str:
        best, frac = r.get("route_optimal_visits"), r.get("visit_fraction")
        of = f" of {best}" if best is not None else ""
        kept = r.get("route_optimal_visits_margin")
        margin = "" if kept is None or kept == best else f"; {kept} keeping {r['margin']:g} m"
        return f"{r['accepting_visits_per_episode']:.2f}{of}" + ("" if frac is None else f" ({100 * frac:.1f}%{margin})")

    def row(name: str, r: dict, **style) -> None:  # a layout file by its name: the title gives its path
        name = Path(name).name if name.endswith(".json") else name
        t.add_row(name, f"{100 * r['safety_rate']:.2f}%", visits(r) if recurrence else f"{100 * r['completion_rate']:.2f}%",
                  f"{r['mean_return']:.2f}", f"{r['mean_distance']:.2f} m", **style)

    per = res["per_layout"]
    if len(per) > 1:  # which layouts fail matters more than the mean
        for r in per:
            row(r["layout"], r, style="red" if r["safety_rate"] < 1.0 else None)
        row(f"all {len(per)}", res, end_section=False, style="bold")
    else:
        counts = {k: per[0][k] for k in ("route_optimal_visits_margin", "margin") if k in per[0]}
        row(per[0]["layout"], {**res, "route_optimal_visits": per[0].get("route_optimal_visits"), **counts})
    Console().print(t)
    if res.get("rejection_rate"):  # not unsafe, not out of time: what the task forbids was entered
        print(f"rejected by the task (what it forbids entered, e.g. a 'never' part broken): "
              f"{100 * res['rejection_rate']:.2f}% of episodes")
    if recurrence:  # a Büchi task: scored by its accepting visits too
        optimum = "" if res.get("visit_fraction") is None else f" ({100 * res['visit_fraction']:.1f}% of the route-optimal count)"
        print(f"accepting visits per episode: {res['accepting_visits_per_episode']:.2f}{optimum}")
        closed = [r["layout"] for r in per if r.get("route_optimal_visits_margin") == 0 and r.get("route_optimal_visits")]
        if closed:  # as training's barrier-margin warning: a hint where to look, not a bound
            print(f"every route to a visit passes closer than the barrier's margin ({per[0]['margin']:g} m), where "
                  f"the barrier may hold the robot back, on: {', '.join(closed)}")
    print(f"wrote {path}")


# --------------------------------------------------------------------------------- d2spo certify
def print_repair_round(console, r: dict, eval_episodes: int) -> None:
    """One line per ``d2spo certify --repair`` round, and the closing before/after evaluation."""
    if "round" not in r:
        b, a = r["eval_before"], r["eval_after"]
        console.print(f"eval ({eval_episodes} episodes): safety {b['safety_rate']:.3f} → "
                      f"{a['safety_rate']:.3f}, completion {b['completion_rate']:.3f} → "
                      f"{a['completion_rate']:.3f}" + ("; worse: the original state is kept"
                                                        if r["reverted"] else ""))
        return
    console.print(f"round {r['round']}: certified ℒ {100 * r['certified_L']:.2f}%, "
                  f"D {100 * r['certified_D']:.2f}%, violated grid points: "
                  f"{r['grid_L_violated']} (Prop. 1), {r['grid_D_violated']} (Prop. 2, explored)"
                  + (f"; added {r['added_L']} + {r['added_D']} counterexamples" if "added_L" in r else ""))


def print_certify(console, s: dict) -> None:
    """``d2spo.certify.certify_run``'s summary: a table per net, the model residual, counterexamples."""
    cpu = f", {s['cpu_seconds']:.0f} s CPU" if "cpu_seconds" in s else ""
    policy = f", policy {s['policy']}" if s.get("policy") else ""
    t = Table(title=f"{s['run']}: Propositions 1-2{policy} ({s['seconds']:.0f} s{cpu})")
    for name in ("net", "proposition", "points", "certified", "not certified", "violated", "worst margin", "worst value"):
        t.add_column(name, justify="left" if name in ("net", "proposition") else "right")
    rows = (("X_L (ℒ)", "1: h < 0", "max_h", "h"), ("grid: ring + contact", "1: h < 0", "max_h", "h"),
            ("P_exp (D, explored)", "2: e ≥ 0", "min_e", "e"), ("grid: explored cells", "2: e ≥ 0", "min_e", "e"),
            ("grid: all free (beyond D)", "2: e ≥ 0", "min_e", "e"))
    # a grid with no violated point whose search found one between its points: flagged on its row (the
    # search's line below says where), not shown as a clean 100%
    found = {k: any(c["counterexample"] for c in s.get("counterexamples", {}).get(k, [])) for k in ("L", "D")}
    between = {"grid_L": found["L"], "grid_D": found["D"]}
    for (label, prop, worst, sym), key in zip(rows, ("X_L", "grid_L", "P_exp", "grid_D", "grid_free")):
        if key not in s["nets"]:
            continue
        n = s["nets"][key]
        if not n["points"]:
            t.add_row(label, prop, "0", "", "", "", "", "")
            continue
        flagged = between.get(key, False) and n["violated"] == 0
        t.add_row(label + (" (a counterexample between its points: below)" if flagged else ""), prop, str(n["points"]),
                  f"{100 * n['certified']:.2f}%", f"{100 * n['not_certified']:.2f}%",
                  f"{100 * n['violated']:.2f}%", f"{n['worst_margin']:.3g}", f"{sym} = {n[worst]:.3g}",
                  style="red" if n["violated"] > 0 else ("yellow" if flagged else None))
    console.print(t)
    r = s["residual"]
    console.print(f"model residual on {r['transitions']} held-out transitions: |Δh| ≤ ρ_h = {r['rho_h']:.4g} "
                  f"(quantile {r['quantile']:g}; features: median {r['features_m']['p50']:.3g} m, "
                  f"max {r['features_m']['max']:.3g} m)")
    console.print("Proven from the weights: h < 0 on each certified ball of ℒ; e ≥ 0 on each certified ball of D "
                  "for the nominal model's next state, within ρ_h. Measured, not proven: ρ_h. Balls are ℓ∞ in "
                  "feature space; nothing is proven between grid poses (docs/certify.md).")
    for key, sym in (("L", "h"), ("D", "e")):
        bad = [c for c in s["counterexamples"][key] if c["counterexample"]]
        if bad:
            c = bad[0]
            console.print(f"counterexample ({'ℒ' if key == 'L' else 'D'}): pose {c['pose']} with {sym} = {c[sym]:.3g}"
                          f" ({len(bad)} of the worst {len(s['counterexamples'][key])} found)")
        else:
            console.print(f"gradient search in {'ℒ' if key == 'L' else 'D'}: no counterexample found")


def version() -> str:
    """The installed d2spo's version (the package metadata; the source tree's when run from it)."""
    try:
        return metadata.version("d2spo")
    except metadata.PackageNotFoundError:
        return __version__
