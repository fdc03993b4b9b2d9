"""One-line errors and flags user trials met (2026-12-03): a flag of another subcommand, `env show`'s
counts and task, `d2spo report` on a folder of one's own runs, an LTL syntax error's flag."""

from __future__ import annotations

import pytest

from d2spo import cli, console

_MISPLACED_BOX = (  # tyro's message for `d2spo env check --label-mode step` before env check took the flag
    "╭─ Unrecognized options ───────────────────────────────────────────────────────╮\n"
    "│ Unrecognized or misplaced options:                                           │\n"
    "│   --label-mode (applied to d2spo env check)                                  │\n"
    "│   step (applied to d2spo env check)                                          │\n"
    "│                                                                              │\n"
    "│ Arguments are applied to the directly preceding subcommand, so ordering can  │\n"
    "│ matter.                                                                      │\n"
    "│ ──────────────────────────────────────────────────────────────────────────── │\n"
    "│ Perhaps you meant:                                                           │\n"
    "│     --label-mode STR                                                         │\n"
    "│         Labelling the distances assume: 'event' (no empty letter) or 'step'. │\n"
    "│         (default: event)                                                     │\n"
    "│         in d2spo ltl --help                                                  │\n"
    "│         Labelling: 'event' (a letter when the set of areas changes to a      │\n"
    "│         non-empty one) or 'step'. (default: event)                           │\n"
    "│         in d2spo train --help                                                │\n"
    "│ ──────────────────────────────────────────────────────────────────────────── │\n"
    "│ For full helptext, run d2spo --help                                          │\n"
    "╰──────────────────────────────────────────────────────────────────────────────╯\n"
)


def _one_error_line(capsys, args: list[str]) -> str:
    try:
        status = cli.main(args)
    except SystemExit as e:  # tyro's parse errors leave through SystemExit, as in the command
        status = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and err[0].startswith("d2spo: error: "), err
    return err[0]


def test_a_flag_of_another_subcommand_reads_as_an_unknown_flag_and_says_where_it_is():
    """It read "Unrecognized options: Unrecognized or misplaced options: --label-mode (applied to d2spo
    env check) step (applied to d2spo env check)"."""
    line = console.tyro_error_line(_MISPLACED_BOX, ["env", "check", "--label-mode", "step"])
    assert line == ("Unrecognized options: --label-mode, step (--label-mode is a flag of d2spo ltl and "
                    "d2spo train, not of d2spo env check)")


@pytest.mark.parametrize("args, says", [
    (["env", "check", "--episodes", "3"], "--episodes is a flag of d2spo demo, d2spo eval, d2spo reproduce and "
                                          "d2spo train, not of d2spo env check"),
    (["env", "show", "--max-steps", "3"], "--max-steps is a flag of d2spo env check, d2spo eval and d2spo train, "
                                          "not of d2spo env show"),
])
def test_the_command_names_the_subcommands_a_misplaced_flag_belongs_to(capsys, args, says):
    line = _one_error_line(capsys, args)
    assert line.startswith(f"d2spo: error: Unrecognized options: {args[2]}, {args[3]} ({says})"), line
    assert "misplaced" not in line and "applied to" not in line


@pytest.mark.parametrize("flags, says", [
    (["--rollout-steps", "-3"], "--rollout-steps: must be an integer >= 0, got -3"),
    (["--rollout-steps", "3", "--seed", "-1"], "--seed: must be an integer in [0, "),
])
def test_env_show_refuses_a_negative_count_or_seed_as_train_and_eval_do(capsys, tmp_path, flags, says):
    """`env show --rollout-steps -3` drew the layout without a rollout, and `--seed -1` was taken."""
    line = _one_error_line(capsys, ["env", "show", "--out", str(tmp_path / "x.png"), *flags])
    assert line.startswith(f"d2spo: error: {says}"), line
    assert not (tmp_path / "x.png").exists()


def test_report_on_a_folder_of_ones_own_runs_says_what_it_reads(capsys, tmp_path):
    """It said only "run `d2spo reproduce all --out runs` first" (36 runs of the paper's tasks) to a
    user whose runs/ held `d2spo train` runs of their own layout and task."""
    (tmp_path / "td3-lag-s0").mkdir()
    (tmp_path / "td3-lag-s0" / "summary.json").write_text("{}")
    line = _one_error_line(capsys, ["report", str(tmp_path)])
    assert "holds no tables or figures of `d2spo reproduce`" in line and "summary.json" in line, line


@pytest.mark.parametrize("args, prefix", [(["env", "check", "--task", "F (A1"], "--task: "),
                                          (["env", "check", "--task=F (A1"], "--task: "),
                                          (["ltl", "F (A1"], "")])
def test_an_ltl_syntax_error_names_the_flag_it_was_typed_after(args, prefix, capsys):
    """One line, exit 2, starting with the flag the formula came with (as every other flag's error
    does), and none for a formula given as a positional argument."""
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"d2spo: error: {prefix}LTL syntax error at column 6: expected ')' to close the '(' at column 3, "
                   "found end of formula in 'F (A1'"], err


