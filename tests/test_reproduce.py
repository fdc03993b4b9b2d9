"""`d2spo reproduce` and `d2spo report`: which runs each target needs, reuse of finished runs,
tables against the paper, snapshots for Fig. 5, and the Ray backend on a local Ray instance. The
figures themselves: tests/test_plots.py."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
from _reproduce import TINY_EPISODES, use_small_configs

from d2spo import reproduce as rp
from d2spo import targets
from d2spo.cli import main
from d2spo.errors import UserError


def test_targets_need_the_paper_runs():
    t2 = rp.runs_for("table2", seeds=3, episodes=20_000)
    assert len(t2) == 18 and {s.algo for s in t2} == set(targets.METHODS)
    assert {(s.task, s.layout) for s in t2} == {("phi1", "paper")}
    t3 = rp.runs_for("table3", seeds=2, episodes=100)
    assert {(s.task, s.layout, s.episodes) for s in t3} == {("relaxed", "relaxed", 100)}
    assert rp.runs_for("fig2", 1, 100) == rp.runs_for("table2", 1, 100) + rp.runs_for("table3", 1, 100)
    f3 = rp.runs_for("fig3", 1, 100)
    assert {(s.algo, s.layout) for s in f3} == {("td3", "open"), ("tlgrl", "open"), ("sl", "paper"), ("d2spo", "paper")}
    assert {s.task for s in f3} == {"phi1", "phi2"}
    f4 = rp.runs_for("fig4", 3, 20_000)
    assert [s.layout for s in f4] == list(targets.PHYSICAL) and {s.preset for s in f4} == {"turtlebot"}
    assert {s.episodes for s in f4} == {targets.FIG4_EPISODES}
    (f5,) = rp.runs_for("fig5", 3, 20_000)
    assert f5.snapshots == (2_000, 10_000, 20_000) and f5.name == "d2spo-phi1-paper-snapshots-s0"
    assert targets.fig5_snapshots(200) == (20, 100, 200)
    assert rp.expand(["all"]) == list(targets.TARGETS) and rp.expand(["fig2", "table2", "fig2"]) == ["fig2", "table2"]
    with pytest.raises(UserError, match="unknown target"):
        rp.expand(["table4"])
    names = [s.name for s in rp.runs_for("fig4", 1, 100)]
    assert len(set(names)) == len(names) and names[0] == "d2spo-phi1-physical-1-turtlebot-s0"


def test_cli_input_errors_exit_2(tmp_path, capsys):
    assert main(["reproduce", "table4", "--out", str(tmp_path)]) == 2
    assert main(["reproduce", "table2", "--seeds", "0", "--out", str(tmp_path)]) == 2
    assert main(["reproduce", "table2", "--backend", "slurm", "--methods", "cpo", "--seeds", "1",
                 "--episodes", "1", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()  # refused before anything is written
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert main(["report", str(tmp_path)]) == 2  # exists but holds nothing
    # a cluster address without the Ray backend would start every run here: refused
    assert main(["reproduce", "table2", "--address", "auto", "--out", str(tmp_path / "y")]) == 2
    (tmp_path / "afile").write_text("x")  # --out a file: one line, exit 2, as train's (it was exit 1)
    assert main(["reproduce", "table2", "--no-train", "--out", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 7 and all(line.startswith("d2spo: error:") for line in err)
    assert "address: is a Ray cluster's, for --backend ray" in err[5] and not (tmp_path / "y").exists()
    assert err[6].endswith("afile: exists and is not a directory")
    assert main(["report", str(tmp_path / "afile")]) == 2  # a file: said so, not "no such directory"
    assert capsys.readouterr().err.strip().endswith("afile: is a file; give the directory `d2spo reproduce --out` wrote")
    # `--methods` with nothing after it rendered an empty table with an IndexError's traceback, exit 1
    assert main(["reproduce", "table2", "--methods", "--no-train", "--out", str(tmp_path / "z")]) == 2
    assert capsys.readouterr().err.strip().startswith("d2spo: error: --methods names no method")
    assert not (tmp_path / "z").exists()


def test_table3_trains_once_reuses_and_reports(tmp_path, monkeypatch):
    use_small_configs(monkeypatch)  # the program of tests/test_fault_battery.py: compiled once per session
    out = tmp_path / "results"
    paths = rp.reproduce(["table3"], out, seeds=2, episodes=TINY_EPISODES, methods=["ppo-lag"], progress=False,
                         log=lambda s: None)
    assert paths == [out / "table3.md"]
    runs = sorted(p.name for p in (out / "runs").iterdir())
    assert runs == ["ppo-lag-relaxed-relaxed-s0", "ppo-lag-relaxed-relaxed-s1"]
    summaries = [json.loads((out / "runs" / r / "summary.json").read_text()) for r in runs]
    with open(out / "table3.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["algo"] == "ppo-lag" and int(row["seeds"]) == 2
    assert float(row["safety_mean"]) == pytest.approx(np.mean([s["safety_rate"] for s in summaries]))
    assert float(row["completion_std"]) == pytest.approx(np.std([s["completion_rate"] for s in summaries]))
    assert float(row["paper_safety"]) == pytest.approx(0.9159)
    collided = []
    for r in runs:
        with open(out / "runs" / r / "episodes.csv") as f:
            collided.append(np.mean([int(e["collided"]) for e in csv.DictReader(f)]))
    assert float(row["collision_rate_all_mean"]) == pytest.approx(np.mean(collided))
    assert all(len(v.lstrip("-0.").replace(".", "").rstrip("0")) <= 12 for v in row.values()  # 12 digits, no
               if v.replace(".", "").replace("-", "").isdigit())  # binary tails (1 - 0.95 = 0.0500...044)
    md = (out / "table3.md").read_text()
    assert "| LPPO | 2 |" in md and "91.59" in md and "63.50" in md
    assert f"over all {TINY_EPISODES} training episodes" in md  # not "the last 2000 of 24"
    # a second call trains nothing: the summaries are not rewritten
    stamp = [(out / "runs" / r / "summary.json").stat().st_mtime_ns for r in runs]
    logs = []
    rp.reproduce(["table3"], out, seeds=2, episodes=TINY_EPISODES, methods=["ppo-lag"], progress=False,
                 log=logs.append)
    assert [(out / "runs" / r / "summary.json").stat().st_mtime_ns for r in runs] == stamp
    assert logs[0].startswith("2 of 2 runs already finished")
    # --no-train with more seeds renders what has finished and trains nothing
    rp.reproduce(["table3"], out, seeds=3, episodes=TINY_EPISODES, methods=["ppo-lag"], progress=False,
                 log=lambda s: None, train=False)
    assert len(list((out / "runs").iterdir())) == 2 and "| LPPO | 2 |" in (out / "table3.md").read_text()
    # report
    assert main(["report", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "Table III" in report and "| LPPO | 2 |" in report and "--seeds 3" in report and "2 of 3 runs" in report


def test_runs_finished_by_another_process_meanwhile_are_kept(tmp_path, monkeypatch):
    """Two ``reproduce`` processes on one OUT: a group the other process finished after this one
    listed its work is reused when its turn comes, never started again (which deleted the finished
    runs, session 12)."""
    specs = [rp.RunSpec("ppo-lag", "relaxed", "relaxed", s, TINY_EPISODES) for s in (0, 1)]
    for s in specs:
        d = rp.run_dir(tmp_path, s)
        d.mkdir(parents=True)
        (d / "summary.json").write_text("{}")
        (d / "episodes.csv").write_text("the other process's episodes\n")
    real, listed = rp.is_finished, []

    def unfinished_when_listed(out, spec):  # the listing comes before the other process finishes
        if len(listed) < len(specs):
            listed.append(spec)
            return False
        return real(out, spec)

    monkeypatch.setattr(rp, "is_finished", unfinished_when_listed)
    logs = []
    rp.run_local(specs, tmp_path, progress=False, log=logs.append)
    assert logs[0].startswith("0 of 2 runs already finished")
    assert any("finished meanwhile" in line for line in logs)
    for s in specs:
        assert (rp.run_dir(tmp_path, s) / "episodes.csv").read_text() == "the other process's episodes\n"
    rp._discard_unstarted(rp.run_dir(tmp_path, specs[0]))  # a finished run is never discarded
    assert (rp.run_dir(tmp_path, specs[0]) / "summary.json").is_file()


def test_runs_another_process_is_training_are_skipped_untouched(tmp_path):
    """Two ``reproduce`` processes on one OUT: a group whose run the other process is training (its
    lock held, no checkpoint yet) is skipped with a line saying so, and none of its directories is
    deleted; before, the group's unstarted directories were removed from under the live training."""
    from d2spo.runio import RunLock, run_holder

    specs = [rp.RunSpec("ppo-lag", "relaxed", "relaxed", s, TINY_EPISODES) for s in (0, 1)]
    dirs = [rp.run_dir(tmp_path, s) for s in specs]
    for d in dirs:
        d.mkdir(parents=True)
        (d / "episodes.csv").write_text("partial\n")  # started, no checkpoint: discarded if not in use
    assert run_holder(dirs[1]) is None
    with RunLock(dirs[1]):  # the other process, training seed 1
        assert run_holder(dirs[1]).startswith("pid ")
        logs = []
        rp.run_local(specs, tmp_path, progress=False, log=logs.append)
        with pytest.raises(UserError, match="in use by another training"):
            rp._discard_unstarted(*dirs)
    assert any(line.startswith("  skipped: ") and "in use by another training" in line for line in logs)
    assert "1 group skipped" in logs[-1]
    for d in dirs:  # neither seed's directory was touched, nor trained
        assert (d / "episodes.csv").read_text() == "partial\n" and not (d / "summary.json").exists()
    assert run_holder(dirs[1]) is None  # released with the lock
    rp._discard_unstarted(*dirs)  # free again: discarded
    assert not any(d.exists() for d in dirs)


