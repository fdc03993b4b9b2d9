"""Faults of issue #35 around the layout a run was trained on: evaluation files of two layouts
sharing a name, the dynamics an evaluation file is named after, a layout file edited under a run,
and a layout file named by another spelling or found from another directory. Nothing here trains
or compiles a learner: where a command would go on to build one it stops with ``Built``
(the ``no_build`` fixture)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _faults import Built, cli, layout_file, one_error, started_run

from d2spo.cli import main
from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import ConfigError, RunDirError

# ------------------------------------------------------------------------ eval file names


@pytest.fixture
def fake_rollouts(monkeypatch):
    """``d2spo eval`` without a policy or a rollout: every layout gets the same rates."""
    rates = {"episodes": 1, "safety_rate": 1.0, "completion_rate": 0.0, "mean_return": 0.0, "mean_length": 1.0,
             "mean_distance": 0.0, "max_steps": 2}
    monkeypatch.setattr("d2spo.evaluate.load_policy",
                        lambda run_dir, which, **kw: (None, None, None, {"policy": "last (after 0 episodes)"}))
    monkeypatch.setattr("d2spo.evaluate._specialist_rollouts", lambda cfg, learner, policy, ecfg, *a, **kw:
                        [dict(rates) for _ in ecfg.layouts()])


def test_two_layouts_never_share_an_evaluation_file(tmp_path, capsys, fake_rollouts):
    run = started_run(tmp_path / "run", "paper")
    a, b = layout_file(tmp_path / "a" / "lab.json", "relaxed"), layout_file(tmp_path / "b" / "lab.json", "open")
    for layout in (a, b, "random:55", "random5:5"):
        assert cli(capsys, "eval", run, "--layout", layout)[0] == 0
    names = sorted(p.name for p in run.glob("eval-*.json"))
    assert len(names) == 4, names
    for p in run.glob("eval-*.json"):
        res = json.loads(p.read_text())
        assert p.name.startswith("eval-lab-") == res["layout"].endswith("lab.json")
    by_layout = {json.loads(p.read_text())["layout"]: p.name for p in run.glob("eval-*.json")}
    assert by_layout[str(a)] != by_layout[str(b)]
    assert by_layout["random:55"] != by_layout["random5:5"]


def test_a_specialist_evaluates_its_own_task_however_spelt(tmp_path, capsys, no_build):
    """`eval --task` on a specialist once compared strings: its own formula in other words (the
    Unicode symbols, other spaces) was refused as 'another task than it learnt'."""
    run = started_run(tmp_path / "run", "paper")  # learnt phi1
    for spelt in ("phi1", "(¬A3 U A2) ∧ (¬A2 U A1) ∧ ◇A1 ∧ ◇A3", "(!A3 U A2)&(!A2 U A1)&F A1&F A3"):
        with pytest.raises(Built):
            cli(capsys, "eval", run, "--task", spelt)
    line = one_error(capsys, "eval", run, "--task", "(¬A3 U A2) ∧ (¬A2 U A1) ∧ ◇A1")
    assert "only a generalist (d2spo train --generalist) runs another task than it learnt" in line


def test_evaluation_file_names_of_built_in_and_random_layouts_are_kept():
    from d2spo.evalfiles import evaluation_path, layout_sha256, layout_tag

    one = {"layout": "paper", "per_layout": [{}], "dynamics": "default", "runtime_filter": None}
    assert evaluation_path(Path("r"), one) == Path("r") / "eval-paper-default.json"
    assert layout_tag("random:11") == "random11" and layout_tag("random") == "random0"
    assert layout_tag("random5:5") == "random5-5" != layout_tag("random:55")
    assert layout_sha256("paper") is None and layout_sha256("random:3") is None


def test_a_run_trained_under_its_own_dynamics_is_evaluated_as_trained_not_as_its_preset(tmp_path, capsys,
                                                                                        fake_rollouts):
    """A run trained with a dynamics file or per-field flags wrote its evaluations as `-default`, the
    preset it started from, though it ran under its own values."""
    from d2spo.evaluate import trained_dynamics
    from d2spo.run import prepare_dir

    assert trained_dynamics(TrainConfig()) == "default"
    assert trained_dynamics(TrainConfig(env=EnvConfig(preset="turtlebot"))) == "turtlebot"
    assert trained_dynamics(TrainConfig(env=EnvConfig(slip=0.05))) == "default"  # the preset's own value
    run = tmp_path / "run"
    run.mkdir()
    prepare_dir(run, TrainConfig(env=EnvConfig(layout="relaxed", v_gain=0.85)), resume=False)
    assert cli(capsys, "eval", run)[0] == 0
    res = json.loads((run / "eval-relaxed-trained.json").read_text())
    assert res["dynamics"] == "trained" and res["dynamics_values"]["v_gain"] == 0.85
    assert cli(capsys, "eval", run, "--slip", "0.2")[0] == 0 and (run / "eval-relaxed-trained-slip0.2-filter-a3-i3.json").exists()


# ------------------------------------------------------------------ the layout's content


def test_a_layout_file_edited_since_the_run_started_is_refused(tmp_path, capsys, no_build, monkeypatch):
    lab = layout_file(tmp_path / "lab.json")
    run = started_run(tmp_path / "run", str(lab))
    def built(*a, **kw):
        raise Built

    for module in ("d2spo.export", "d2spo.certify_load"):  # as if it had a checkpoint; stop where they would build
        monkeypatch.setattr(f"{module}.has_checkpoint", lambda run_dir: True)
        monkeypatch.setattr(f"{module}.build", built)
    for command in (["train", "--resume", str(run), "--no-progress"], ["export", str(run), "--out", str(tmp_path / "x")],
                    ["certify", str(run)]):
        with pytest.raises(Built):  # unchanged: the checks pass
            main(command)
    lab.write_text(lab.read_text().replace('"name"', ' "name"', 1))  # one byte more
    line = one_error(capsys, "train", "--resume", run, "--no-progress")
    assert f"{run}: its layout file {lab} changed since the run started" in line
    line = one_error(capsys, "eval", run)
    assert f"its layout file {lab} changed since the run started" in line
    assert f"to evaluate on it as it is now, pass --layout {lab}" in line
    # export and certify read the map too: an export's filter, a certificate, of another map than learnt
    # (they once went on with the edited file)
    line = one_error(capsys, "export", run, "--out", tmp_path / "y")
    assert f"its layout file {lab} changed since the run started" in line and "export's map" in line
    assert not (tmp_path / "y").exists()
    line = one_error(capsys, "certify", run)
    assert f"its layout file {lab} changed since the run started" in line and "checked against another map" in line
    recorded = json.loads((run / "inputs.json").read_text())["layout"]
    assert recorded["file"] == str(lab) and len(recorded["sha256"]) == 64
    # from Python too: load_policy (what the figures call) once built the learner on the edited file
    from d2spo.run import load_policy
    with pytest.raises(RunDirError, match="changed since the run started.*train a new run on it as it is now"):
        load_policy(run)


def test_the_training_layout_file_is_known_by_its_content_not_its_spelling(tmp_path, monkeypatch):
    """`d2spo eval RUN --layout in/lab.json` ran with the filter as trained and `--layout /abs/in/lab.json`
    (the same file) with it on, as if elsewhere. Now a file is the training layout when it holds the
    bytes the run started with, and an edited file is another layout (the filter on)."""
    from d2spo.evaluate import filter_choice
    from d2spo.run import is_training_layout, load_run_config

    monkeypatch.chdir(tmp_path)
    lab = layout_file(tmp_path / "in" / "lab.json")
    run = started_run(tmp_path / "run", "in/lab.json")
    cfg = load_run_config(run)
    assert cfg.algo == "d2spo"
    for spelling in ("in/lab.json", "./in/lab.json", str(lab), "in/../in/lab.json"):
        same = is_training_layout(run, cfg, spelling)
        assert same and filter_choice(cfg, spelling, None, None, None, same) is None, spelling
    (tmp_path / "copy.json").write_bytes(lab.read_bytes())
    assert is_training_layout(run, cfg, "copy.json")  # the same bytes: the same layout
    assert not is_training_layout(run, cfg, "relaxed") and not is_training_layout(run, cfg, "missing.json")
    lab.write_text(lab.read_text().replace('"name"', ' "name"', 1))  # one byte more
    same = is_training_layout(run, cfg, "in/lab.json")
    assert not same and filter_choice(cfg, "in/lab.json", None, None, None, same) is True
    assert filter_choice(cfg, "in/lab.json", None, None) is None  # by name alone, as before


def test_a_run_on_a_relative_layout_path_is_found_from_another_directory(tmp_path, capsys, no_build, monkeypatch):
    """config.json keeps the layout's path as given (``lab.json``); from another directory the run's
    file is found where inputs.json recorded it, or at the --layout given, if it holds the same bytes."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path / "a")
    layout_file(tmp_path / "a" / "lab.json")
    run = started_run(tmp_path / "a" / "run", "lab.json")
    monkeypatch.chdir(tmp_path / "b")
    for command in (["train", "--resume", str(run), "--no-progress"], ["eval", str(run)]):
        with pytest.raises(Built):  # found through inputs.json's absolute path
            main(command)
    (tmp_path / "a" / "lab.json").rename(tmp_path / "b" / "moved.json")
    line = one_error(capsys, "eval", run)
    assert f"its layout file lab.json (at {tmp_path / 'a' / 'lab.json'} when it started) is not found from" in line
    assert "pass --layout PATH" in line
    with pytest.raises(Built):  # the same bytes elsewhere, named by --layout
        main(["eval", str(run), "--layout", "moved.json"])
    layout_file(tmp_path / "b" / "other.json", "open")
    assert "is not found from" in one_error(capsys, "eval", run, "--layout", "other.json")  # other bytes


