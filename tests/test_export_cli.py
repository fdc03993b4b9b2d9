"""`d2spo export` on the command line, the example that drives an export, and what the command and
``Policy.load`` refuse: one line and exit status 2, or one ArtefactError. The runtime's own calls
(``act``, ``filter``, ``scan_error``, the automaton): tests/test_deploy_runtime.py."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
from _cli import one_error_line
from _tiny import tiny_cfg, write_run

from d2spo import cli
from d2spo.cli_export import FILTER_NOTE
from d2spo.deploy import Policy
from d2spo.errors import ArtefactError
from d2spo.export import ExportConfig, export_run

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tiny(tiny_export):
    """``_tiny_run`` of ϕ1 on ``paper``: tests/conftest.py's ``tiny_export``, built once per worker."""
    return tiny_export


def _temporary_dirs_here(monkeypatch, tmp_path) -> Path:
    """Point Python's temporary files at a fresh folder of ``tmp_path`` and return it."""
    import tempfile

    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    return temp


def test_the_example_drives_the_export_from_a_gymnasium_loop(tiny, capsys, monkeypatch, tmp_path):
    """From an export, and from a run directory (exported into a temporary directory the example
    removes once the policy is loaded: one was left in /tmp per run before)."""
    temp = _temporary_dirs_here(monkeypatch, tmp_path)
    for path in (tiny[1], tiny[0]):
        monkeypatch.setattr(sys, "argv", ["deploy_gym_loop.py", str(path), "--episodes", "2", "--filter", "on"])
        runpy.run_path(str(ROOT / "examples" / "deploy_gym_loop.py"), run_name="__main__")
        lines = capsys.readouterr().out.splitlines()
        assert len(lines) == 3 and not any("differed" in ln for ln in lines)  # the tracker kept the env's state
        assert json.loads(lines[-1])["episodes"] == 2 and json.loads(lines[-1])["runtime_filter"] == "on"
    assert list(temp.iterdir()) == []


def test_a_new_export_removes_the_files_only_the_one_it_replaces_had(tiny, tmp_path):
    """An earlier export with --onnx left policy.onnx & co.; exporting again without --onnx must not
    leave them beside the new manifest, where a robot stack reading policy.onnx would run the old run."""
    import shutil

    out = tmp_path / "again"
    shutil.copytree(tiny[1], out)
    manifest = json.loads((out / "manifest.json").read_text())
    if not manifest["onnx"]:  # where the onnx package is missing, as an export with --onnx lists them
        manifest["onnx"] = {"policy": {"file": "policy.onnx", "sha256": "0"}, "cbf": {"file": "cbf.onnx", "sha256": "0"}}
        (out / "manifest.json").write_text(json.dumps(manifest))
        for name in ("policy.onnx", "cbf.onnx"):
            (out / name).write_bytes(b"old")
    assert any(f.suffix == ".onnx" for f in out.iterdir())
    (out / "notes.txt").write_text("mine")  # not listed by the export: left alone
    export_run(tiny[0], out, ExportConfig(onnx=False))
    assert sorted(f.name for f in out.iterdir()) == ["manifest.json", "notes.txt", "weights.npz"]


def test_the_example_refuses_a_path_that_is_not_a_policy_in_one_line(tiny, tmp_path, capsys, monkeypatch):
    temp = _temporary_dirs_here(monkeypatch, tmp_path)
    run = tiny[0]
    nope, unwritten = tmp_path / "nope", run / "export"  # unwritten: said "no such run directory" before
    for args, says in [([nope], f"no such export or run directory; `d2spo export RUN --out {nope}`"),
                       ([unwritten], f"the run {run} has no export there: `d2spo export {run} --out {unwritten}`"),
                       ([tiny[1] / "manifest.json"], "is a file"), ([tiny[1], "--episodes", "0"], "--episodes")]:
        monkeypatch.setattr(sys, "argv", ["deploy_gym_loop.py", *map(str, args)])
        with pytest.raises(SystemExit) as e:
            runpy.run_path(str(ROOT / "examples" / "deploy_gym_loop.py"), run_name="__main__")
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and "error:" in err[0] and says in err[0], err
        assert "no such run directory" not in err[0]
    assert list(temp.iterdir()) == []  # the temporary export directory of a failed export is removed too


