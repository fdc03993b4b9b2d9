"""Ctrl-C on the `d2spo` command: one line, exit status 130 from the interrupt itself (not the
watchdog's grace), the run directory left as a run that can be resumed or started again (issue #35:
it died by SIGSEGV 25-37 s later)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from d2spo.runio import run_holder

# The `d2spo` command (its entry point: cli.main) with the watchdog's grace an hour: an exit 130 within
# the test's minute is the KeyboardInterrupt ending the command, never the watchdog (interrupts._raise).
_COMMAND_WITHOUT_WATCHDOG = ("import sys\nfrom d2spo import cli, interrupts\ninterrupts.GRACE = 3600.0\n"
                             "sys.argv[0] = 'd2spo'\nsys.exit(cli.main())\n")


@pytest.mark.skipif(os.name != "posix", reason="needs SIGINT")
def test_ctrl_c_while_compiling_exits_at_once_with_one_line(tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "D2SPO_COMPILE_CACHE": "off"}  # compiling, whatever the cache holds
    proc = subprocess.Popen([sys.executable, "-c", _COMMAND_WITHOUT_WATCHDOG, "train", "--task", "phi1", "--layout",
                             "paper", "--episodes", "8", "--num-envs", "2", "--out", str(out), "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not (out / "config.json").exists():  # the run directory is prepared: compilation starts
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.1)
    time.sleep(2.0)
    proc.send_signal(signal.SIGINT)
    try:  # not a speed threshold: the watchdog (the one other way to 130) would take an hour
        stdout, stderr = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"the interrupt did not end the command: {proc.communicate()[1][-2000:]}")
    assert proc.returncode == 130, (proc.returncode, stderr[-2000:])
    assert [ln for ln in stderr.splitlines() if ln.strip()] == ["d2spo: error: interrupted"]
    assert run_holder(out) is None  # the lock is free
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]


def test_an_interrupt_swallowed_on_its_way_still_ends_the_command():
    """The `d2spo` command's SIGINT handler raises KeyboardInterrupt and, should that be swallowed
    (Python ignores exceptions raised in garbage-collection callbacks), exits 130 with one line."""
    code = ("import os, signal, time\nfrom d2spo import interrupts\ninterrupts.GRACE = 0.5\n"
            "signal.signal(signal.SIGINT, interrupts.interrupted)\n"
            "try:\n    os.kill(os.getpid(), signal.SIGINT)\n    time.sleep(5)\nexcept KeyboardInterrupt:\n    pass\n"
            "time.sleep(30)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130 and proc.stderr.strip().splitlines() == ["d2spo: error: interrupted"], proc.stderr


def test_an_interrupt_python_cannot_raise_ends_the_command_at_once():
    """A KeyboardInterrupt raised where Python can only report it ("Exception ignored in ...": a
    finaliser, XLA's garbage-collection callback) ends the `d2spo` command at once with 130 and
    its one line (``interrupts.leave_if_swallowed``), not after the watchdog's grace."""
    code = ("import sys, time\nfrom d2spo import interrupts\ninterrupts.GRACE = 60.0\n"
            "sys.unraisablehook = interrupts.leave_if_swallowed\n"
            "class Held:\n    def __del__(self):\n        raise KeyboardInterrupt\n"
            "Held()\nprint('carried on', flush=True)\n")
    # at once: the statement after the swallowed interrupt never runs (no clock: GRACE is a minute)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130 and proc.stderr.strip().splitlines() == ["d2spo: error: interrupted"], proc.stderr
    assert proc.stdout == "", proc.stdout


@pytest.mark.skipif(os.name != "posix", reason="needs SIGTERM")
def test_sigterm_ends_the_command_with_one_line_and_143_and_a_run_with_the_resume_hint(tmp_path):
    """SIGTERM (`timeout`, a batch scheduler's stop) ended the command silently by the signal's
    default action. Now it ends as Ctrl-C does: one line, "terminated", exit 143 (128 + 15), and a
    training with a checkpoint gets the hint to resume. The command's own handler, installed by
    ``cli.main()``, in a child process whose command sends itself the signal mid-run."""
    code = ("import os, signal, sys, time\nfrom d2spo import cli, progress\n"
            "class Cmd:\n    def run(self):\n        os.kill(os.getpid(), signal.SIGTERM)\n        time.sleep(20)\n"
            "cli.parse = lambda args: Cmd()\nsys.exit(cli.main())\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143 and proc.stderr.strip().splitlines() == ["d2spo: error: terminated"], proc.stderr
    # a training stopped after its first checkpoint: the resume hint, as for Ctrl-C
    run = tmp_path / "run"
    code = ("import os, signal, sys\nfrom d2spo import cli, progress\n"
            "progress.has_checkpoint = lambda out: True\n"
            "def stopped(*a, **kw):\n    os.kill(os.getpid(), signal.SIGTERM)\n    import time; time.sleep(20)\n"
            "progress.train = stopped\n"
            f"sys.argv = ['d2spo', 'train', '--task', 'relaxed', '--layout', 'relaxed', '--out', {str(run)!r}, "
            "'--no-progress']\nsys.exit(cli.main())\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines() == [f"d2spo: error: terminated; `d2spo train --resume {run}` continues "
                                                "from its last checkpoint"], proc.stderr


@pytest.mark.skipif(os.name != "posix", reason="needs SIGINT")
def test_ctrl_c_after_the_command_finished_leaves_with_its_status_and_no_line():
    """A Ctrl-C that lands after the command's work is done (a short training that ended just
    before it) died of the signal in interpreter teardown: exit -2, stderr empty (seen in the fault
    battery). Now the command leaves at once with the status it finished with, saying nothing."""
    code = ("import os, signal, sys, time\nfrom d2spo import cli\n"
            "class Cmd:\n    def run(self):\n        return 0\n"
            "cli.parse = lambda args: Cmd()\nstatus = cli.main()\n"
            "os.kill(os.getpid(), signal.SIGINT)\ntime.sleep(20)\nprint('teardown ran on', flush=True)\n"
            "sys.exit(status)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert (proc.returncode, proc.stderr, proc.stdout) == (0, "", "")
