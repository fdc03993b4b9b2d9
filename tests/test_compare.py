"""`d2spo compare RUN ...` (d2spo/compare.py): a user's own runs side by side, from their files."""

from __future__ import annotations

import csv
import json

import matplotlib.image
import pytest

from d2spo import cli
from d2spo.runio import EPISODE_FIELDS, VISITS_FIELD


def fake_run(path, algo, seed, collided, completed, task="phi1", layout="paper", visits=None, optimum=None,
             generalist=False):
    """A finished run's files as `d2spo train` writes them: one episode per entry of ``collided``."""
    path.mkdir(parents=True)
    fields = EPISODE_FIELDS + ((VISITS_FIELD,) if visits is not None else ())
    with open(path / "episodes.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for i, (c, d) in enumerate(zip(collided, completed)):
            w.writerow([i, float(i % 7) - 3.0, float(c), int(c), int(d), int(d), 100, 0.0, 0.0]
                       + ([visits[i]] if visits is not None else []))
    window = collided[-4:]
    summary = {"algo": algo, "seed": seed, "task": task, "layout": layout, "episodes": len(collided),
               "window": 4, "window_episodes": len(window), "safety_rate": 1 - sum(window) / len(window),
               "completion_rate": sum(completed[-4:]) / len(window), "wall_seconds": 10.0}
    if visits is not None:
        summary.update(accepting_visits_per_episode=sum(visits[-4:]) / 4, route_optimal_visits=optimum,
                       visit_fraction=sum(visits[-4:]) / 4 / optimum)
    (path / "summary.json").write_text(json.dumps(summary))
    (path / "config.json").write_text(json.dumps({"algo": algo, "generalist": generalist}))
    return path


def test_one_row_per_learner_with_the_collisions_of_all_training_episodes(tmp_path, capsys):
    """The seeds of a learner average into its row; the collisions count every training episode,
    the early ones the window (the last 4 here) does not see; the files are written."""
    a0 = fake_run(tmp_path / "d0", "d2spo", 0, [0] * 10, [0] * 6 + [1] * 4)
    a1 = fake_run(tmp_path / "d1", "d2spo", 1, [1] + [0] * 9, [0] * 7 + [1] * 3)
    b0 = fake_run(tmp_path / "t0", "td3-lag", 0, [1, 1, 1, 0, 0, 0, 0, 0, 0, 1], [0] * 10)
    out = tmp_path / "cmp"
    assert cli.main(["compare", str(a0), str(a1), str(b0), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| D²SPO | 2 | 100.00 ± 0.00 | 87.50 ± 12.50 | 0, 1 (5.00%) | 10 | 10 s |" in text, text
    assert "| LTD3 | 1 | 75.00 | 0.00 | 4 (40.00%) | 10 | 10 s |" in text, text
    rows = list(csv.DictReader(open(out / "compare.csv")))
    assert [r["learner"] for r in rows] == ["D²SPO", "LTD3"] and rows[0]["collisions_all"] == "0 1"
    assert (out / "compare.md").read_text() == text.split("wrote ")[0]
    assert matplotlib.image.imread(out / "compare.png").shape[1] > 500


def test_a_patrol_is_scored_by_its_visits_of_the_route_optimal_count(tmp_path, capsys):
    p = fake_run(tmp_path / "p", "d2spo", 0, [0] * 8, [0] * 8, task="patrol2", visits=[3, 4, 5, 6, 7, 7, 8, 8],
                 optimum=10)
    assert cli.main(["compare", str(p), "--out", "None"]) == 0
    text = capsys.readouterr().out
    assert "| visits |" in text and "| D²SPO | 1 | 100.00 | 7.50 of 10 (75.0%) |" in text, text
    assert "wrote" not in text


@pytest.mark.parametrize("case, says", [
    ("task", "runs of different tasks are not compared"), ("layout", "runs of different layouts are not compared"),
    ("limit", "runs of different episode limits are not compared"), ("twice", "given twice"),
    ("unfinished", "an unfinished run (no summary.json yet"), ("missing", "not a run directory"),
])
def test_runs_that_measure_different_things_are_one_line_exit_2(case, says, tmp_path, capsys):
    a = fake_run(tmp_path / "a", "d2spo", 0, [0] * 4, [1] * 4, task="patrol2", visits=[1] * 4, optimum=5)
    kw = {"task": "patrol3"} if case == "task" else {"layout": "relaxed"} if case == "layout" else {}
    b = fake_run(tmp_path / "b", "td3-lag", 0, [0] * 4, [1] * 4, **{"task": "patrol2", "visits": [1] * 4,
                                                                    "optimum": 6 if case == "limit" else 5, **kw})
    if case == "unfinished":
        (b / "summary.json").unlink()
    other = {"twice": a, "missing": tmp_path / "nothing"}.get(case, b)
    assert cli.main(["compare", str(a), str(other), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("d2spo: error: ") and says in err[0], err
    assert not (tmp_path / "o").exists()


def test_a_generalist_has_its_own_row(tmp_path, capsys):
    g = fake_run(tmp_path / "g", "d2spo", 0, [0] * 4, [1] * 4, generalist=True)
    s = fake_run(tmp_path / "s", "d2spo", 0, [0] * 4, [1] * 4)
    assert cli.main(["compare", str(g), str(s), "--out", "None"]) == 0
    text = capsys.readouterr().out
    assert "| D²SPO (generalist) | 1 |" in text and "| D²SPO | 1 |" in text
