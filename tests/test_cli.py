"""The command line: bad input gets one line on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from d2spo import cli, console


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "d2spo.cli", *args], capture_output=True, text=True, timeout=300
    )


def test_tyro_box_condenses_to_one_line():
    box = (
        "╭─ Value error ─────────╮\n"
        "│ Error parsing --n: bad │\n"
        "│ ────────────────────── │\n"
        "│ Argument helptext:     │\n"
        "╰────────────────────────╯\n"
    )
    assert console.tyro_error_line(box) == "Value error: Error parsing --n: bad"


def test_a_usage_error_exits_2_with_one_line_from_the_command():
    """The `d2spo` process itself: exit status 2, one line, no traceback (the cases below run
    ``cli.main`` in this process, 3.6-4.0 s less each than a new interpreter)."""
    res = run_cli("no-such-command")
    assert res.returncode == 2, res
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("d2spo: error: ")
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize(
    "args",
    [
        ["env", "show", "--rollout-steps", "many"],
        ["ltl"],
        ["train", "--task", "true", "--episodes", "1"],  # done before the first step: nothing to learn
        ["env", "check", "--task", "A1 | !A1"],
    ],
)
def test_usage_errors_exit_2_with_one_line(args, capsys):
    try:
        status = cli.main(args)
    except SystemExit as e:  # tyro's parse errors leave through SystemExit, as in the command
        status = e.code
    err = capsys.readouterr().err
    assert status == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("d2spo: error: ")
    assert "Traceback" not in err


def test_a_never_part_alone_is_refused_with_a_goal_the_formula_does_not_name(capsys):
    assert cli.main(["env", "check", "--task", "G !A4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "G !A4 asks for nothing to reach" in err[0] and "'never' part alone" in err[0], err
    assert "e.g. 'G !A4 & F A1'" in err[0]  # the formula's own never part kept (it said 'G !x & F A1')
    assert cli.main(["env", "check", "--task", "true"]) == 2  # no never part to keep
    assert "e.g. 'F A1' (with a never part: 'G !x & F A1')" in capsys.readouterr().err


def test_a_never_part_over_no_label_names_the_missing_propositions_and_the_labels(capsys):
    """`env check --task 'G !a4'` said only "nothing to reach", not that a4 labels no area of the layout."""
    assert cli.main(["env", "check", "--task", "G !a4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "G !a4 asks for nothing to reach" in err[0], err
    assert "propositions with no area, always false: ['a4']; its labels: A1, A2, A3, A4" in err[0], err
    assert "did you mean A4 for a4?" in err[0] and "layout 'paper'" in err[0]


@pytest.mark.parametrize("formula", ["true", "G !a", "A1 | !A1"])
def test_ltl_notes_a_task_with_nothing_to_reach(formula, capsys):
    """`d2spo ltl true` and `d2spo ltl 'G !a'` printed an automaton done at once, with no word that
    training refuses it."""
    assert cli.main(["ltl", formula]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{formula!r} asks for nothing to reach" in err[0], err
    goal = "'G !a & F A1'" if formula == "G !a" else "'F A1' (with a never part: 'G !x & F A1')"
    assert err[0].startswith("d2spo: warning: ") and f"add a goal, e.g. {goal}" in err[0]
    assert cli.main(["ltl", "F a"]) == 0 and not capsys.readouterr().err.strip()


def test_ltl_warns_of_operators_run_into_a_name_unless_a_label_is_so_named(tmp_path, capsys):
    """`Fb` and `GFa` parsed silently as propositions named Fb and GFa."""
    assert cli.main(["ltl", "GFa & F b | Fb"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["d2spo: warning: proposition 'Fb' looks like 'F b'; write operators apart from names (the parser "
                   "reads 'Fb' as one proposition)",
                   "d2spo: warning: proposition 'GFa' looks like 'G F a'; write operators apart from names (the "
                   "parser reads 'GFa' as one proposition)"], err
    layout = json.loads(_docs_layout_example())
    layout["areas"][0]["label"] = "Fb"  # an area of that label: no warning for it
    path = tmp_path / "fb.json"
    path.write_text(json.dumps(layout))
    assert cli.main(["ltl", "F Fb & F GFa", "--layout", str(path)]) == 0
    err = capsys.readouterr().err
    assert "'GFa' looks like 'G F a'" in err and "'Fb' looks" not in err, err


def test_a_task_built_on_a_layout_names_operators_run_into_a_label_in_its_one_error():
    """The task-building path (``make_env``: train, eval, env check) refuses a proposition that labels
    no area; where it reads as operators run into a label, the one error says how it reads apart
    (no separate warning: two lines for one mistake)."""
    import warnings

    from d2spo.envs import EnvConfig, make_env
    from d2spo.errors import ConfigError

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ConfigError, match=r"proposition 'XA4' names no area .*did you mean X A4 for XA4\?\)$"):
            make_env(EnvConfig(layout="paper"), task="F A1 & G !XA4")


def test_ltl_on_a_layout_warns_of_propositions_that_label_no_area(capsys):
    """`d2spo ltl 'F a4' --layout paper` printed the automaton with no word that a4 labels no area."""
    assert cli.main(["ltl", "F a4", "--layout", "paper"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "propositions with no area, always false: ['a4']" in err[0], err
    assert "did you mean A4 for a4?" in err[0]
    assert cli.main(["ltl", "F A4", "--layout", "paper"]) == 0 and not capsys.readouterr().err.strip()


@pytest.mark.parametrize("formula", ["false", "G false", "F A1 & G !A1", "GF A1 & G !A1"])
def test_ltl_warns_in_one_line_that_an_unsatisfiable_formula_has_no_run(formula, capsys):
    """`d2spo ltl false` printed a one-state rejecting automaton and nothing else; `d2spo train`
    refuses it. Now one warning line says so; a satisfiable formula prints none."""
    assert cli.main(["ltl", formula]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{formula!r} is unsatisfiable: no run satisfies it" in err[0], err
    assert cli.main(["ltl", formula.replace("!A1", "!A2")]) == 0
    assert ("unsatisfiable" in capsys.readouterr().err) == formula.endswith("false")


def _docs_layout_example() -> str:
    """The example layout of docs/layouts.md, verbatim (the first ```json block)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "layouts.md").read_text()
    return text.split("```json\n", 1)[1].split("```", 1)[0]


def test_env_check_needs_no_task(tmp_path, capsys):
    """The layout copied from docs/layouts.md (one area) passes `env check`; a task is checked only
    when one is given, and phi1 (A1, A2, A3) then fails with one line naming what is missing."""
    path = tmp_path / "my_lab.json"
    path.write_text(_docs_layout_example())
    assert cli.main(["env", "check", "--layout", str(path)]) == 0
    out = capsys.readouterr().out
    assert "'my-lab'" in out and "areas A1" in out and "no task checked" in out
    assert cli.main(["env", "check", "--layout", str(path), "--task", "F A1"]) == 0
    assert "task 'F A1': needs 1 area visit on this layout" in capsys.readouterr().out
    assert cli.main(["env", "check", "--layout", str(path), "--task", "phi1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "task:" in err[0] and "'A2', 'A3'" in err[0]


def test_env_check_takes_the_robot_of_a_dynamics_file_and_a_radius(tmp_path, capsys):
    """`env check` took only --preset: a user's own robot (its speed, its size) could not be checked."""
    motion = {"dt": 0.1, "v_max": 0.05, "omega_max": 1.0, "actuator_tau": 0.0, "v_gain": 1.0, "omega_gain": 1.0,
              "slip": 0.0, "noise_xy": 0.0, "noise_theta": 0.0}
    (tmp_path / "slow.json").write_text(json.dumps(motion))
    assert cli.main(["env", "check", "--layout", "paper", "--task", "F A1"]) == 0
    fast = capsys.readouterr().out
    assert cli.main(["env", "check", "--layout", "paper", "--task", "F A1", "--dynamics", str(tmp_path / "slow.json"),
                     "--robot-radius", "0.2"]) == 0
    slow = capsys.readouterr().out
    assert "a robot of radius 0.2 m fits" in slow
    limit = lambda out: int(out.split("episode limit ")[1].split()[0])  # noqa: E731
    assert limit(slow) > limit(fast)  # the slow robot's route needs more steps
    assert cli.main(["env", "check", "--layout", "paper", "--robot-radius", "2.0"]) == 2


def test_misspelled_flag_keeps_the_suggestion(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--episods", "10"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].count("Unrecognized options") == 1, err
    assert "did you mean --episodes?" in err[0]
    with pytest.raises(SystemExit):  # two typos: each gets its own, from this subcommand only (not --seeds)
        cli.main(["train", "--seeed", "1", "--episods", "3"])
    err = capsys.readouterr().err
    assert "--episodes for --episods" in err and "--seed for --seeed" in err and "--seeds" not in err


@pytest.mark.parametrize("args, says", [
    (["train", "--episodes", "0"], "d2spo: error: --episodes: must be a positive integer, got 0"),
    (["train", "--td3.batch-size=0"], "d2spo: error: --td3.batch-size: must be a positive integer, got 0"),
    (["train", "--generalist", "--generalist-layouts", "99999999"], "d2spo: error: --generalist-layouts: at most"),
])
def test_a_refused_value_is_named_by_the_flag_typed(capsys, args, says):
    """A config's refusal names its field ("td3.batch_size"); the user typed a flag ("--td3.batch-size")."""
    try:
        status = cli.main(args)
    except SystemExit as e:  # refused while tyro parses (a learner's section), or after it
        status = e.code
    assert status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(says), err


def test_a_field_not_typed_as_a_flag_keeps_its_name():
    assert console.as_typed("td3.batch_size: bad", ["train", "--td3.batch-size", "0"]) == "--td3.batch-size: bad"
    assert console.as_typed("fast: bad", ["train", "--no-fast"]) == "--no-fast: bad"
    assert console.as_typed("episodes: bad", ["train", "--config", "c.json"]) == "episodes: bad"  # from the file
    assert console.as_typed("episodes: bad", ["train", "--episodes-x", "3"]) == "episodes: bad"
    assert console.as_typed("no field here", ["train", "--episodes", "0"]) == "no field here"
    assert console.as_typed("reward.r_goal: bad", ["train", "--r-goal", "inf"]) == "--r-goal: bad"  # flattened
    # a section nested in a learner's: its check names the inner path (it read "td3.actor_lr: bad")
    assert console.as_typed("td3.actor_lr: bad", ["train", "--td3-lag.td3.actor-lr", "1e30"]) == \
        "--td3-lag.td3.actor-lr: bad"
    assert console.as_typed("td3.actor_lr: bad", ["train", "--td3-lag.td3.actor-lr=1e30"]) == \
        "--td3-lag.td3.actor-lr: bad"


@pytest.mark.parametrize("args,hint", [
    (["--cpo.target-kl", "0.02"], "(--cpo.target-kl is a flag of --algo cpo, not of --algo d2spo: "
                                  "see d2spo train --algo cpo --help)"),
    (["--algo", "td3-lag", "--cbf.d", "0.2"], "(--cbf.d is a flag of --algo d2spo or --algo sl, not of --algo "
                                              "td3-lag: see d2spo train --algo d2spo --help)"),
    (["--algo", "cpo", "--bogus", "1"], "(see d2spo train --algo cpo --help)"),  # the help that lists cpo's flags
    (["--bogus", "1"], "(see d2spo train --help)"),
])
def test_a_flag_of_another_learner_points_to_the_help_that_lists_it(capsys, args, hint):
    """`train --cpo.target-kl 0.02` (the default learner is d2spo) said "see d2spo train --help",
    whose list (d2spo's flags) does not hold it."""
    with pytest.raises(SystemExit) as e:
        cli.main(["train", *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and err[0].endswith(hint), err


def test_version(capsys):
    from d2spo import __version__

    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"d2spo {__version__}"


def test_ltl_distance_defaults_to_one_area_at_a_time(capsys):
    """phi1 needs three visits with disjoint areas; the distance over every letter (1: all three areas at
    once) is only shown when asked for, and the output says which letters the distances use."""
    def initial_distance(*flags: str) -> tuple[str, str]:
        assert cli.main(["ltl", "phi1", *flags]) == 0
        out = capsys.readouterr().out.splitlines()
        return out[2].split()[2], out[-1]

    d, note = initial_distance()
    assert d == "3" and "one area at a time" in note
    d, note = initial_distance("--all-letters")
    assert d == "1" and "every letter" in note
    d, note = initial_distance("--layout", "relaxed")  # relaxed has no A3
    assert d == "-" and "'relaxed'" in note


def test_ltl_refuses_an_unknown_label_mode_before_printing_anything(capsys):
    """As `d2spo train --label-mode` does; it once printed the automaton and went on (exit 0)."""
    assert cli.main(["ltl", "patrol2", "--label-mode", "foo"]) == 2
    seen = capsys.readouterr()
    assert seen.out == "" and seen.err.strip() == "d2spo: error: --label-mode: must be one of ['event', 'step'], got 'foo'"


@pytest.mark.parametrize("args,hint", [(["eval", "RUN", "--episodes", "abc"], "d2spo eval --help"),
                                       (["env", "show", "--bogus"], "d2spo env show --help"),
                                       (["frob"], "d2spo --help")])
def test_a_usage_error_points_to_its_subcommands_help(args, hint, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"(see {hint})"), err


def test_the_help_hints_know_every_subcommand():
    import typing

    names = {typing.get_args(a)[1].name for a in typing.get_args(cli.commands("d2spo"))}
    assert names == {"train", *cli.SUBCOMMANDS}
    from d2spo.cli_env import EnvCommands

    env = {typing.get_args(a)[1].name for a in typing.get_args(EnvCommands)}
    assert env == set(cli.ENV_SUBCOMMANDS)


def _help(args: list[str]) -> str:
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as e:
        cli.parse(args)
    assert e.value.code == 0
    return out.getvalue()


def test_train_lists_and_takes_the_flags_of_the_learner_algo_names():
    """`d2spo train --help` shows D²SPO's sections (the default --algo), not the baselines'; with
    `--algo cpo` it is the other way round; a flag of another learner is refused, not ignored."""
    d2spo, cpo = _help(["train", "--help"]), _help(["train", "--algo", "cpo", "--help"])
    assert "--cbf.gamma-exp" in d2spo and "--d2spo.pretrain" in d2spo and "--cpo." not in d2spo
    assert "--cpo.rollout-steps" in cpo and "--cbf." not in cpo and "--td3." not in cpo
    assert "--td3-lag.td3.actor-lr" in _help(["train", "--algo=td3-lag", "--help"])
    assert cli.parse(["train", "--algo", "cpo", "--cpo.rollout-steps", "512"]).config().cpo.rollout_steps == 512
    res = run_cli("train", "--algo", "td3", "--cpo.rollout-steps", "512")
    assert res.returncode == 2 and "--cpo.rollout-steps" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("what", ["deep", "long-number"])
def test_unreadable_json_is_one_line_exit_2(what, tmp_path, capsys):
    """A layout, a --dynamics file or a run's config.json nested 100 000 deep, or holding a number of
    5000 digits, is one line and exit 2, not a RecursionError or ValueError traceback."""
    text = "[" * 100_000 + "]" * 100_000 if what == "deep" else '{"arena": [' + "9" * 5000 + ', 5]}'
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text(text)
    for args in (["env", "check", "--layout", str(bad)], ["train", "--dynamics", str(bad), "--out", str(tmp_path / "o")],
                 ["eval", str(tmp_path / "run")]):
        assert cli.main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("d2spo: error:") and "JSON" in err[0], (args, err)


@pytest.mark.parametrize("args", [["env", "show", "--out", "{d}/x.txt"], ["ltl", "phi1", "--layout", "paper", "--plot", "{d}/y.docx"],
                                  ["eval", "{d}", "--plot", "{d}/z.doc"], ["env", "show", "--out", "{d}/no/x.png"]])
def test_a_picture_path_matplotlib_cannot_write_is_one_line_exit_2(args, tmp_path, capsys):
    """Checked before any work: a suffix that is no picture format, or a folder that does not exist."""
    assert cli.main([a.format(d=tmp_path) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error:") and ("picture format" in err[0] or "folder" in err[0])
    assert not list(tmp_path.glob("*.*"))  # nothing written


@pytest.mark.parametrize("extra,named", [
    (["--episodes", "100"], "--episodes"), (["--out", "OTHER"], "--out"), (["--td3.batch-size", "64"], "--td3.batch-size"),
    # a generalist's settings without --generalist (once dropped silently: the default learner does not read them)
    (["--generalist-layouts", "4", "--validation-episodes", "4"], "leave out --generalist-layouts, --validation-episodes"),
    (["--c-n", "0.05", "--max-steps", "500"], "leave out --max-steps, --c-n"),  # the env's flags, flat
    # --generalist names itself only, not the defaults it gives other fields
    (["--generalist", "--validation-layouts", "3"], "leave out --generalist, --validation-layouts"),
])
def test_resume_refuses_the_flags_its_config_json_would_override(extra, named, tmp_path, capsys):
    """`--resume DIR` continues with DIR/config.json: a training flag beside it would be ignored, so it
    is refused (one line, exit 2) instead of silently dropped."""
    assert cli.main(["train", "--resume", str(tmp_path), "--no-progress", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error: --resume:") and named in err[0], err
    if named.startswith("leave out"):
        assert err[0].endswith(named), err


def test_the_command_line_starts_without_matplotlib_or_scipy():
    """`d2spo --help`, a usage error or `d2spo ltl` need neither: they are imported where a picture
    is drawn or a layout's grid searched (start-up times: bench/RESULTS.md, "2026-11-29, night")."""
    code = "import sys, d2spo.cli; print(sorted({m.split('.')[0] for m in sys.modules} & {'matplotlib', 'scipy'}))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"


def test_ltl_plot_refuses_a_recurrence_train_refuses(tmp_path, capsys):
    """`ltl --plot` said it checks that the task can be done, but passed `GF A1`, whose "laps" are a
    step out of A1 and back: `train` and `env check` refuse it. Now it refuses it too, after the picture."""
    picture = tmp_path / "f.png"
    assert cli.main(["ltl", "GF A1", "--layout", "paper", "--plot", str(picture)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not laps" in err[0] and picture.is_file(), err
    assert cli.main(["env", "check", "--layout", "paper", "--task", "GF A1"]) == 2
    assert "not laps" in capsys.readouterr().err