def test_report_says_per_section_how_it_was_rendered(tmp_path):
    """Tables and figures rendered by different invocations (different seeds) each keep their own
    provenance line in the report; the last invocation does not overwrite the earlier ones."""
    from d2spo.report import build_report

    (tmp_path / "fig3.png").write_bytes(b"png")
    (tmp_path / "table2.md").write_text("### Table II\n")
    rp.reproduce(["fig3"], tmp_path, seeds=1, episodes=20_000, progress=False, log=lambda s: None, train=False)
    rp.reproduce(["table2"], tmp_path, seeds=3, episodes=20_000, methods=["cpo"], progress=False,
                 log=lambda s: None, train=False)
    rendered = json.loads((tmp_path / "reproduce.json").read_text())["rendered"]
    assert rendered["fig3"]["seeds"] == 1 and rendered["fig3"]["runs"] == 8 and rendered["fig3"]["finished"] == 0
    assert rendered["table2"]["seeds"] == 3 and rendered["table2"]["runs"] == 3 and rendered["table2"]["methods"] == ["cpo"]
    report = build_report(tmp_path).read_text()
    assert "`d2spo reproduce fig3 --seeds 1 --episodes 20000`: 0 of 8 runs finished" in report
    assert "`d2spo reproduce table2 --seeds 3 --episodes 20000 --methods cpo`: 0 of 3 runs finished" in report
    # the last command, as the footer: with its methods (copying it without them would train all six)
    assert f"Last command: `d2spo reproduce table2 --seeds 3 --episodes 20000 --methods cpo --out {tmp_path} --no-train`" \
        in report


