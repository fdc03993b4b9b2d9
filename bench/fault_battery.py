"""Issue #35's fault battery, re-run as a hostile user would: the installed `d2spo` command (and
`python -c` for the Gymnasium cases), each case in its own temporary directory, each command under a
wall-clock limit in a session of its own (so that a hang is killed with all its children).

    python bench/fault_battery.py [--out battery.md] [--only 7 8] [--keep]

A case PASSes when every command it runs ends in the exit status expected, with exactly one
non-empty line on stderr where a refusal is expected, no 'Traceback' on stderr, within its limit,
and the case's own checks hold (files untouched, names distinct, ...). Prints one table row per
command (case, command, expected, exit status, stderr lines, traceback, hung, verdict) and writes
the table as markdown to --out. Exit status 1 if any case FAILs.

Trainings are tiny (tlgrl on `relaxed`, the shapes of tests/_run_faults.py), so that the XLA
compile cache (~/.cache/d2spo, or $D2SPO_CACHE_DIR) serves them after the first run. Case 2 (a
`reproduce` killed between the two summaries of a vmapped seed group) has a window of milliseconds
that no outside kill can hit reliably: it runs the pytest test that provokes exactly that moment.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import struct
import sys
import tempfile
import time
from pathlib import Path

from fault_battery_harness import (
    BASE_RUNS,
    D2SPO,
    PY,
    REPO,
    Case,
    d2spo,
    deep_json,
    finish,
    finished_run,
    kill_group,
    last_line,
    markdown,
    python,
    run,
    start,
    tiny,
    wait_for,
    write_layout,
)


# ------------------------------------------------------------------------------------ the cases
def case_01_ctrl_c_while_compiling(c: Case, quick: bool) -> None:
    """Ctrl-C (SIGINT to the process group, 0.5 s after config.json appears) while `train` compiles
    (cache off): exit 130 within 2 s of the signal with one line; the process group gone 40 s later
    (it once died by SIGSEGV 25-37 s after); no temporary files, the lock free: `--resume` then
    finishes with exit 0."""
    out = c.tmp / "run"
    argv = [str(D2SPO), "train", *tiny(), "--out", str(out)]
    t0 = time.monotonic()
    proc = start(argv, c.tmp, {"D2SPO_COMPILE_CACHE": "off"}, sigint_default=True)
    if not wait_for(out / "config.json", proc, 120):
        c.add(c.show(argv), "exit 130 in 2 s", finish(proc, argv, t0, 1), ["config.json never appeared"])
        return
    time.sleep(0.5)  # compiling: the 20 episodes end 4-5 s after config.json with the cache off (F26)
    ended_before = proc.poll() is not None or (out / "summary.json").exists()
    sent = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    ran = finish(proc, argv, t0, (sent - t0) + 30)
    after = time.monotonic() - sent
    problems = [] if after < 2.0 else [f"exited {after:.1f} s after SIGINT"]
    if ended_before:  # the signal came too late to test a compile (the case's premise, not the CLI)
        problems.append("the training had already finished when the signal was sent")
    time.sleep(5 if quick else 40)
    try:
        os.killpg(proc.pid, 0)
        problems.append("processes of its group still alive 40 s later")
    except ProcessLookupError:
        pass
    if ran.rc == -signal.SIGSEGV:
        problems.append("SIGSEGV")
    tmp_files = [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    if tmp_files:
        problems.append(f"temporary files left: {tmp_files}")
    c.check(ran, 130, extra=problems, must_say="interrupted", expected="exit 130 in 2 s, one line, gone 40 s later")
    c.check(d2spo("train", "--resume", str(out), "--no-progress", cwd=c.tmp, timeout=300), 0)


def case_02_reproduce_killed_between_summaries(c: Case, quick: bool) -> None:
    """`reproduce` killed after one seed of a vmapped group wrote summary.json, before the group's
    first checkpoint; then rerun: exit 0, the other seed not wiped, tables as an uninterrupted
    run's. The kill lands in a window of milliseconds, so this runs the pytest test that raises
    KeyboardInterrupt at exactly that moment (tests/test_fault_battery.py)."""
    test = "tests/test_fault_battery.py::test_a_group_killed_between_its_seeds_summaries_before_any_checkpoint_resumes"
    ran = run([str(PY), "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly", "-n0", test],
              REPO, timeout=600)
    if ran.rc == 4 or "unrecognized arguments: -n0" in ran.stderr:  # no xdist
        ran = run([str(PY), "-m", "pytest", "-q", "-p", "no:cacheprovider", test], REPO, timeout=600)
    c.check(ran, 0, one_line=False, expected="pytest passes (rerun exit 0, seed kept)")


def case_03_layout_file_edited(c: Case, quick: bool) -> None:
    """A run on a layout file killed (SIGKILL) after its first checkpoint, the file edited, then
    `--resume`: refused in one line, exit 2. `eval` of the run on its training layout: refused too
    (docs/runs.md), naming `--layout`; with `--layout lab.json` it evaluates the file as it is."""
    lab = write_layout(c.tmp / "lab.json")
    out = c.tmp / "run"
    argv = [str(D2SPO), "train", *tiny(episodes=100_000, layout=str(lab)), "--out", str(out)]
    t0 = time.monotonic()
    proc = start(argv, c.tmp)
    seen = wait_for(out / "checkpoint.json", proc, 300)
    kill_group(proc)
    ran = finish(proc, argv, t0, 10)
    c.add(c.show(argv) + " ; kill -9", "killed after a checkpoint", ran,
          [] if seen else [f"no checkpoint before the kill: {last_line(ran)}"])
    if not seen:
        return
    write_layout(lab, radius=0.4)
    c.check(d2spo("train", "--resume", str(out), "--no-progress", cwd=c.tmp), 2, must_say="changed", within=30)
    c.check(d2spo("eval", str(out), "--episodes", "2", cwd=c.tmp), 2, must_say="--layout", within=30)
    c.check(d2spo("eval", str(out), "--episodes", "2", "--layout", str(lab), cwd=c.tmp, timeout=300), 0)


def case_04_lock_symlink(c: Case, quick: bool) -> None:
    """A `.lock` symlink planted in a run directory, pointing outside --out (to an existing file, and
    to a missing one): not followed; the target untouched (or not created); one line, exit 2."""
    for exists in (True, False):
        out = c.tmp / f"run-{exists}"
        target = c.tmp / "outside" / f"precious-{exists}.txt"
        target.parent.mkdir(exist_ok=True)
        if exists:
            target.write_text("precious")
        out.mkdir()
        (out / ".lock").symlink_to(target)
        ran = d2spo("train", *tiny(), "--out", str(out), cwd=c.tmp, timeout=120)
        after = target.read_text() if target.exists() else None
        extra = [] if after == ("precious" if exists else None) else [f"target now {after!r}"]
        c.check(ran, 2, extra=extra, must_say="symbolic link",
                expected=f"exit 2, one line, target {'untouched' if exists else 'not created'}")


def case_05_eval_file_names(c: Case, quick: bool) -> None:
    """`eval --layout a/lab.json` and `--layout b/lab.json` (different contents) of a run on `relaxed`
    (two areas, as lab.json), and `random:55` vs `random5:5` of a run on `paper` (four areas, as
    random layouts): each evaluation writes a file of its own name."""
    write_layout(c.tmp / "a" / "lab.json")
    write_layout(c.tmp / "b" / "lab.json", radius=0.4)
    for layouts, trained in ((["a/lab.json", "b/lab.json"], "relaxed"), (["random:55", "random5:5"], "paper")):
        run_dir = finished_run(c.tmp / f"run-{trained}", trained)  # as many areas as the layouts evaluated
        before = set(run_dir.glob("eval-*.json"))
        made = []
        for lay in layouts:
            ran = d2spo("eval", str(run_dir), "--episodes", "2", "--layout", lay, cwd=c.tmp, timeout=300)
            new = sorted(set(run_dir.glob("eval-*.json")) - before - set(made))
            made += new
            c.check(ran, 0, extra=[] if len(new) == 1 else [f"new eval files: {[p.name for p in new]}"],
                    expected="exit 0, a new eval-*.json")
        c.add(f"names: {', '.join(p.name for p in made)}", "two names", None,
              [] if len({p.name for p in made}) == 2 else ["the two evaluations share a file"])


def case_06_resume_with_other_flags(c: Case, quick: bool) -> None:
    """`--resume DIR --episodes 100` and `--resume DIR --out OTHER`: refused in one line, exit 2,
    OTHER not created."""
    run_dir = finished_run(c.tmp / "run")
    c.check(d2spo("train", "--resume", str(run_dir), "--episodes", "100", cwd=c.tmp), 2, within=30)
    other = c.tmp / "other"
    ran = d2spo("train", "--resume", str(run_dir), "--out", str(other), cwd=c.tmp)
    c.check(ran, 2, within=30, extra=["OTHER was created"] if other.exists() else [])


def case_07_one_line_refusals(c: Case, quick: bool) -> None:
    """Inputs that once ended in a traceback: each now one line, exit 2, within 60 s (the huge
    sizes refused before compiling: within 30 s)."""
    t = c.tmp
    deep = deep_json(t / "deep.json")
    digits = t / "digits.json"
    digits.write_text(write_layout(t / "ok.json").read_text().replace('"radius": 0.4', '"radius": ' + "4" * 5000, 1))
    cfg_run = finished_run(t / "deep-config-run")
    deep_json(cfg_run / "config.json")
    (t / "reproduce").mkdir()
    bad_json = {"invalid JSON": b"{not json", "a list": b"[1, 2, 3]", "not UTF-8": b"\xff\xfe\x00{\x80}"}
    cases = [
        ["train", "--task", "true", "--out", "r1"],
        ["train", "--task", "A1 | !A1", "--out", "r2"],
        ["env", "check", "--task", "true"],
        ["train", "--layout", str(deep), "--out", "r3"],
        ["train", "--dynamics", str(deep), "--out", "r4"],
        ["train", "--resume", str(cfg_run), "--no-progress"],
        ["train", "--layout", str(digits), "--out", "r5"],
        ["env", "check", "--layout", str(digits), "--task", "relaxed"],
        ["env", "show", "--out", "x.txt"],
        ["ltl", "phi1", "--layout", "paper", "--plot", "y.docx"],
        ["train", "--td3.buffer-size", "1e11", "--out", "r6"],
        ["train", "--td3.buffer-size", "100000000000", "--out", "r7"],
        ["train", "--td3.hidden", "10000000", "10000000", "--out", "r8"],
    ]
    for args in cases:
        c.check(d2spo(*_no_progress(args), cwd=t), 2, within=30)
    for what, content in bad_json.items():
        d = t / f"reproduce-{what.replace(' ', '-')}"
        d.mkdir()
        (d / "reproduce.json").write_bytes(content)
        ran = d2spo("report", str(d), cwd=t)
        c.check(ran, 2, within=30, expected=f"exit 2, one line ({what})")
    written = [p.name for p in t.iterdir() if p.name in ("x.txt", "y.docx")]
    c.add("no x.txt / y.docx written", "nothing written", None, [f"wrote {written}"] if written else [])


def _no_progress(args: list[str]) -> list[str]:
    return [*args, "--no-progress"] if args[0] == "train" and "--no-progress" not in args else args


def case_08_hangs(c: Case, quick: bool) -> None:
    """Inputs that once hung: a layout /dev/zero, a layout FIFO (nobody writing), 10^8 evaluation
    episodes, 5*10^7 environments: one line, exit 2, each within 60 s."""
    fifo = c.tmp / "fifo.json"
    os.mkfifo(fifo)
    for args in (["train", "--layout", "/dev/zero", "--out", "r1"], ["train", "--layout", str(fifo), "--out", "r2"],
                 ["env", "check", "--layout", str(fifo)],
                 ["train", *tiny(), "--eval-episodes", "100000000", "--out", "r3"],
                 ["train", *tiny(), "--num-envs", "50000000", "--out", "r4"]):
        c.check(d2spo(*_no_progress(args), cwd=c.tmp, timeout=60), 2, within=60)
    run_dir = finished_run(c.tmp / "run")
    c.check(d2spo("eval", str(run_dir), "--episodes", "100000000", cwd=c.tmp, timeout=60), 2, within=60)


_ASYNC = """
import gymnasium as gym
envs = gym.make_vec("d2spo.envs:d2spo/Nav-v0", num_envs=2, vectorization_mode="async"{kw})
obs, _ = envs.reset(seed=0)
obs, r, term, trunc, info = envs.step(envs.action_space.sample())
assert obs.shape[0] == 2 and r.shape == (2,)
envs.close()
print("stepped")
"""


def case_09_async_vector_env(c: Case, quick: bool) -> None:
    """`gymnasium.make_vec("d2spo.envs:d2spo/Nav-v0", num_envs=2, vectorization_mode="async")`:
    steps, or is refused in one line naming the spawn context; never hangs (120 s). With
    `vector_kwargs={"context": "spawn"}`: steps."""
    ran = python(_ASYNC.format(kw=""), c.tmp, timeout=120)
    if ran.rc == 0:
        c.check(ran, 0, extra=[] if "stepped" in ran.stdout else ["did not step"], expected="steps, or one line 'spawn'")
    else:  # a ConfigError out of gymnasium's make_vec is a Python traceback: its last line must name spawn
        last = ran.err_lines[-1] if ran.err_lines else ""
        c.add(c.show(ran.argv[:2]) + " make_vec(async)", "steps, or refused naming spawn", ran,
              ([] if "spawn" in last else [f"refusal does not name spawn: {last[:160]}"])
              + (["hung"] if ran.hung else []))
    ran = python(_ASYNC.format(kw=', vector_kwargs={"context": "spawn"}'), c.tmp, timeout=120)
    c.check(ran, 0, one_line=False, extra=[] if "stepped" in ran.stdout else ["did not step"],
            expected="exit 0, steps")


def _tf_records(path: Path) -> list[bytes]:
    """The records of a TFRecord (event) file; a record cut by the kill ends the list."""
    data, out, i = path.read_bytes(), [], 0
    while i + 12 <= len(data):
        (n,) = struct.unpack("<Q", data[i:i + 8])
        if i + 12 + n + 4 > len(data):
            break
        out.append(data[i + 12:i + 12 + n])
        i += 12 + n + 4
    return out


def case_10_tensorboard_of_a_killed_run(c: Case, quick: bool) -> None:
    """A training SIGKILLed after its second checkpoint: its tb/ event file is not empty and
    parses, holding scalars logged before the kill."""
    out = c.tmp / "run"
    argv = [str(D2SPO), "train", *tiny(episodes=100_000, every=10), "--out", str(out)]
    t0 = time.monotonic()
    proc = start(argv, c.tmp)
    seen = wait_for(out / "checkpoint.prev.json", proc, 300)
    kill_group(proc)
    ran = finish(proc, argv, t0, 10)
    problems = [] if seen else [f"no second checkpoint before the kill: {last_line(ran)}"]
    events = sorted((out / "tb").glob("events.out.tfevents.*")) if (out / "tb").is_dir() else []
    scalars, size = 0, sum(p.stat().st_size for p in events)
    try:
        from tensorboardX.proto.event_pb2 import Event

        for p in events:
            for rec in _tf_records(p):
                scalars += sum(1 for v in Event.FromString(rec).summary.value if v.HasField("simple_value"))
    except Exception as e:  # a file that does not parse
        problems.append(f"event file does not parse: {e!r}")
    if size == 0 or scalars == 0:
        problems.append(f"event files: {len(events)}, {size} bytes, {scalars} scalars")
    c.add(c.show(argv) + " ; kill -9", "tb/ events parse, scalars > 0", ran, problems)
    c.rows[-1].why = "; ".join(x for x in (f"{size} bytes, {scalars} scalars", c.rows[-1].why) if x)


def case_11_ltl_task_name_typo(c: Case, quick: bool) -> None:
    """`d2spo ltl phi3` (a typo of a task name): says, in one clean warning line (no Python source
    line), that phi3 is not a known task; a real task name and a formula print no warning."""
    c.check(d2spo("ltl", "phi3", cwd=c.tmp), (0, 2), one_line=True, must_say="task",
            expected="one line: not a known task")
    for formula in ("phi1", "(!A2 U A1) & F A2"):
        ran = d2spo("ltl", formula, cwd=c.tmp)
        c.check(ran, 0, one_line=False, extra=[f"warned: {last_line(ran)}"] if ran.err_lines else [],
                expected="exit 0, no warning")


def case_12_resume_a_finished_run(c: Case, quick: bool) -> None:
    """`--resume` on a finished run: returns quickly (no compiling to train 0 episodes), exit 0."""
    run_dir = finished_run(c.tmp / "run")
    ran = d2spo("train", "--resume", str(run_dir), "--no-progress", cwd=c.tmp, timeout=120)
    c.check(ran, 0, one_line=False, within=15, expected="exit 0 within 15 s")
    c.rows[-1].why = "; ".join(x for x in (f"{ran.seconds:.1f} s", c.rows[-1].why) if x)


def case_13_readme_certify(c: Case, quick: bool) -> None:
    """The README's certify usage typed literally: `d2spo certify RUN [--repair]` is one line, exit
    2; the README's certify lines are commands that parse (no `[--repair]` to type)."""
    c.check(d2spo("certify", "RUN", "[--repair]", cwd=c.tmp), 2)
    lines = [ln for ln in (REPO / "README.md").read_text().splitlines() if ln.lstrip().startswith("d2spo certify")]
    bad = [ln for ln in lines if "[" in ln.split("#")[0]]
    c.add("README: " + " | ".join(ln.split("#")[0].strip() for ln in lines), "commands to type as they are",
          None, ([f"README still shows {bad}"] if bad else []) + ([] if lines else ["no certify line in README"]))
    finished_run(c.tmp / "runs" / "d2spo-phi1")  # a tlgrl run: certify refuses it in one line
    c.check(d2spo("certify", "runs/d2spo-phi1", cwd=c.tmp), 2)