def test_an_export_given_where_a_run_is_asked_for_is_named_as_an_export(tiny, capsys):
    for command in (["eval", str(tiny[1])], ["export", str(tiny[1]), "--out", str(tiny[1].parent / "x")]):
        assert cli.main(command) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is an exported policy (`d2spo export`), not a run directory" in err[0], err


def test_export_command_and_bad_input(tiny, tmp_path, capsys):
    run = tiny[0]
    assert cli.main(["export", str(run), "--out", str(tmp_path / "cli"), "--runtime-filter", "True",
                     "--filter-iters", "5"]) == 0
    out = capsys.readouterr().out
    assert "runtime filter on by default" in out and "note: the runtime filter" not in out  # asked for: no note
    assert Policy.load(tmp_path / "cli").filter_on and Policy.load(tmp_path / "cli").runtime_filter.iters == 5
    assert cli.main(["export", str(run), "--out", str(tmp_path / "cli")]) == 0  # an earlier export is replaced
    assert Policy.load(tmp_path / "cli").filter_on  # on unless told: eval turns it on under other dynamics
    assert not json.loads((run / "config.json").read_text())["d2spo"]["runtime_filter"]  # trained without it
    out = capsys.readouterr().out.splitlines()
    assert "runtime filter on by default" in out[0] and out[2] == FILTER_NOTE and "--runtime-filter False" in out[2]
    assert cli.main(["export", str(run), "--out", str(tmp_path / "cli"), "--runtime-filter", "False"]) == 0
    out = capsys.readouterr().out
    assert "runtime filter off by default" in out and FILTER_NOTE not in out  # off as asked: no note
    assert not Policy.load(tmp_path / "cli").filter_on
    assert "no such run directory" in one_error_line(capsys, ["export", str(tmp_path / "nothing"), "--out",
                                                               str(tmp_path / "o")])
    write_run(tmp_path / "nockpt", tiny_cfg())
    assert "no checkpoint" in one_error_line(capsys, ["export", str(tmp_path / "nockpt"), "--out", str(tmp_path / "o")])
    (tmp_path / "file").write_text("x")
    assert "exists and is not a directory" in one_error_line(capsys, ["export", str(run), "--out",
                                                                       str(tmp_path / "file")])
    assert "holds no exported policy" in one_error_line(capsys, ["export", str(run), "--out", str(run)])
    # what an export stopped before its manifest left (Ctrl-C): its own files only, taken over
    (tmp_path / "partial").mkdir()
    (tmp_path / "partial" / "weights.npz").write_bytes(b"half")
    (tmp_path / "partial" / ".weights.npz.123-0a1b2c3d.tmp").write_bytes(b"half")
    (tmp_path / "partial" / "nominal.onnx").write_bytes(b"half")  # --onnx's third graph
    assert cli.main(["export", str(run), "--out", str(tmp_path / "partial")]) == 0
    Policy.load(tmp_path / "partial")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "weights.npz").write_bytes(b"x")
    (tmp_path / "mine" / "notes.txt").write_text("mine")  # not an export's: the folder is left alone
    assert "holds no exported policy" in one_error_line(capsys, ["export", str(run), "--out", str(tmp_path / "mine")])
    # a filter of no iterations would return the action as it is: refused, as eval and training refuse it
    assert "--filter-iters: must be a positive integer, got 0" in one_error_line(
        capsys, ["export", str(run), "--out", str(tmp_path / "o"), "--filter-iters", "0"])
    write_run(tmp_path / "ppo", tiny_cfg("ppo-lag"))
    assert "ppo-lag is not exported" in one_error_line(capsys, ["export", str(tmp_path / "ppo"), "--out",
                                                                 str(tmp_path / "o")])
    write_run(tmp_path / "td3", tiny_cfg("td3"))
    assert "only D²SPO has a runtime filter" in one_error_line(capsys, ["export", str(tmp_path / "td3"), "--out",
                                                                         str(tmp_path / "o"), "--filter-iters", "2"])
    assert not (tmp_path / "o").exists()


