"""What the command line shows, from data alone (no training): the eval and certify tables, and
the evaluation file ``d2spo eval`` writes."""

from __future__ import annotations

import io
import json

import pytest
from rich.console import Console

from d2spo.console import print_certify, print_evaluation, print_repair_round
from d2spo.errors import NaNError
from d2spo.evalfiles import evaluation_path, number_tag, write_evaluation
from d2spo.evaluate import dynamics_label


def _res(run: str, per: list[tuple[str, float]], runtime_filter=None) -> dict:
    rows = [{"layout": lay, "safety_rate": s, "completion_rate": 0.5, "mean_return": 1.25, "mean_distance": 2.0}
            for lay, s in per]
    mean = {k: sum(r[k] for r in rows) / len(rows) for k in ("safety_rate", "completion_rate", "mean_return",
                                                              "mean_distance")}
    return {"run": run, "episodes": 4 * len(rows), "layout": per[0][0], "dynamics": "default-slip0.2",
            "runtime_filter": runtime_filter, "filter_alpha": 1.5 if runtime_filter is not None else None,
            "filter_iters": 5 if runtime_filter is not None else None, "per_layout": rows, **mean}


def test_evaluation_is_named_written_and_shown(tmp_path, capsys):
    one = _res(str(tmp_path), [("paper", 1.0)])
    assert evaluation_path(tmp_path, one) == tmp_path / "eval-paper-default-slip0.2.json"
    three = _res(str(tmp_path), [("random:0", 1.0), ("random:1", 0.75), ("random:2", 1.0)], runtime_filter=True)
    assert evaluation_path(tmp_path, three).name == "eval-random0x3-default-slip0.2-filter-a1.5-i5.json"
    # numbers as :g writes them where that reads back exactly; two that agree to six digits stay apart
    assert [number_tag(x) for x in (1.2, 0.05, 2.0, float("inf"), 1e-7)] == ["1.2", "0.05", "2", "inf", "1e-07"]
    near = evaluation_path(tmp_path, {**three, "filter_alpha": 1.5000001})
    assert near.name == "eval-random0x3-default-slip0.2-filter-a1.5000001-i5.json"
    assert dynamics_label(None, {"slip": 0.2, "v_gain": 0.8500001}, "default") == "default-slip0.2-v_gain0.8500001"

    path = write_evaluation(tmp_path, three)
    assert json.loads(path.read_text()) == three
    print_evaluation(three, path, filter_asked=None)
    out = capsys.readouterr().out
    assert out.rstrip().endswith(f"wrote {path}")
    out = " ".join(out.split())  # the title is wrapped to the table's width
    assert "runtime filter on (not the training layout/dynamics" in out
    assert "random:1" in out and "75.00%" in out and "all 3" in out and "91.67%" in out
    # the episode limit is shown whether asked or not (other dynamics change the default one)
    print_evaluation({**one, "max_steps": 300}, path, filter_asked=None)
    assert "(4 episodes of 300 steps" in " ".join(capsys.readouterr().out.split())
    print_evaluation({**three, "max_steps": 450}, path, filter_asked=None)
    assert "episodes of up to 450 steps" in " ".join(capsys.readouterr().out.split())
    print_evaluation(three, path, filter_asked=True)  # asked for: no note on why it is on
    assert "not the training" not in " ".join(capsys.readouterr().out.split())
    # a generalist's: on everywhere, its own training layouts too; and the task it ran is named
    print_evaluation({**three, "generalist": True, "task": "phi1"}, path, filter_asked=None)
    out = " ".join(capsys.readouterr().out.split())
    assert "runtime filter on (a generalist's default;" in out and "task 'phi1'" in out and "zero-shot" not in out