_MAKE = """
import gymnasium as gym
env = gym.make({id!r}, layout="paper", task="phi1")
obs, _ = env.reset(seed=0)
env.step(env.action_space.sample())
print(env.spec.max_episode_steps)
"""


def case_14_gymnasium_make(c: Case, quick: bool) -> None:
    """`gymnasium.make("d2spo/Nav-v0")` without importing d2spo.envs: Gymnasium 1.x loads no plugin
    entry points, so README.md and docs/env.md give the `"d2spo.envs:d2spo/Nav-v0"` form, which
    must step with spec.max_episode_steps 300 (as must the plain id after `import d2spo.envs`);
    the plain id alone works, or fails with Gymnasium's NamespaceNotFound (no hang)."""
    for env_id, pre in (("d2spo.envs:d2spo/Nav-v0", ""), ("d2spo/Nav-v0", "import d2spo.envs\n"),
                        ("d2spo/Nav-v0", "")):
        ran = python(pre + _MAKE.format(id=env_id), c.tmp, timeout=120)
        steps = ran.stdout.strip().splitlines()[-1:] if ran.stdout.strip() else []
        shown = ("import d2spo.envs; " if pre else "") + f"gym.make({env_id!r})"
        if not pre and env_id == "d2spo/Nav-v0" and ran.rc == 1 and "NamespaceNotFound" in ran.stderr:
            c.add(shown, "works, or NamespaceNotFound (documented)", ran, [])
            c.rows[-1].why = "Gymnasium's NamespaceNotFound: the documented form is d2spo.envs:d2spo/Nav-v0"
            continue
        c.check(ran, 0, one_line=False, extra=[] if steps == ["300"] else [f"max_episode_steps {steps}"],
                expected="exit 0, max_episode_steps 300")
        c.rows[-1].command = shown


