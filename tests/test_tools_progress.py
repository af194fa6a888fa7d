"""Progress bars and spinners (pure renderers, and the in-place line on a stream)."""

from __future__ import annotations

import io
import re
import threading
import time
from pathlib import Path

import pytest

from benchmarks.accuracy import main as accuracy_main
from bridge.cli import main
from bridge.tools import progress
from bridge.tools.progress import REDRAW_S, Progress, eta_seconds, format_duration, render_bar
from bridge.tools.recording import format_bytes

pytestmark = pytest.mark.usefixtures("restore_logging")  # main() runs in-process


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


def test_detail_block_is_redrawn_in_place_under_the_bar() -> None:
    now = [0.0]
    s = io.StringIO()
    with Progress("cal", 100, stream=s, enabled=True, clock=lambda: now[0]) as p:
        p.update(10, detail="a\nb\nc")
        now[0] += 1.0
        p.update(50, detail="x\ny")  # a shorter block: the old third row is erased
    text = s.getvalue()
    first, second = text.split("\r")[1:3]
    assert first.startswith("cal [") and first.count("\n") == 3  # bar + 3 detail rows
    # back up over the 3 rows drawn before, then bar, x, y and one erased row
    assert second.startswith("\x1b[3A") and " 50%" in second
    rows = second.split("\n")
    assert [r.replace("\x1b[K", "") for r in rows[1:4]] == ["x", "y", ""]
    assert text.endswith("\n")


@pytest.mark.integration
def test_a_ticking_spinner_turns_without_updates_and_stops_on_close() -> None:
    s = io.StringIO()
    p = Progress("fit", None, stream=s, enabled=True, tick=True)
    deadline = time.monotonic() + 5.0
    while s.getvalue().count("\r") < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    p.close()
    drawn = s.getvalue()
    assert drawn.count("\r") >= 3  # it redrew itself with nobody calling update()
    assert len({line[:6] for line in drawn.split("\r")[1:]}) >= 2  # the spinner character moved
    time.sleep(3 * REDRAW_S)
    assert s.getvalue() == drawn  # closed: the thread is gone, nothing more is written
    assert not any(t.name == "progress" for t in threading.enumerate())


@pytest.mark.integration
def test_record_shows_a_bar_with_bytes_and_stops_at_its_duration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sim.rec"
    assert (
        main(["record", "--port", "sim", "--out", str(out), "--duration", "1.5", "--progress"]) == 0
    )
    err = capsys.readouterr().err
    assert "recording [" in err and "done" in err and str(out) in err
    size = out.stat().st_size
    assert size > 0
    shown = re.findall(r"(\d+(?:\.\d+)?) (B|kB|MB) to ", err)
    assert shown and format_bytes(size) == " ".join(shown[-1])  # the final size, as on disk


@pytest.mark.integration
def test_bench_accuracy_counts_units_on_its_bar(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every update drawn: which ones a rate-limited bar shows depends on how fast the
    # machine runs the units (a fast one finishes unit 1 between two redraws).
    monkeypatch.setattr(progress, "REDRAW_S", 0.0)
    args = ["--units", "2", "--samples", "300", "--eval-samples", "100", "--timing-samples", "0"]
    accuracy_main([*args, "--progress"])
    cap = capsys.readouterr()
    assert "unit 1/2" in cap.err and "unit 2/2" in cap.err and "100%" in cap.err
    assert "accuracy [" not in cap.out  # figures on stdout, the bar on stderr


def test_format_bytes() -> None:
    assert [format_bytes(n) for n in (999, 12_345, 4_560_000)] == ["999 B", "12.3 kB", "4.56 MB"]