def test_a_patrol_on_one_layout_shows_the_count_that_keeps_the_margin(tmp_path, capsys, monkeypatch):
    """docs/ltl.md: a patrol's row shows the route-optimal count keeping the barrier's margin where it
    differs, on one layout as on several (the one-layout row is built from the mean's fields)."""
    monkeypatch.setenv("COLUMNS", "200")  # rich's width: the cell on one line
    one = _res(str(tmp_path), [("paper", 1.0)])
    layout = {"route_optimal_visits": 10, "route_optimal_visits_margin": 8, "margin": 0.3, "visit_fraction": 0.5,
              "accepting_visits_per_episode": 5.0}
    one["per_layout"][0].update(layout)
    one.update(accepting_visits_per_episode=5.0, visit_fraction=0.5)
    print_evaluation(one, tmp_path / "e.json", filter_asked=None)
    assert "5.00 of 10 (50.0%; 8 keeping 0.3 m)" in capsys.readouterr().out
    one["per_layout"][0]["route_optimal_visits_margin"] = 10  # the same count: not repeated
    print_evaluation(one, tmp_path / "e.json", filter_asked=None)
    out = capsys.readouterr().out
    assert "5.00 of 10 (50.0%)" in out and "keeping" not in out


def test_a_non_finite_evaluation_leaves_the_earlier_file(tmp_path):
    good = _res(str(tmp_path), [("paper", 1.0)])
    path = write_evaluation(tmp_path, good)
    bad = dict(good, mean_return=float("nan"))
    with pytest.raises(NaNError, match="non-finite rates"):
        write_evaluation(tmp_path, bad)
    assert json.loads(path.read_text()) == good


def test_certify_summary_is_shown():
    net = {"points": 10, "certified": 0.9, "not_certified": 0.1, "violated": 0.0, "worst_margin": 0.01,
           "max_h": -0.5, "min_e": 0.2}
    s = {"run": "RUN", "seconds": 3.0, "nets": {"X_L": net, "grid_L": dict(net, violated=0.1), "P_exp": net,
                                                 "grid_D": dict(net, points=0)},
         "residual": {"transitions": 64, "rho_h": 0.0123, "quantile": 0.99, "features_m": {"p50": 0.5, "max": 1.5}},
         "counterexamples": {"L": [{"counterexample": True, "pose": [1.0, 2.0, 0.0], "h": 0.3}],
                             "D": [{"counterexample": False, "pose": [0.0, 0.0, 0.0], "e": 0.1}]}}
    buf = io.StringIO()
    console = Console(file=buf, width=200)
    print_certify(console, s)
    print_repair_round(console, {"round": 2, "certified_L": 0.95, "certified_D": 0.5, "grid_L_violated": 3,
                                 "grid_D_violated": 0}, 10)
    out = buf.getvalue()
    assert "RUN: Propositions 1-2 (3 s)" in out and "90.00%" in out and "h = -0.5" in out
    assert "ρ_h = 0.0123" in out and "pose [1.0, 2.0, 0.0] with h = 0.3 (1 of the worst 1 found)" in out
    assert "gradient search in D: no counterexample found" in out
    assert "round 2: certified ℒ 95.00%, D 50.00%, violated grid points: 3 (Prop. 1), 0 (Prop. 2, explored)" in out
    assert "between its points" not in out  # the ring's grid has violated points: red, not flagged
    # a ring grid with none violated, but a counterexample found by the search: flagged on its row
    buf = io.StringIO()
    print_certify(Console(file=buf, width=220), {**s, "nets": {**s["nets"], "grid_L": net}})
    assert "grid: ring + contact (a counterexample between its points: below)" in buf.getvalue()


def test_the_eval_table_fits_a_log_s_80_columns(tmp_path, capsys, monkeypatch):
    """In a log (80 columns) the table cut "completion_rate" and a layout file's path to "/tmp/trial_wo…":
    its headings are words, and a file's row is its name (the title keeps the path)."""
    monkeypatch.setenv("COLUMNS", "80")
    res = _res(str(tmp_path), [(str(tmp_path / "a" / "long" / "folder" / "my_lab.json"), 1.0)])
    print_evaluation(res, tmp_path / "e.json", filter_asked=None)
    out = capsys.readouterr().out
    assert "│ my_lab.json " in out and "completed" in out and "…" not in out.split("┏")[1], out
