"""The figures of `d2spo reproduce` (``d2spo.plots``), drawn from run directories: the reward
curves of Figs. 2-3 against known returns, and Figs. 4-5 from one short D²SPO run with snapshots."""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest
from _reproduce import FIG5_EPISODES
from matplotlib.image import imread

from d2spo import plot_outcomes, plots
from d2spo import reproduce as rp


def png_dpi(path) -> int:
    """The resolution a PNG records (its pHYs chunk), in dots per inch."""
    from PIL import Image

    return round(Image.open(path).info["dpi"][0])


def test_reward_curves_are_moving_averages_with_a_band_over_seeds(tmp_path):
    """Fig. 2 reads episodes.csv of the table runs: the curve is the moving-average return, mean over
    seeds, with a ± 1 std band. Run directories with known returns stand in for trained runs."""
    from d2spo.runio import EPISODE_FIELDS

    out = tmp_path / "r"
    specs = rp.runs_for("table3", 2, 50, ["ppo-lag"])
    for s, offset in zip(specs, (0.0, 2.0)):
        d = rp.run_dir(out, s)
        d.mkdir(parents=True)
        rows = [(i, float(i) + offset, 0.0, 0, 0, 0, 200, 0.0, 0.0) for i in range(50)]
        with open(d / "episodes.csv", "w", newline="") as f:
            csv.writer(f).writerows([EPISODE_FIELDS, *rows])
    dirs = [rp.run_dir(out, s) for s in specs]
    x, mean, std, seeds = plots.reward_curves({"LPPO": dirs}, smooth=5)["LPPO"]
    assert seeds == 2
    assert len(x) == len(mean) == 46 and x[0] == 5
    np.testing.assert_allclose(mean, np.arange(46) + 2.0 + 1.0)  # mean of i..i+4, plus the mean offset 1
    np.testing.assert_allclose(std, 1.0)  # the two seeds differ by 2 everywhere
    _, _, one_std, _ = plots.reward_curves({"LPPO": dirs[:1]}, smooth=5)["LPPO"]
    assert np.all(one_std == 0)  # one seed: no spread
    assert plots.reward_curves({"LPPO": [tmp_path / "missing"], "x": []}) == {}  # no episodes: no curve
    path = rp.render("fig2", out, 2, 50, ["ppo-lag"])
    assert path == out / "fig2.png" and png_dpi(path) == 300
    assert imread(path).shape[1] > 0.9 * 9.0 * 300  # two panels of 4.5 in, cropped to what is drawn
    # a run shorter than the default width of 200 still gets a curve: a fifth of it per window,
    # each point placed at the end of its window (not at 200 + i)
    x, mean, _, _ = plots.reward_curves({"LPPO": dirs})["LPPO"]
    assert len(x) == 41 and x[0] == 10 and x[-1] == 50
    np.testing.assert_allclose(mean[0], np.mean(np.arange(10)) + 1.0)


def test_figs_4_and_5_render_from_one_short_d2spo_run(tmp_path, short_d2spo_run):
    """Fig. 5 from a run with policy snapshots (tests/conftest.py's short D²SPO run, which
    tests/test_d2spo.py checks), standing in for the Fig. 5 run, then Fig. 4 from the same run
    standing in for the first physical layout's (the others are drawn as 'not run'): one training
    serves both, and the figures draw the snapshots and the final checkpoint."""
    out = tmp_path / "r"
    (f5,) = rp.runs_for("fig5", 1, FIG5_EPISODES)
    assert f5.snapshots == (3, 16, 32)
    run, _, _ = short_d2spo_run
    shutil.copytree(run, rp.run_dir(out, f5))
    for n in f5.snapshots:
        assert (rp.run_dir(out, f5) / f"policy-{n}.msgpack").is_file()
    fig5 = rp.render("fig5", out, 1, FIG5_EPISODES)
    height, width, _ = imread(fig5).shape  # the layout and three snapshots, 4 in each at 300 dpi, a legend below
    assert png_dpi(fig5) == 300 and width > 0.9 * 16 * 300 and 0.9 * 4 * 300 < height < width / 2
    assert fig5.stat().st_size > 20_000
    f4 = rp.runs_for("fig4", 1, 200)
    assert f4[0].episodes == 20 and f4[0].layout == "physical-1"
    shutil.copytree(rp.run_dir(out, f5), rp.run_dir(out, f4[0]))
    fig4 = rp.render("fig4", out, 1, 200)
    height, width, _ = imread(fig4).shape  # surfaces over level sets, four layouts, one colourbar
    assert png_dpi(fig4) == 300 and width > 0.9 * 16 * 300 and height > 0.9 * 8 * 300
    assert fig4.stat().st_size > 20_000


def test_fig5_of_a_run_without_snapshots_is_refused(tmp_path):
    """It once drew the layout alone under a legend of trajectory marks it never drew."""
    from d2spo.config import TrainConfig
    from d2spo.errors import RunDirError
    from d2spo.run import prepare_dir

    run = tmp_path / "run"
    run.mkdir()
    prepare_dir(run, TrainConfig(), resume=False)
    with pytest.raises(RunDirError, match="trained without policy snapshots"):
        plots.snapshot_figure(tmp_path / "fig5.png", run)
    assert not (tmp_path / "fig5.png").exists()


def test_a_rejected_episode_is_told_from_one_out_of_time():
    """An episode the task rejected (a 'never' part broken) ended early, safe and not complete; the
    plot drew it as 'out of time' and no number counted it (a trial's lab: 6 of 20 episodes)."""
    from d2spo.rollout import rates

    nan = np.full(3, np.nan)
    poses = np.zeros((4, 6, 3))  # T + 1 = 6 poses: the last is NaN when the episode ended earlier
    poses[0, 3:], poses[1, 4:], poses[2, 5:] = nan, nan, nan
    collided, completed = np.array([True, False, False, False]), np.array([False, True, False, False])
    assert plot_outcomes.outcomes(poses, collided, completed) == ["collided", "completed", "rejected", "neither"]
    length = np.array([2, 3, 4, 5])
    r = rates(collided, completed, np.zeros(4), length, poses, max_steps=5)
    assert r["rejection_rate"] == 0.25 and "rejection_rate" not in rates(collided, completed, np.zeros(4), length)
    names = [h.get_label() for h in plot_outcomes.outcome_handles(drawn={"rejected"})]
    assert "trajectory: the task rejected it (what it forbids entered) (x: end)" in names
    assert not any("rejected" in h.get_label() for h in plot_outcomes.outcome_handles())  # no mark that is not drawn
