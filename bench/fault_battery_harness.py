"""The harness of bench/fault_battery.py (split from it: this module runs commands and records
verdicts, that one holds the cases): each command in a session of its own under a wall-clock limit,
its exit status, stderr lines and traceback checked, one ``Row`` per command, and the small
fixtures the cases share (a finished tiny run, a layout file, a deeply nested JSON)."""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PY = Path(sys.executable)
D2SPO = PY.with_name("d2spo")

TINY = ["--algo", "tlgrl", "--task", "relaxed", "--num-envs", "8", "--chunk-steps", "25", "--window", "50",
        "--eval-episodes", "0", "--max-steps", "150", "--shaping-metric", "geodesic",
        "--td3.hidden", "16", "16", "--td3.batch-size", "32", "--td3.learning-starts", "64",
        "--td3.buffer-size", "4096", "--no-progress"]
"""A training (``tiny`` adds its episodes and layout) that compiles in 4-10 s with the cache off (its
20 episodes ended 4.9 s after config.json appeared, on F26) and runs 20 episodes in well under a
second (cached: ~4 s); 150 steps, so that `relaxed` fits without a warning."""


def tiny(episodes: int = 20, every: int = 10, layout: str = "relaxed") -> list[str]:
    return ["--episodes", str(episodes), "--checkpoint-every", str(every), *TINY, "--layout", layout]


# ------------------------------------------------------------------------------------ running
@dataclasses.dataclass
class Ran:
    """One command, as it ended."""

    argv: list[str]
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    hung: bool

    @property
    def err_lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]

    @property
    def traceback(self) -> bool:
        return "Traceback" in self.stderr or "Traceback" in self.stdout


def kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def start(argv: list[str], cwd: Path, env: dict | None = None, sigint_default: bool = False) -> subprocess.Popen:
    """``argv`` in a session of its own; ``sigint_default``: SIGINT raises KeyboardInterrupt in it
    even where this script was started in the background (which ignores SIGINT in its children)."""
    return subprocess.Popen(argv, cwd=cwd, env={**os.environ, **(env or {})}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True, errors="replace",
                            start_new_session=True,
                            preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) if sigint_default else None)


def finish(proc: subprocess.Popen, argv: list[str], t0: float, timeout: float) -> Ran:
    try:
        out, err = proc.communicate(timeout=max(0.1, timeout - (time.monotonic() - t0)))
        hung = False
    except subprocess.TimeoutExpired:
        kill_group(proc)
        out, err = proc.communicate()
        hung = True
    kill_group(proc)  # whatever it left running
    return Ran(argv, None if hung else proc.returncode, out, err, time.monotonic() - t0, hung)


def run(argv: list[str], cwd: Path, timeout: float = 60, env: dict | None = None) -> Ran:
    t0 = time.monotonic()
    return finish(start(argv, cwd, env), argv, t0, timeout)


def d2spo(*args: str, cwd: Path, timeout: float = 60, env: dict | None = None) -> Ran:
    return run([str(D2SPO), *args], cwd, timeout, env)


def python(code: str, cwd: Path, timeout: float = 120) -> Ran:
    return run([str(PY), "-c", code], cwd, timeout)


