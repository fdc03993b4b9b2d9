"""`d2spo certify` on run directories: a barrier shifted up is reported violated (down: certified in
ℒ), and bad input gets one line and exit status 2."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest
from _cli import one_error_line
from _tiny import tiny_cfg, write_run

from d2spo.checkpoint import Checkpoints, run_fingerprint
from d2spo.train import learner_program

CCFG_TINY = dict(grid_step=0.25, headings=2, residual_episodes=2, search_starts=8, search_steps=4)
"""A small grid and search: certification of the tiny runs below takes seconds once compiled."""






@pytest.fixture(scope="module")
def untrained_run(tmp_path_factory):
    """A d2spo run directory whose checkpoint is the learner's initial state (no training)."""
    from d2spo.run import build

    cfg = tiny_cfg()
    _, _, learner = build(cfg)
    carry = learner_program(learner, "init")(jax.random.PRNGKey(0))
    path = tmp_path_factory.mktemp("certify") / "run"
    write_run(path, cfg, carry)
    return path


def _shifted(run, c: float):
    """The run with h_Θ's output bias shifted by c."""
    cbf = run.carry.safety.cbf
    last = max((k for k in cbf["params"] if k.startswith("Dense_")), key=lambda k: int(k.split("_")[1]))
    new = jax.tree_util.tree_map(lambda a: a, cbf)
    new["params"][last]["bias"] = cbf["params"][last]["bias"] + c
    return run._replace(carry=run.carry.replace(safety=run.carry.safety.replace(cbf=new)))