def test_a_run_without_a_recorded_layout_hash_still_resumes_and_evaluates(tmp_path, no_build):
    lab = layout_file(tmp_path / "lab.json")
    run = started_run(tmp_path / "run", str(lab))
    (run / "inputs.json").unlink(missing_ok=True)  # a run of an earlier d2spo
    lab.write_text(lab.read_text() + "\n")
    with pytest.raises(Built):
        main(["train", "--resume", str(run), "--no-progress"])
    with pytest.raises(Built):
        main(["eval", str(run)])


def test_a_specialist_on_a_layout_of_other_area_slots_is_refused_or_warned():
    """A specialist reads area k's position in slot k: on a layout of another area count the refusal
    names both counts; the same count in another label order ran without a word (a user's lab file
    with its areas reordered), and now warns."""
    from types import SimpleNamespace as NS

    from d2spo.errors import TaskWarning
    from d2spo.evaluate import check_same_slots

    def env(*labels, states=3):
        return NS(layout=NS(areas=[NS(label=x) for x in labels]), n_states=states,
                  observation_size=2 * len(labels) + states)

    trained = env("dock", "dock", "kitchen", "office")
    check_same_slots(trained, env("dock", "dock", "kitchen", "office"), "lab.json")  # nothing to say
    with pytest.warns(TaskWarning, match=r"lists its areas' labels as \['dock', 'kitchen', 'dock', 'office'\]"):
        check_same_slots(trained, env("dock", "kitchen", "dock", "office"), "lab.json")
    with pytest.raises(ConfigError, match="trained on 4 areas and 3 automaton states; layout 'small.json' has 3 "
                                          "areas and the task 3 states here"):
        check_same_slots(trained, env("dock", "kitchen", "office"), "small.json")


def test_the_runs_own_task_refused_on_a_typed_layout_names_the_layout(tmp_path, capsys, monkeypatch):
    """`eval RUN --layout office.json` of a run that learnt phi1 (A1..A3; office has desk and kitchen):
    the refusal named `--task`, which the user never typed; it names `--layout` and the run's task.
    With `--task` typed, the task stays the culprit."""
    monkeypatch.setattr("d2spo.evaluate.load_policy", lambda *a, **kw: (None, None, None, {"policy": "last"}))
    run = started_run(tmp_path / "run", "paper")
    office = str(Path(__file__).parent / "data" / "layouts" / "office.json")
    line = one_error(capsys, "eval", run, "--layout", office)
    assert line.startswith("d2spo: error: --layout: the run's task 'phi1' does not fit this layout: ") \
        and "propositions with no area" in line, line
    assert one_error(capsys, "eval", run, "--layout", office, "--task", "phi1").startswith("d2spo: error: --task: ")