def test_flag_of_value_finds_a_list_flags_later_value():
    from d2spo.console import flag_of_value

    assert flag_of_value("b", ["train", "--tasks", "a", "b", "--seed", "1"]) == "--tasks"
    assert flag_of_value("1", ["train", "--tasks", "a", "b", "--seed", "1"]) == "--seed"
    assert flag_of_value("c", ["train", "--tasks", "a", "b"]) is None


def test_env_show_draws_a_rollout_of_the_task_given_and_refuses_a_task_with_no_rollout(tmp_path, capsys):
    """`env show --task T --rollout-steps N`: the random rollout is an episode of T (the title names it);
    a task with no rollout to end is a mistake (one line, exit 2), as is a task the layout cannot do."""
    import matplotlib.image

    out = tmp_path / "show.png"
    assert cli.main(["env", "show", "--task", "patrol2", "--rollout-steps", "40", "--out", str(out)]) == 0
    assert matplotlib.image.imread(out).shape[0] > 100
    for args in (["--task", "patrol2"], ["--task", "F A9", "--rollout-steps", "40"]):
        assert cli.main(["env", "show", *args, "--out", str(tmp_path / "x.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("d2spo: error: --task:"), err
    assert not (tmp_path / "x.png").exists()


def test_env_check_reads_the_letters_train_would_with_label_mode(capsys):
    """`env check` had no --label-mode (a user trial: "--label-mode is a flag of d2spo ltl and d2spo
    train"). `F (A1 & X A2)` needs A2 as the letter right after A1: there is one with letters read on
    entering areas, none with a letter every step (the robot is still in A1 or between areas)."""
    assert cli.main(["env", "check", "--task", "F (A1 & X A2)", "--label-mode", "event"]) == 0
    assert "needs 2 area visits" in capsys.readouterr().out
    line = _one_error_line(capsys, ["env", "check", "--task", "F (A1 & X A2)", "--label-mode", "step"])
    assert "cannot be completed on layout 'paper'" in line and "--label-mode step: every step is a letter" in line
    corridor = "tests/data/layouts/handmade/corridor-5.json"  # the margin fails it in either mode: geometry
    assert cli.main(["env", "check", "--layout", corridor, "--task", "G !A2 & F A3", "--label-mode", "step"]) == 0
    warned = capsys.readouterr().err
    assert "while keeping 0.3 m" in warned and "--label-mode step" not in warned, warned
    line = _one_error_line(capsys, ["env", "check", "--task", "G F A1", "--label-mode", "step"])
    assert "(every step in an area reads its letter again, with --label-mode step)" in line, line
    # `A4 U A1` from a start outside every area: the empty letter fails it at once (no area is entered)
    line = _one_error_line(capsys, ["env", "check", "--task", "A4 U A1", "--label-mode", "step"])
    assert "step labelling reads the empty letter (no area) at the start" in line and "first area" not in line, line
    assert _one_error_line(capsys, ["env", "check", "--label-mode", "steps"]).startswith(
        "d2spo: error: --label-mode: must be one of ['event', 'step'], got 'steps'")


@pytest.mark.parametrize("sub", ["check", "show"])
def test_env_subcommand_help_says_what_it_does_once(capsys, sub):
    """`env check --help` printed its description twice, the second time as the title of a "cmd
    options" box (a user trial, 2026-12-03)."""
    with pytest.raises(SystemExit) as e:
        cli.main(["env", sub, "--help"])
    out = capsys.readouterr().out
    first = {"check": "Validate a layout", "show": "Draw a layout"}[sub]
    assert e.value.code == 0 and out.count(first) == 1 and "cmd options" not in out, out


def test_env_show_draws_its_rollout_under_the_labelling_asked_for(tmp_path, capsys, monkeypatch):
    """`env show --label-mode step --rollout-steps N`: the rollout's env reads a letter every step (its
    episode ends where a step-labelled one would) and the title says so; without a rollout, or with a
    labelling that does not exist, one line and exit 2."""
    from d2spo import demo
    from d2spo.envs import render

    seen, titles = [], []
    make = demo.make_env
    monkeypatch.setattr(demo, "make_env", lambda cfg, **kw: seen.append(cfg.label_mode) or make(cfg, **kw))
    monkeypatch.setattr(render, "save_layout_png", lambda lay, out, title=None, **kw: titles.append(title))
    for mode in ("step", "event"):
        assert cli.main(["env", "show", "--rollout-steps", "5", "--label-mode", mode, "--out", str(tmp_path / "x.png")]) == 0
    assert seen == ["step", "event"] and titles[0].endswith("(seed 0, step labelling)") and "step" not in titles[1]
    capsys.readouterr()
    for args, says in ((["--label-mode", "step"], "--label-mode: applies to the random rollout only: give --rollout-steps N (N > 0) too"),
                       (["--label-mode", "steps", "--rollout-steps", "5"], "--label-mode: must be one of ['event', 'step'], got 'steps'")):
        assert _one_error_line(capsys, ["env", "show", *args, "--out", str(tmp_path / "y.png")]).startswith(
            f"d2spo: error: {says}")