def test_a_damaged_or_foreign_export_is_refused(tiny, tmp_path):
    with pytest.raises(ArtefactError, match="is a run directory, not an export; `d2spo export"):
        Policy.load(tiny[0])
    with pytest.raises(ArtefactError, match="no such directory"):
        Policy.load(tmp_path / "nope")
    with pytest.raises(ArtefactError, match=r"is a file; give the directory `d2spo export` wrote \("):
        Policy.load(tiny[1] / "manifest.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ArtefactError, match="no manifest.json"):
        Policy.load(tmp_path / "empty")
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny[1], copy)
    weights = copy / "weights.npz"
    weights.write_bytes(weights.read_bytes()[:-10])
    with pytest.raises(ArtefactError, match="damaged"):
        Policy.load(copy)
    manifest = json.loads((tiny[1] / "manifest.json").read_text())
    (copy / "manifest.json").write_text(json.dumps({**manifest, "format_version": 99}))
    with pytest.raises(ArtefactError, match="format version 99"):
        Policy.load(copy)
    shutil.copy(tiny[1] / "weights.npz", weights)
    # any value edited (the speed a robot is sent at, the filter's alpha): refused, not run as written
    for edit in ({"action": {**manifest["action"], "v_max": 9.0}},
                 {"filter": {**manifest["filter"], "alpha": "cubicc"}},
                 {"automaton": {**manifest["automaton"], "delta": [[0]]}}):
        (copy / "manifest.json").write_text(json.dumps({**manifest, **edit}))
        with pytest.raises(ArtefactError, match="edited or damaged since export"):
            Policy.load(copy)
    (copy / "manifest.json").write_text(json.dumps({**manifest, "observation": {"size": "sixteen"}}, indent=1))
    with pytest.raises(ArtefactError, match="edited or damaged since export"):
        Policy.load(copy)
    # an export of an earlier d2spo (format version 1, no content_sha256) that a broken writer left without a key
    old = {k: v for k, v in manifest.items() if k not in ("automaton", "content_sha256")}
    (copy / "manifest.json").write_text(json.dumps({**old, "format_version": 1}))
    with pytest.raises(ArtefactError, match="damaged .KeyError"):
        Policy.load(copy)
    unchecked = {k: v for k, v in manifest.items() if k != "content_sha256"}
    (copy / "manifest.json").write_text(json.dumps({**unchecked, "format_version": 1}))
    Policy.load(copy)  # version 1 predates the checksum: it loads as before


def test_a_manifest_whose_checksum_was_deleted_is_refused(tiny, tmp_path):
    """Deleting content_sha256 let an edited manifest (a faster v_max) load unchecked, as an export from
    before the key; a manifest of the format version that always records it is damaged or edited without it."""
    import shutil

    from d2spo.deploy.manifest import CHECKSUMMED_SINCE, FORMAT_VERSION

    copy = tmp_path / "copy"
    shutil.copytree(tiny[1], copy)
    manifest = json.loads((tiny[1] / "manifest.json").read_text())
    assert manifest["format_version"] == FORMAT_VERSION >= CHECKSUMMED_SINCE and "content_sha256" in manifest
    edited = {k: v for k, v in manifest.items() if k != "content_sha256"}
    for m in (edited, {**edited, "action": {**manifest["action"], "v_max": 9.0}}):
        (copy / "manifest.json").write_text(json.dumps(m))
        with pytest.raises(ArtefactError, match=r"damaged or edited since export \(no content_sha256, which every "
                                                r"manifest of format version 2 records\)"):
            Policy.load(copy)
    for version in (True, 1.5, "2"):  # a format version is an integer this runtime reads
        (copy / "manifest.json").write_text(json.dumps({**manifest, "format_version": version}))
        with pytest.raises(ArtefactError, match="format version .*; this d2spo reads versions 1 and 2"):
            Policy.load(copy)


def test_the_export_says_how_the_policy_it_wrote_was_evaluated(tmp_path):
    """An unfinished run or one whose final policy never stayed safe exported without a word; the
    export now quotes the run's evaluation of the policy it wrote, or says there is none."""
    from d2spo.cli_export import evaluated_line

    m = {"source": {"policy": "last (after 112 episodes)", "episodes": 112}, "config": {"episodes": 400}}
    assert evaluated_line(tmp_path, m).startswith("note: the run is unfinished (112 of 400 episodes): this policy "
                                                  "has not been evaluated; d2spo eval")
    e = {"episodes": 8, "safety_rate": 0.0, "completion_rate": 0.25}
    (tmp_path / "summary.json").write_text(json.dumps({"eval": e, "eval_best": {**e, "safety_rate": 1.0}}))
    assert evaluated_line(tmp_path, m).endswith("(8 episodes): 0.00% safe, 25.00% complete")
    best = {**m, "source": {"policy": "best (episode 90)", "episodes": 112}}
    assert evaluated_line(tmp_path, best).endswith("(8 episodes): 100.00% safe, 25.00% complete")
    (tmp_path / "summary.json").write_text(json.dumps({"route_optimal_visits": 11,
                                                       "eval": {**e, "accepting_visits_per_episode": 6.5}}))
    assert evaluated_line(tmp_path, m).endswith("0.00% safe, 6.50 accepting visits per episode")
    (tmp_path / "summary.json").write_text(json.dumps({"episodes": 400}))
    assert "holds no final evaluation" in evaluated_line(tmp_path, m)