def test_h_shifted_up_is_reported_violated_and_shifted_down_certified(untrained_run, tmp_path):
    from d2spo.certify import CertifyConfig, certify_run, status_maps, write_outputs
    from d2spo.certify_load import load_cbf_run

    ccfg = CertifyConfig(**CCFG_TINY)  # the same config as the repair test: the compiled pieces are shared
    run = load_cbf_run(untrained_run)
    up, up_nets = certify_run(untrained_run, ccfg, run=_shifted(run, 20.0), search=False)
    assert up["nets"]["grid_L"]["points"] > 0 and up["nets"]["grid_L"]["violated"] == 1.0
    assert up["grid_L_violated"] == up["nets"]["grid_L"]["points"]
    down, _ = certify_run(untrained_run, ccfg, run=_shifted(run, -20.0), search=False)
    assert down["nets"]["grid_L"]["certified"] == 1.0
    assert down["nets"]["grid_free"]["violated"] == 1.0  # e ≈ α(−20) < 0 wherever the robot is free
    assert down["nets"]["grid_D"]["points"] == 0  # an untrained run has explored nothing
    json.dumps(up)  # the summary is what certify.json holds
    # the picture: Prop. 1's map is violated (2) wherever the ring and contact grid has a point
    maps, _ = status_maps(run, ccfg, up_nets)
    assert set(np.unique(maps[0])) <= {-1, 2} and (maps[0] == 2).any()
    up["counterexamples"] = {"L": [], "D": []}
    j, png = write_outputs(tmp_path, run, ccfg, up, up_nets)
    assert json.loads(j.read_text())["grid_L_violated"] == up["grid_L_violated"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_gets_one_line_and_exit_2(tmp_path, capsys, untrained_run):
    assert "no such run directory" in one_error_line(capsys, ["certify", str(tmp_path / "nothing")])
    write_run(tmp_path / "tlgrl", tiny_cfg("tlgrl"))
    assert "no learned CBF" in one_error_line(capsys, ["certify", str(tmp_path / "tlgrl")])
    write_run(tmp_path / "generalist", dataclasses.replace(tiny_cfg(), generalist=True))  # was a KeyError
    assert "a generalist reads a field bank" in one_error_line(capsys, ["certify", str(tmp_path / "generalist")])
    assert "a generalist reads a field bank" in one_error_line(capsys, ["certify", str(tmp_path / "generalist"),
                                                                         "--repair", "--out", str(tmp_path / "g")])
    write_run(tmp_path / "nockpt", tiny_cfg())
    assert "no checkpoint" in one_error_line(capsys, ["certify", str(tmp_path / "nockpt")])
    foreign = tmp_path / "foreign"
    write_run(foreign, tiny_cfg(), carry={"something": np.zeros(3)})
    assert "checkpoint" in one_error_line(capsys, ["certify", str(foreign)])
    assert "--eps-safe: " in one_error_line(capsys, ["certify", str(untrained_run), "--eps-safe", "0"])
    assert "--eps-unsafe: " in one_error_line(capsys, ["certify", str(untrained_run), "--repair", "--eps-unsafe", "-1",
                                                    "--out", str(tmp_path / "r")])
    # the repair's flags without --repair would be ignored (no repaired run written): refused, before any work
    assert one_error_line(capsys, ["certify", str(untrained_run), "--out", str(tmp_path / "r")]).endswith(
        "--out acts only with --repair; add --repair, or leave it out")
    assert "--rounds, --calls act only with --repair" in one_error_line(
        capsys, ["certify", str(untrained_run), "--rounds", "3", "--calls", "5"])
    assert not (tmp_path / "r").exists()


def test_bad_epsilon_through_the_command_line_has_no_traceback(untrained_run):
    res = subprocess.run([sys.executable, "-m", "d2spo.cli", "certify", str(untrained_run), "--eps-unsafe", "0"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == ["d2spo: error: --eps-unsafe: must be a finite number > 0, got 0.0"]



def test_certify_checks_the_policy_eval_and_export_take(untrained_run, tmp_path):
    """A validated run's kept policy is the one `d2spo eval` and `d2spo export` take by default; certify
    checked the newest checkpoint's barrier instead. Now ``--policy best`` (the default) checks the kept
    one, ``--policy last`` the newest, and certify.json says which."""
    from flax import serialization

    from d2spo.certify import CertifyConfig, certify_run
    from d2spo.certify_load import load_cbf_run, with_policy
    from d2spo.run import best_policy_path

    ccfg = CertifyConfig(**CCFG_TINY)
    last = load_cbf_run(untrained_run)
    run = tmp_path / "run"
    run.mkdir()
    for f in untrained_run.iterdir():  # its config and inputs; the checkpoint is written below
        if f.is_file():
            (run / f.name).write_bytes(f.read_bytes())
    kept = _shifted(last, 20.0).carry  # the kept policy: h shifted up, violated on the ring
    newest_carry = _shifted(last, -20.0).carry  # the newest checkpoint's: shifted down, certified there
    Checkpoints(run, run_fingerprint(run)).save(newest_carry, {"episodes": 0, "env_steps": 0, "chunks": 0,
                                                             "wall_seconds": 0.0, "best": {"episodes": 0}})
    best_policy_path(run).write_bytes(serialization.to_bytes(jax.device_get((kept.agent.actor, kept.safety))))
    loaded = load_cbf_run(run)
    best, _ = certify_run(run, ccfg, run=with_policy(loaded, run, "best"), search=False)
    newest, _ = certify_run(run, ccfg, run=with_policy(loaded, run, "last"), search=False)
    assert best["policy"].startswith("best on validation") and newest["policy"].startswith("last")
    assert best["nets"]["grid_L"]["violated"] == 1.0 and newest["nets"]["grid_L"]["certified"] == 1.0


def test_certify_names_each_stage_as_it_starts_and_is_quiet_without_progress(untrained_run, tmp_path, capsys):
    """A certification runs a minute or more without a table: stderr says which stage runs (a log
    gets a line per stage); --no-progress prints none of them."""
    import shutil

    from d2spo import cli
    from d2spo.progress import StageProgress

    run = tmp_path / "run"
    shutil.copytree(untrained_run, run)
    flags = [f"--{k.replace('_', '-')}={v}" for k, v in CCFG_TINY.items()]
    assert cli.main(["certify", str(run), *flags]) == 0
    seen = capsys.readouterr()
    stages = [ln.split(": ", 1)[1].split(" (")[0] for ln in seen.err.splitlines() if ln.startswith("certify run: ")]
    assert stages == ["the nominal model's residual on the data", "Propositions 1-2 on the datasets and the grids",
                      "searching for counterexamples", "drawing certify.png"], seen.err
    assert "wrote" in seen.out and (run / "certify.json").is_file()
    with StageProgress(None, False, "certify run") as on_stage:  # --no-progress: no callback, no console used
        assert on_stage is None


@pytest.fixture(scope="module")
def filled_run(untrained_run, tmp_path_factory):
    """The untrained run with X_L and P_exp filled from the pose grid and h shifted up by 0.3, so that
    part of the ring is violated: something for --repair to work on."""
    import jax.numpy as jnp

    from d2spo.certify import CertifyConfig, _compiled
    from d2spo.certify_load import load_cbf_run
    from d2spo.certify_search import pose_grid
    from d2spo.repair import add_counterexamples

    ccfg = CertifyConfig(**CCFG_TINY)
    run = load_cbf_run(untrained_run)
    grid = pose_grid(run, ccfg)
    near = np.asarray(_compiled(run, ccfg)["nearest"](jnp.asarray(grid)))
    carry = add_counterexamples(run, ccfg, run.carry, grid[near <= 0.2][:40], [(grid[near >= 0.3][:40], 0)], 1)
    path = tmp_path_factory.mktemp("repair") / "run"
    write_run(path, tiny_cfg(), _shifted(run._replace(carry=carry), 0.3).carry)
    return path


def test_repair_rule_is_never_worse_in_anything():
    from d2spo.repair import better

    def s(cl, cd, vl, vd=0):
        return {"certified_L": cl, "certified_D": cd, "grid_L_violated": vl, "grid_D_violated": vd}

    assert better(s(0.5, 0.9, 3), s(0.4, 0.9, 3)) and better(s(0.4, 0.9, 2), s(0.4, 0.9, 3))
    assert not better(s(0.9, 0.8, 0), s(0.4, 0.9, 3))  # ℒ up, D down: not better
    assert not better(s(0.5, 0.9, 4), s(0.4, 0.9, 3))  # one more violated grid point
    assert not better(s(0.4, 0.9, 3), s(0.4, 0.9, 3))  # no change: repair stops
    assert better(s(0.1, 0.0, 0), s(float("nan"), float("nan"), 1))  # an empty net counts as 0
    # fewer violations in D's explored part do not buy new ones in the ring (they were summed)
    assert not better(s(1.0, 0.9, 5, 2), s(1.0, 0.9, 0, 36))
    assert better(s(1.0, 0.9, 0, 2), s(1.0, 0.9, 0, 36))


def test_repair_drops_the_kept_policy_so_the_repaired_one_is_used(filled_run, tmp_path):
    """The repaired run kept the original's policy-best.msgpack and its entry, so `d2spo eval`, `export`
    and `certify` (which take a kept policy first) read the unrepaired networks."""
    from flax import serialization

    from d2spo.certify import CertifyConfig
    from d2spo.certify_load import load_cbf_run, with_policy
    from d2spo.repair import RepairConfig, repair_run
    from d2spo.run import best_policy_path

    run = tmp_path / "validated"
    shutil.copytree(filled_run, run)
    loaded = load_cbf_run(run)
    meta = dict(loaded.meta, best={"episodes": 0, "success_rate": 0.0})
    Checkpoints(run, run_fingerprint(run)).save(loaded.carry, meta)
    kept = _shifted(loaded, 20.0).carry
    best_policy_path(run).write_bytes(serialization.to_bytes(jax.device_get((kept.agent.actor, kept.safety))))
    out = tmp_path / "repaired"
    repair_run(run, out, CertifyConfig(**CCFG_TINY), RepairConfig(rounds=1, calls=1, copies=1, eval_episodes=0))
    assert not best_policy_path(out).exists()
    repaired = load_cbf_run(out)
    assert "best" not in repaired.meta
    assert with_policy(repaired, out, "best").meta["policy"].startswith("last")


def test_a_search_of_no_steps_is_refused_and_repair_takes_policy_last(capsys, untrained_run, tmp_path):
    """--search-steps 0 ran no search and said "no counterexample found"; --repair refused --policy last,
    the policy it repairs."""
    assert "--search-steps: " in one_error_line(capsys, ["certify", str(untrained_run), "--search-steps", "0"])
    assert "give last" in one_error_line(capsys, ["certify", str(untrained_run), "--repair", "--policy", "best",
                                                  "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r").exists()


def test_repair_writes_an_ordinary_run_no_worse_than_before(filled_run, tmp_path):
    from d2spo.certify import CertifyConfig
    from d2spo.evaluate import EvalConfig, evaluate_run
    from d2spo.repair import RepairConfig, repair_run
    from d2spo.run import build, load_run_config

    out = tmp_path / "repaired"
    res = repair_run(filled_run, out, CertifyConfig(**CCFG_TINY), RepairConfig(rounds=1, calls=1, copies=1, eval_episodes=0))
    assert res["before"]["grid_L_violated"] > 0 and len(res["rounds"]) >= 2  # something was tried
    assert all(r["better"] for r in res["rounds"][1:res["kept"] + 1])  # the kept round beat every earlier one
    for k in ("certified_L", "certified_D"):  # never worse than the original
        assert np.nan_to_num(res["after"][k]) >= np.nan_to_num(res["before"][k])
    assert res["after"]["grid_L_violated"] <= res["before"]["grid_L_violated"]
    saved = json.loads((out / "certify.json").read_text())
    assert saved["repair_kept_round"] == res["kept"] and len(saved["repair_rounds"]) == len(res["rounds"])
    # `d2spo train --resume` reads the run's own config and the checkpoint with the learner's template
    cfg = load_run_config(out)
    assert cfg == load_run_config(filled_run)
    _, _, learner = build(cfg)
    carry, meta = Checkpoints(out, run_fingerprint(out)).load(jax.eval_shape(learner.init, jax.random.PRNGKey(0)))
    assert meta["episodes"] == 0
    orig, _ = Checkpoints(filled_run, run_fingerprint(filled_run)).load(jax.eval_shape(learner.init, jax.random.PRNGKey(0)))
    same = all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(carry.safety.cbf),
                                                     jax.tree_util.tree_leaves(orig.safety.cbf)))
    assert same == (res["kept"] == 0)
    r = evaluate_run(out, EvalConfig(episodes=2))  # `d2spo eval`
    assert 0.0 <= r["safety_rate"] <= 1.0
