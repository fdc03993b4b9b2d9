"""The console side of training: a live bar on a terminal that keeps the episode count and the ETA at
80 columns, plain periodic lines in a log, and the compilation visible in both."""

from __future__ import annotations

import io

from rich.console import Console

from d2spo import progress


def chunk(episodes: int, wall: float) -> dict:
    return {"episodes": episodes, "total": 1000, "env_steps": 10 * episodes, "wall_seconds": wall,
            "safety_rate": 0.9, "completion_rate": 0.25, "completion_rate_relaxed": 0.5}


def test_bar_keeps_count_and_eta_at_80_columns():
    console = Console(file=io.StringIO(), width=80, force_terminal=True, color_system=None)
    display = progress.progress_display(console, show=True)
    assert isinstance(display, progress._Bars)
    clock = [0.0]
    display.bar.get_time = lambda: clock[0]
    on_event = display.add("tlgrl (!A2 U A1) & F A…", 1000)

    def screen() -> list[str]:
        console.file = io.StringIO()
        console.print(display.bar.get_renderable())
        return console.file.getvalue().splitlines()

    on_event({"phase": "compiling", "episodes": 0, "total": 1000})
    top, below = screen()
    assert "0/1000 episodes" in top and "compiling" in below
    on_event({"phase": "compiled", "compile_seconds": 12.0, "episodes": 0, "total": 1000})
    clock[0] = 20.0
    on_event(chunk(100, 8.0))
    clock[0] = 30.0
    on_event(chunk(200, 18.0))  # 10 episodes/s: 800 left -> 80 s
    top, below = screen()
    assert len(top) <= 80 and "200/1000 episodes" in top and "eta 0:01:20" in top, top
    assert "safe 90.0%" in below and "done 25.0%" in below


def test_plain_lines_when_not_a_terminal(monkeypatch):
    out = io.StringIO()
    display = progress.progress_display(Console(file=out, force_terminal=False), show=True)
    assert isinstance(display, progress._Lines)
    clock = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: clock[0])
    on_event = display.add("tlgrl relaxed", 1000)
    on_event({"phase": "compiling", "episodes": 0, "total": 1000})
    clock[0] = 12.0
    on_event({"phase": "compiled", "compile_seconds": 12.0, "episodes": 0, "total": 1000})
    for t, n in ((22.0, 20), (40.0, 280), (52.0, 400), (70.0, 580), (112.0, 1000)):
        clock[0] = t
        on_event(chunk(n, t - 12.0))
    on_event({"phase": "evaluating", "episodes": 100})
    lines = out.getvalue().splitlines()
    assert lines[0] == "tlgrl relaxed: compiling the learner (once per run)…"
    assert lines[1] == "tlgrl relaxed: compiled in 12.0 s; training 1000 episodes"
    # the first chunk, then a line once 30 s have passed since the last one (not at 40 s or 70 s), and the last
    assert [ln.split(": ")[1].split()[0] for ln in lines[2:5]] == ["20/1000", "400/1000", "1000/1000"]
    # the first chunk ends few episodes (all started together): no ETA from them (2 ep/s, 8 min)
    assert "0:00:22, eta …, 2.0 ep/s" in lines[2]
    # then the pace since that line: 380 episodes in 30 s, 600 left, 47 s (not 60 s at 10 ep/s since compiled)
    assert "0:00:52, eta 0:00:47, 12.7 ep/s" in lines[3]
    assert lines[5] == "tlgrl relaxed: evaluating the final policy (100 episodes)…" and len(lines) == 6
    assert "1000/1000 episodes (100%), 0:01:52, eta 0:00:00," in lines[4]