def wait_for(path: Path, proc: subprocess.Popen, limit: float) -> bool:
    """Whether ``path`` appears while ``proc`` runs, within ``limit`` seconds."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        if path.exists():
            return True
        if proc.poll() is not None:
            return path.exists()
        time.sleep(0.05)
    return False


# ------------------------------------------------------------------------------------ results
@dataclasses.dataclass
class Row:
    case: str
    command: str
    expected: str
    rc: str
    err_lines: str
    traceback: str
    hung: str
    verdict: str
    why: str = ""


class Case:
    """The rows of one case; ``check`` adds one per command."""

    def __init__(self, name: str, tmp: Path):
        self.name, self.tmp, self.rows = name, tmp, []

    def show(self, argv: list[str]) -> str:
        text = " ".join(shlex.quote(str(a)) for a in argv)
        text = text.replace(str(self.tmp) + "/", "").replace(str(self.tmp), ".").replace(str(D2SPO), "d2spo")
        text = text.replace(str(PY), "python")
        text = text.replace(" ".join(shlex.quote(f) for f in TINY), "TINY")
        return text if len(text) <= 110 else text[:107] + "..."

    def add(self, command: str, expected: str, ran: Ran | None, problems: list[str]) -> bool:
        ok = not problems
        if ok and ran is not None and ran.err_lines:  # a warning, or the refusal: shown as it reads
            problems = [f"stderr: {last_line(ran)}"]
        self.rows.append(Row(self.name, command, expected,
                             "-" if ran is None else ("hung" if ran.rc is None else str(ran.rc)),
                             "-" if ran is None else str(len(ran.err_lines)),
                             "-" if ran is None else ("yes" if ran.traceback else "no"),
                             "-" if ran is None else ("yes" if ran.hung else "no"),
                             "PASS" if ok else "FAIL", "; ".join(problems)))
        return ok

    def check(self, ran: Ran, rc: int | tuple[int, ...], one_line: bool | None = None, within: float | None = None,
              extra: tuple[str, ...] | list[str] = (), expected: str | None = None, must_say: str | None = None) -> bool:
        """``ran`` ended with ``rc`` (one of them), no traceback, not hung, within ``within`` s;
        ``one_line``: exactly one non-empty stderr line (None: the default, rc != 0);
        ``must_say``: a word stderr holds (case-insensitive). ``extra``: the case's own problems."""
        rcs = (rc,) if isinstance(rc, int) else rc
        one_line = rcs != (0,) if one_line is None else one_line
        problems = list(extra)
        if ran.hung:
            problems.append(f"hung: killed after {ran.seconds:.0f} s")
        elif ran.rc not in rcs:
            problems.append(f"exit {ran.rc}, expected {'/'.join(map(str, rcs))}: {last_line(ran)}")
        if ran.traceback:
            problems.append("traceback")
        if one_line and len(ran.err_lines) != 1:
            problems.append(f"{len(ran.err_lines)} stderr lines: {last_line(ran)}")
        if within is not None and ran.seconds > within:
            problems.append(f"took {ran.seconds:.1f} s > {within:.0f} s")
        if must_say and must_say.lower() not in ran.stderr.lower():
            problems.append(f"stderr does not say {must_say!r}: {last_line(ran)}")
        exp = expected or (f"exit {'/'.join(map(str, rcs))}" + (", one line" if one_line else ""))
        return self.add(self.show(ran.argv), exp, ran, problems)


def last_line(ran: Ran) -> str:
    lines = ran.err_lines or [ln for ln in ran.stdout.splitlines() if ln.strip()]
    return lines[-1][:160] if lines else "(nothing)"


BASE_RUNS: dict[str, Path] = {}
"""Per layout, the tiny finished run ``finished_run`` copies (the battery removes them at its end)."""


def finished_run(dest: Path, layout: str = "relaxed") -> Path:
    """A copy at ``dest`` of a tiny finished run on ``layout`` (trained once per battery)."""
    if layout not in BASE_RUNS:
        root = Path(tempfile.mkdtemp(prefix="battery-base-"))
        ran = d2spo("train", *tiny(layout=layout), "--out", str(root / "run"), cwd=root, timeout=300)
        if ran.rc != 0:
            raise RuntimeError(f"the base run did not train: {ran.stderr[-2000:]}")
        BASE_RUNS[layout] = root / "run"
    shutil.copytree(BASE_RUNS[layout], dest)
    return dest


def write_layout(path: Path, radius: float = 0.35) -> Path:
    """A small layout file (5 m arena, two areas); ``radius`` changes its content."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "name": "lab", "arena": [5.0, 5.0], "start": [0.6, 0.6, 0.0],
        "obstacles": [{"center": [2.5, 2.5], "radius": 0.4}],
        "areas": [{"name": "A1", "center": [4.2, 0.9], "radius": radius},
                  {"name": "A2", "center": [0.9, 4.2], "radius": radius}]}, indent=1))
    return path


def deep_json(path: Path, depth: int = 100_000) -> Path:
    path.write_text("[" * depth + "]" * depth)
    return path


def markdown(rows: list[Row], seconds: float) -> str:
    """The battery's table as markdown: one row per command, then the count of FAILs."""
    head = ["case", "command", "expected", "exit", "stderr lines", "traceback", "hung", "verdict", "why / note"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r.case, f"`{r.command}`", r.expected, r.rc, r.err_lines, r.traceback, r.hung, r.verdict, r.why]
        lines.append("| " + " | ".join(str(x).replace("|", "\\|").replace("\n", " ") for x in cells) + " |")
    fails = sum(r.verdict == "FAIL" for r in rows)
    lines.append("")
    lines.append(f"{len(rows)} rows, {fails} FAIL; wall time {seconds:.0f} s; {sys.platform}, d2spo at {D2SPO}")
    return "\n".join(lines) + "\n"