CASES = [case_01_ctrl_c_while_compiling, case_02_reproduce_killed_between_summaries, case_03_layout_file_edited,
         case_04_lock_symlink, case_05_eval_file_names, case_06_resume_with_other_flags, case_07_one_line_refusals,
         case_08_hangs, case_09_async_vector_env, case_10_tensorboard_of_a_killed_run, case_11_ltl_task_name_typo,
         case_12_resume_a_finished_run, case_13_readme_certify, case_14_gymnasium_make]


# ------------------------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, help="write the table as markdown here")
    p.add_argument("--only", nargs="*", type=int, help="run only these case numbers")
    p.add_argument("--quick", action="store_true", help="wait 5 s, not 40 s, after the Ctrl-C (case 1)")
    p.add_argument("--keep", action="store_true", help="keep the temporary directories")
    a = p.parse_args(argv)
    if not D2SPO.exists():
        print(f"no d2spo command beside {PY}", file=sys.stderr)
        return 2
    t0, rows = time.monotonic(), []
    for i, fn in enumerate(CASES, 1):
        if a.only and i not in a.only:
            continue
        tmp = Path(tempfile.mkdtemp(prefix=f"battery-{i:02d}-"))
        case = Case(f"{i}. {fn.__name__.split('_', 2)[2].replace('_', ' ')}", tmp)
        t = time.monotonic()
        try:
            fn(case, a.quick)
        except Exception as e:  # the battery's own failure is a FAIL of the case, not a crash
            case.add("(battery)", "runs", None, [f"{type(e).__name__}: {e}"[:300]])
        finally:
            if not a.keep:
                shutil.rmtree(tmp, ignore_errors=True)
        rows += case.rows
        verdict = "FAIL" if any(r.verdict == "FAIL" for r in case.rows) else "PASS"
        print(f"{verdict} {case.name} ({time.monotonic() - t:.0f} s)", file=sys.stderr, flush=True)
    if not a.keep:
        for base in BASE_RUNS.values():
            shutil.rmtree(base.parent, ignore_errors=True)
    text = markdown(rows, time.monotonic() - t0)
    print(text)
    if a.out:
        a.out.write_text(text)
    return 1 if any(r.verdict == "FAIL" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