def test_plain_lines_eta_when_a_run_ends_at_once_or_no_episode_ends(monkeypatch):
    """A run whose first line is its last (a short run, or a resumed one near its end) says eta 0:00:00,
    not ``…``; a line after which no episode ended gives no ETA from the first chunk's few episodes."""
    clock = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: clock[0])

    def lines_of(start: int, chunks) -> list[str]:
        out = io.StringIO()
        clock[0] = 0.0
        on_event = progress.progress_display(Console(file=out, force_terminal=False), show=True).add("x", 1000)
        on_event({"phase": "compiling", "episodes": start, "total": 1000})
        clock[0] = 10.0
        on_event({"phase": "compiled", "compile_seconds": 10.0, "episodes": start, "total": 1000})
        for t, n in chunks:
            clock[0] = t
            on_event(chunk(n, t - 10.0))
        return out.getvalue().splitlines()[2:]

    for start in (0, 990):
        assert [ln.split(", ")[2] for ln in lines_of(start, [(15.0, 1000)])] == ["eta 0:00:00"]
    stalled = lines_of(0, [(15.0, 20), (50.0, 20), (90.0, 60)])
    assert [ln.split(", ")[2] for ln in stalled] == ["eta …", "eta …", "eta 0:29:22"]  # 40 in 75 s since the first: 940 left


def test_a_patrols_line_shows_visits_and_no_completion():
    """A recurrence completes no episode: its line shows safety and visits, not 'done 0.0%'."""
    reach = progress._stats({"safety_rate": 1.0, "completion_rate": 0.5, "completion_rate_relaxed": 0.5}, 2.0)
    assert reach == "2.0 ep/s · safe 100.0% · done 50.0% (relaxed 50.0%)"
    never = progress._stats({"safety_rate": 1.0, "completion_rate": 0.5, "completion_rate_relaxed": 0.5,
                             "accepting_visits": 0.5}, 2.0)  # `reach-never`: a Büchi task that completes
    assert "visits 0.50/ep" in never and "done 50.0%" in never
    patrol = progress._stats({"safety_rate": 0.99, "completion_rate": 0.0, "completion_rate_relaxed": 0.0,
                              "accepting_visits": 3.25, "recurrence": True}, 2.0)
    assert patrol == "2.0 ep/s · safe 99.0% · visits 3.25/ep"


def test_the_line_names_its_window_and_the_rejected_share():
    d = {"safety_rate": 1.0, "completion_rate": 0.5, "completion_rate_relaxed": 0.5, "window_episodes": 200,
         "rejection_rate": 0.25}
    assert progress._stats(d, 2.0) == "2.0 ep/s · last 200: safe 100.0% · done 50.0% (relaxed 50.0%) · rejected 25.0%"
    assert "rejected" not in progress._stats({**d, "rejection_rate": 0.0}, 2.0)


def test_the_summary_table_shows_the_rejected_share_only_when_some_were():
    base = {"episodes": 300, "env_steps": 3000, "wall_seconds": 1.0, "env_steps_per_second": 3000.0,
            "safety_rate": 1.0, "completion_rate": 0.5, "completion_rate_relaxed": 0.5, "window_episodes": 300}
    def text(summary):
        out = io.StringIO()
        Console(file=out, width=200).print(progress.summary_table(summary, "t"))
        return out.getvalue()
    assert "rejected by the task (last 300)" in text({**base, "rejection_rate": 0.21})
    assert "21.00%" in text({**base, "rejection_rate": 0.21})
    assert "rejected" not in text({**base, "rejection_rate": 0.0}) and "rejected" not in text(base)


def test_no_progress_prints_nothing():
    display = progress.progress_display(Console(file=io.StringIO()), show=False)
    with display:
        assert display.add("x", 10) is None


def test_ctrl_c_in_training_says_how_to_resume_where_a_checkpoint_is(tmp_path, monkeypatch, capsys):
    """`d2spo train` stopped by Ctrl-C: one line, exit 130, and where a checkpoint was written the
    command that continues from it (without one, the plain line)."""
    from d2spo import cli

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(progress, "train", stopped)
    args = ["train", "--task", "F A1", "--layout", "relaxed", "--no-progress", "--out", str(tmp_path / "run")]
    assert cli.main(args) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["d2spo: error: interrupted"]
    monkeypatch.setattr(progress, "has_checkpoint", lambda out: True)
    assert cli.main(args) == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        f"d2spo: error: interrupted; `d2spo train --resume {tmp_path / 'run'}` continues from its last checkpoint"]