def test_a_policy_with_non_finite_weights_is_not_exported(tmp_path):
    """A checkpoint whose actor held NaN (hand-edited, its checksums fixed) was exported, exit 0, while
    `d2spo eval` and `train --resume` refused it."""
    import jax
    import jax.numpy as jnp

    from d2spo.errors import NaNError
    from d2spo.run import build
    from d2spo.train import learner_program

    cfg = tiny_cfg()
    _, _, learner = build(cfg)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    actor = jax.tree_util.tree_map(lambda a: a.at[(0,) * a.ndim].set(jnp.nan), carry.agent.actor)
    write_run(tmp_path / "run", cfg, carry.replace(td3=carry.td3.replace(agent=carry.agent.replace(actor=actor))))
    with pytest.raises(NaNError, match="non-finite weights; nothing exported"):
        export_run(tmp_path / "run", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def _rehashed(manifest: dict, **edits) -> dict:
    """``manifest`` with top-level ``edits`` and its content_sha256 recomputed: what a writer with a bug, or
    an edit that also rewrote the checksum, leaves."""
    from d2spo.deploy.manifest import CONTENT_KEY, content_sha256

    m = {**manifest, **edits}
    return {**m, CONTENT_KEY: content_sha256(m)}


def test_a_manifest_whose_checksums_hold_but_which_this_runtime_would_misread_is_refused_at_load(tiny, tmp_path):
    """The checksums catch a damaged copy, not a consistent manifest with values the runtime does not
    have: an unknown alpha ran as the cubic one, an unknown label mode as step labelling, a NaN v_max
    gave a NaN command, an activation, a transition or a weight of the wrong shape failed in the robot's
    loop with numpy's KeyError, IndexError or matmul error. Each is now refused by Policy.load."""
    import hashlib
    import io
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny[1], copy)
    m = json.loads((tiny[1] / "manifest.json").read_text())
    actor = m["networks"]["actor"]
    automaton = m["automaton"]
    delta = [list(row) for row in automaton["delta"]]
    delta[0][1] = 77
    for edits, match in [
        ({"filter": {**m["filter"], "alpha": "quadratic"}}, "filter.alpha must be 'linear' or 'cubic'"),
        ({"filter": {**m["filter"], "dt": 0.0}}, r"filter.dt must be a finite number > 0"),
        ({"automaton": {**automaton, "label_mode": "evnt"}}, "label_mode must be 'event' or 'step'"),
        ({"automaton": {**automaton, "delta": delta}}, "automaton: delta must be"),
        ({"action": {**m["action"], "v_max": float("nan")}}, r"action.v_max must be a finite number > 0"),
        ({"networks": {**m["networks"], "actor": {**actor, "layers": [{**actor["layers"][0], "activation": "gelu"},
                                                                       *actor["layers"][1:]]}}},
         "activation 'gelu' is not one of"),
    ]:
        (copy / "manifest.json").write_text(json.dumps(_rehashed(m, **edits)))
        with pytest.raises(ArtefactError, match=match):
            Policy.load(copy)
    # weights of another shape, the manifest's SHA-256 of them updated: refused at load, not at the first act
    with np.load(tiny[1] / "weights.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["actor.0.kernel"] = arrays["actor.0.kernel"][:-1]
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    (copy / "weights.npz").write_bytes(buf.getvalue())
    weights = {**m["weights"], "sha256": hashlib.sha256(buf.getvalue()).hexdigest()}
    (copy / "manifest.json").write_text(json.dumps(_rehashed(m, weights=weights)))
    with pytest.raises(ArtefactError, match="damaged .ValueError: matmul"):
        Policy.load(copy)
