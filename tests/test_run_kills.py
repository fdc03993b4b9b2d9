"""A kill at any moment of a training (inside checkpoint writes too) ends in a byte-identical
resume: the run directory as a kill -9 would leave it at each moment, and a real SIGKILL in a child
process. The moments are drawn at random: set D2SPO_FAULT_SEED to draw others (failures print it)."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import jax
import pytest
from _run_faults import CFG, SEED, Images, assert_same_run, resume_quietly

from d2spo.config import config_to_dict
from d2spo.errors import RunDirWarning
from d2spo.train import train


# ------------------------------------------------------------------------------- kills
def _first_commit(images: Images) -> int:
    return next(i for i, (lab, _) in enumerate(images.taken) if lab == "write checkpoint.json")


KILLS = {
    "mid-append": lambda imgs: lambda i, lab: lab == "append",
    "before-first-checkpoint": lambda imgs: lambda i, lab: i <= _first_commit(imgs),
    "writing-state": lambda imgs: lambda i, lab: i > _first_commit(imgs) and lab.startswith("write checkpoint-"),
    "committing": lambda imgs: lambda i, lab: i > _first_commit(imgs) and lab == "write checkpoint.json",
    "after-commit": lambda imgs: lambda i, lab: lab == "write checkpoint.prev.json" or lab.startswith("delete"),
    "before-summary": lambda imgs: lambda i, lab: lab == "write summary.json",
}


@pytest.mark.parametrize("when", list(KILLS))
def test_killed_at_any_moment_resumes_byte_identical(run_reference, tmp_path, when):
    ref, _, images = run_reference
    rng = random.Random(f"{SEED}-{when}")
    moment, image = images.pick(rng, KILLS[when](images))
    why = f"killed at {moment}, D2SPO_FAULT_SEED={SEED}"
    run = tmp_path / "run"
    shutil.copytree(image, run)
    if not (run / "config.json").is_file():  # killed before it wrote anything: started again in place
        train(CFG, run)
    elif not (run / "checkpoint.json").is_file():
        with pytest.warns(RunDirWarning, match="no checkpoint was written"):
            train(CFG, run, resume=True)
    else:
        resume_quietly(run)
    assert_same_run(run, ref, why)


def test_kill_9_during_a_checkpoint_write_then_resume_is_exact(run_reference, tmp_path):
    """A real SIGKILL in a child process, at a random rename of a checkpoint file."""
    ref, _, images = run_reference
    writes = [lab for lab, _ in images.taken if lab.startswith("write checkpoint")]
    k = random.Random(f"{SEED}-kill9").randrange(1, len(writes))
    run = tmp_path / "run"
    script = f"""
import json, os, signal, sys
from pathlib import Path
import jax
jax.config.update("jax_compilation_cache_dir", {jax.config.jax_compilation_cache_dir!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
from d2spo.config import config_from_dict
from d2spo.train import train
run, n, real = Path(sys.argv[1]), [0], os.replace
def replace(src, dst, *a, **kw):
    if Path(dst).parent == run and Path(dst).name.startswith("checkpoint"):
        n[0] += 1
        if n[0] == {k}:
            os.kill(os.getpid(), signal.SIGKILL)
    return real(src, dst, *a, **kw)
os.replace = replace
train(config_from_dict(json.loads(sys.argv[2])), run)
"""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1] / "src"),
                                                        os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", script, str(run), json.dumps(config_to_dict(CFG))], env=env,
                          check=False, capture_output=True, text=True, timeout=300)
    why = f"SIGKILL at checkpoint write {k} ({writes[k - 1]}), D2SPO_FAULT_SEED={SEED}"
    assert proc.returncode == -signal.SIGKILL, (why, proc.stderr[-2000:])
    assert [p for p in run.iterdir() if p.name.endswith(".tmp")], "the kill left a temporary file"
    assert (run / ".lock").read_text().startswith("pid ") and str(os.getpid()) not in (run / ".lock").read_text()
    if (run / "checkpoint.json").is_file():  # the dead process's lock is taken over
        resume_quietly(run)
    else:
        with pytest.warns(RunDirWarning):
            train(CFG, run, resume=True)
    assert_same_run(run, ref, why)
