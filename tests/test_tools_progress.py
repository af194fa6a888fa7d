"""Progress bars and spinners (pure renderers, and the in-place line on a stream)."""

from __future__ import annotations

import io

from bridge.tools.progress import Progress, eta_seconds, format_duration, render_bar


def test_bar_shows_fraction_and_eta_at_the_average_rate() -> None:
    line = render_bar("fit", 25, 100, elapsed=10.0, width=20)
    assert "[#####...............]" in line and " 25%" in line
    assert "ETA 0:30" in line  # 25 % in 10 s: 30 s to go
    assert "done" in render_bar("fit", 120, 100, elapsed=1.0)  # clamped


def test_eta_and_durations() -> None:
    assert eta_seconds(0, 10, 5.0) != eta_seconds(0, 10, 5.0)  # NaN before any progress
    assert format_duration(float("nan")) == "--:--"
    assert format_duration(3725) == "1:02:05"


def test_progress_rewrites_one_line_and_ends_it() -> None:
    now = [0.0]
    s = io.StringIO()
    with Progress("bench", 4, stream=s, enabled=True, clock=lambda: now[0]) as p:
        for i in range(1, 5):
            now[0] += 1.0
            p.update(i)
    text = s.getvalue()
    assert text.count("\n") == 1 and text.endswith("\n")
    assert text.count("\r") >= 4 and "100%" in text


def test_progress_is_silent_on_a_pipe() -> None:
    s = io.StringIO()  # not a tty
    with Progress("record", None, stream=s) as p:
        p.update(note="x")
    assert s.getvalue() == ""