def test_runs_trained_with_other_settings_are_refused_unless_allowed(tmp_path, capsys):
    """A run in OUT whose config differs from what reproduce would train today (here: the old
    shaping clearance) must not slip into a table silently: exit 2 naming the setting, or, with
    --allow-stale, a warning and a count in the report."""
    from d2spo.config import config_to_dict
    from d2spo.report import build_report

    (spec,) = rp.runs_for("table2", 1, TINY_EPISODES, ["cpo"])
    d = rp.run_dir(tmp_path, spec)
    d.mkdir(parents=True)
    old = config_to_dict(spec.config())
    old["env"]["reward"]["shaping_clearance"] = None
    (d / "config.json").write_text(json.dumps(old))
    args = ["reproduce", "table2", "--methods", "cpo", "--seeds", "1", "--episodes", str(TINY_EPISODES),
            "--no-train", "--out", str(tmp_path)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "env.reward.shaping_clearance: None -> 0.3" in err[0] and "--allow-stale" in err[0]
    assert f"1 run in {tmp_path / 'runs'} was trained with other settings" in err[0]
    assert main(args + ["--allow-stale"]) == 0
    assert json.loads((tmp_path / "reproduce.json").read_text())["rendered"]["table2"]["stale"] == 1
    assert "1 of them trained with other settings" in build_report(tmp_path).read_text()
    # the same config as today's is not stale
    (d / "config.json").write_text(json.dumps(config_to_dict(spec.config())))
    assert rp.stale_runs(tmp_path, [spec]) == {} and main(args) == 0


def test_the_published_runs_are_todays_defaults_and_render_without_training(tmp_path):
    """docs/reproduce.md's recipe: the runs in docs/results/runs are what ``reproduce`` would train
    today (a changed default must come with runs trained again), and table3 renders from a copy."""
    from pathlib import Path

    published = Path(__file__).resolve().parent.parent / "docs" / "results"
    specs = [s for t in ("table2", "table3", "fig3", "fig4") for s in rp.runs_for(t, 3 if t.startswith("table") else 1,
                                                                               20_000)]
    assert all((rp.run_dir(published, s) / "summary.json").is_file() for s in specs)
    assert rp.stale_runs(published, specs) == {}
    for s in rp.runs_for("table3", 3, 20_000):
        shutil.copytree(rp.run_dir(published, s), rp.run_dir(tmp_path, s))
    assert main(["reproduce", "table3", "--no-train", "--out", str(tmp_path)]) == 0
    assert "| D²SPO | 3 |" in (tmp_path / "table3.md").read_text()
    # Fig. 4 needs the networks, which the published runs do not hold: one line, not an empty figure
    # that said its 4 of 4 runs were finished (a trial)
    for s in rp.runs_for("fig4", 1, 20_000):
        shutil.copytree(rp.run_dir(published, s), rp.run_dir(tmp_path, s))
    assert main(["reproduce", "fig4", "--no-train", "--out", str(tmp_path)]) == 2
    assert not (tmp_path / "fig4.png").exists()


def test_snapshots_are_saved_and_loaded(tmp_path):
    from test_train import tiny  # its learner: the compiled chunk of tests/test_train.py is reused

    from d2spo.run import build, load_snapshot, snapshot_path
    from d2spo.train import train

    cfg = tiny(eval_episodes=0, snapshots=(5, 40))
    train(cfg, tmp_path / "run")
    assert snapshot_path(tmp_path / "run", 5).is_file() and snapshot_path(tmp_path / "run", 40).is_file()
    _, _, learner = build(cfg)
    early = load_snapshot(tmp_path / "run", 5, learner)
    late = load_snapshot(tmp_path / "run", 40, learner)
    leaves = zip(jax.tree_util.tree_leaves(early), jax.tree_util.tree_leaves(late))
    assert any(not np.allclose(a, b) for a, b in leaves)  # the actor moved between the two
    with pytest.raises(Exception, match="no policy snapshot"):
        load_snapshot(tmp_path / "run", 7, learner)


def test_ray_backend_on_a_local_instance(tmp_path):
    """`--backend ray` on a local Ray instance that the command starts and stops. It runs in a
    child process, so Ray's processes and JAX's fork warning stay out of the test worker."""
    pytest.importorskip("ray")
    import subprocess
    import sys

    out = tmp_path / "results"
    cmd = [sys.executable, "-m", "d2spo.cli", "reproduce", "table3", "--backend", "ray", "--methods", "ppo-lag",
           "--seeds", "1", "--episodes", str(TINY_EPISODES), "--out", str(out), "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    spec = rp.RunSpec("ppo-lag", "relaxed", "relaxed", 0, TINY_EPISODES)
    summary = json.loads((rp.run_dir(out, spec) / "summary.json").read_text())
    assert summary["episodes"] == TINY_EPISODES and summary["seed"] == 0
    assert done.stdout.count("finished ppo-lag-relaxed-relaxed-s") == 1
    assert "0 of 1 runs already finished" in done.stdout and "1 Ray task\n" in done.stdout
    # the same directory layout as the local backend: the table reads it
    assert "| LPPO | 1 |" in (out / "table3.md").read_text()


def test_the_report_names_the_cpu_model(tmp_path):
    """XLA compiles for the CPU it runs on: the report says which one (family and model from Linux)."""
    from d2spo.report import cpu_model

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\n"
                    "model name\t: AMD EPYC\n\nprocessor\t: 1\nmodel name\t: another\n")
    assert cpu_model(str(info)) == "AMD EPYC (family 25, model 17)"
    assert cpu_model(str(tmp_path / "missing")) != ""


def test_the_report_names_the_cpus_the_process_may_use(monkeypatch):
    """XLA compiles for the CPUs the process may run on (d2spo/compile_cache.py): under ``taskset -c
    0`` on a 2-core machine the line says 1 of 2."""
    import os

    from d2spo.report import machine

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert ", 2 CPU cores, jax " in machine()
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    assert ", 1 of 2 CPU cores usable, jax " in machine()


def test_a_table_of_stale_runs_states_their_own_episodes(tmp_path):
    """With --allow-stale, table2.md said "over all 60 training episodes" for rows of 40-episode runs."""
    from d2spo import tables

    published = Path(__file__).resolve().parent.parent / "docs" / "results"
    runs = {m: [rp.run_dir(published, s) for s in rp.runs_for("table2", 3, 20_000, [m])] for m in ("td3-lag", "d2spo")}
    text = tables.write_table(tmp_path, "table2", runs, "phi1", "paper", 20_000).read_text()
    assert "over the last 2000 of 20000 training episodes, mean" in text
    text = tables.write_table(tmp_path, "table2", runs, "phi1", "paper", 30_000).read_text()
    assert ("over the last 2000 of 20000 training episodes (the runs' own: 30000 were asked, and runs trained with "
            "other settings were used as they are, --allow-stale)") in text


def test_a_resumed_run_is_announced(tmp_path, monkeypatch):
    """After an interrupted call, the next said only "0 of 2 runs already finished; training 2"."""
    specs = [rp.RunSpec("ppo-lag", "relaxed", "relaxed", s, TINY_EPISODES) for s in (0, 1)]
    d = rp.run_dir(tmp_path, specs[0])
    d.mkdir(parents=True)
    (d / "checkpoint.json").write_text("{}")  # seed 0 was started alone and interrupted
    monkeypatch.setattr(rp, "train_one", lambda *a, **k: None)
    logs = []
    rp.run_local(specs, tmp_path, progress=False, log=logs.append, vmap_seeds=False)
    assert logs[0] == (f"0 of 2 runs already finished in {tmp_path}; training 2 (1 resuming from a checkpoint an "
                       "interrupted call left)"), logs


def test_a_table_of_runs_with_other_windows_says_each_row_is_over_its_own(tmp_path):
    """The heading took the first run's window for every row (mixing runs with --allow-stale)."""
    import json
    import shutil

    from d2spo import tables

    published = Path(__file__).resolve().parent.parent / "docs" / "results"
    dirs = []
    for s, window in ((0, 2000), (1, 100)):
        src = rp.run_dir(published, rp.RunSpec("d2spo", "phi1", "paper", s, 20_000))
        d = tmp_path / "runs" / src.name
        d.mkdir(parents=True)
        shutil.copy(src / "episodes.csv", d)
        summary = json.loads((src / "summary.json").read_text())
        (d / "summary.json").write_text(json.dumps({**summary, "window": window}))
        dirs.append(d)
    text = tables.write_table(tmp_path, "table2", {"d2spo": dirs}, "phi1", "paper", 20_000).read_text()
    assert "over each run's own window, the last 100 or 2000 of its 20000 training episodes" in text
    assert "(the population std, ddof 0)" in text
