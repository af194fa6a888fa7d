"""The console's pure parts: the line's truth and reference, quiet in the background, the gate
that holds log lines, the state directory's clean-up, the calibration's progress texts."""

from __future__ import annotations

import io
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from waiting import wait_for

from bridge.app.sample import CompassSample, DaemonStatus
from bridge.console import ConsoleOutput, TerminalGate, format_line
from bridge.events import Event
from bridge.mavlink.commands import CalibrationRelay
from bridge.protocol.device import LinkCounters, LinkState
from bridge.storage import StateStore
from bridge.tools.calhelp import PlainProgress, is_progress_text, no_bridge_hint
from bridge.types import HeadingReference

DEADLINE_S = 10.0


def _status() -> DaemonStatus:
    return DaemonStatus("sim", LinkState.STREAMING, LinkCounters(attitude_frames=9), 9, 0, "x")


def _sample(
    hdg: float, ref: HeadingReference = "magnetic", device: float | None = 321.2
) -> CompassSample:
    return CompassSample(
        0.0,
        "host",
        hdg,
        ref,
        hdg,
        None,
        None,
        0.1,
        0.1,
        seq=8,
        device_heading_deg=device,
    )


def test_the_line_shows_the_truth_and_how_far_off_in_the_published_reference() -> None:
    line = format_line(_sample(5.52), _status(), truth_deg=5.5)
    assert "[host, device hdg 321.2 mag]  tilt device  [sim truth   5.5 mag, off  +0.0]" in line
    assert "off -44.3]" in format_line(_sample(321.2), _status(), truth_deg=5.5)  # wraps at 360
    # BRG_HDG_REF = 1: the heading is true; the device's own stays magnetic, and says so
    true = format_line(_sample(155.1, "true", 160.2), _status(), truth_deg=155.3)
    assert true.startswith("hdg 155.1 true  pitch")
    assert "device hdg 160.2 mag]  tilt device  [sim truth 155.3 true, off  -0.2]" in true
    assert "sim truth" not in format_line(_sample(5.5), _status())  # a real compass: no truth


def _wait(cond: Callable[[], object], what: str) -> None:
    wait_for(cond, what, DEADLINE_S)


@pytest.mark.integration
def test_in_the_background_the_console_says_its_intro_then_holds_everything() -> None:
    fg = [False]
    out = io.StringIO()
    err = io.StringIO()
    gate = TerminalGate(err, foreground=lambda: fg[0])
    con = ConsoleOutput(
        _status,
        out,
        tty=True,
        interval=0.02,
        intro="Simulated compass",
        foreground=lambda: fg[0],
        gate=gate,
    )
    gate.write("start-up warning\n")  # before the first update: out at once
    con.start()
    con.publish(_sample(10.0))
    _wait(lambda: "Simulated compass\n" in out.getvalue(), "the intro")
    time.sleep(0.1)
    con.note("Calibration accepted and saved: ~/x/calibration.json")
    gate.write("a log line\n")
    time.sleep(0.2)
    assert out.getvalue() == "Simulated compass\n"  # no live line, no note in the background
    assert err.getvalue() == "start-up warning\n"  # the log line is held
    fg[0] = True  # fg
    _wait(lambda: "\rhdg  10.0 mag" in out.getvalue(), "the live line")
    text = out.getvalue()
    assert text.index("Calibration accepted and saved") < text.index("\rhdg")
    assert err.getvalue() == "start-up warning\na log line\n"
    fg[0] = False
    gate.write("held until the end\n")
    con.close(2.0)
    gate.release_all()
    assert err.getvalue().endswith("held until the end\n")


def test_the_gate_bounds_what_it_holds_and_says_what_it_lost() -> None:
    err = io.StringIO()
    gate = TerminalGate(err, foreground=lambda: False, limit=20)
    gate.close_in_background()
    for i in range(5):
        gate.write(f"line {i}\n")
    gate.release_all()
    assert err.getvalue() == "line 0\nline 1\n(3 more lines written in the background lost)\n"


def test_clear_removes_only_the_stores_documents(tmp_path: Path) -> None:
    store = StateStore(tmp_path / "s")
    assert store.clear() == []  # no directory yet: nothing to do
    store.save("calibration", {"a": 1})
    store.save("calibration", {"a": 2})  # makes calibration.json.prev
    store.save("params", {"set": {}})
    (tmp_path / "s" / "params.json.tmp").write_text("interrupted")
    (tmp_path / "s" / "mine.txt").write_text("keep")
    (tmp_path / "s" / "not a name.json").write_text("keep")
    removed = sorted(p.name for p in store.clear())
    assert removed == [
        "calibration.json",
        "calibration.json.prev",
        "params.json",
        "params.json.tmp",
    ]
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["mine.txt", "not a name.json"]
    assert store.load("calibration").payload is None


def _progress(pct: float, attempt: int = 1) -> Event:
    data = {"mode": "mag", "sensor": "mag", "completion_pct": pct, "attempt": attempt}
    return Event("calibration.progress", f"Calibration {pct:.0f}%", data=data)


def _texts(relay: CalibrationRelay, events: list[Event]) -> list[str]:
    out = []
    for e in events:
        out += [m.text for m in relay.packets(e) if m.get_type() == "STATUSTEXT"]
    return out


def test_a_statustext_every_20_percent_outside_the_px4_flow() -> None:
    relay = CalibrationRelay()
    relay.begin("ardupilot")
    pcts = [0, 3, 15, 21, 22, 39, 47, 61, 75, 79, 86, 99, 100]
    assert _texts(relay, [_progress(p) for p in pcts]) == [
        "Mag calibration 20%: keep turning it",
        "Mag calibration 40%: keep turning it",
        "Mag calibration 60%: keep turning it",
        "Mag calibration 80%: keep turning it",
    ]
    relay.begin(None)  # started elsewhere (zenoh, the CLI): relayed ArduPilot-style, afresh
    assert _texts(relay, [_progress(45)]) == ["Mag calibration 40%: keep turning it"]
    relay.begin("px4")  # PX4's own lines instead
    assert _texts(relay, [_progress(45)]) == ["[cal] progress <45>"]
    assert is_progress_text("Mag calibration 40%: keep turning it")
    assert not is_progress_text("Too much motion: turn slower / steadier")


def test_piped_progress_lines_and_the_hint() -> None:
    out = io.StringIO()
    p = PlainProgress(out)
    for pct, missing in ((0, 80), (5, 70), (21, 40), (22, 39), (65, 3)):
        p.progress(pct, missing)
    p.text("Too much motion: turn slower / steadier")
    p.text("Too much motion: turn slower / steadier")
    p.text("Mag calibration 60%: keep turning it")
    p.progress(67, 2)
    p.again()  # the bridge's reminder: no step passed for a while, still working
    assert out.getvalue().splitlines() == [
        "calibrating: 0% (80 of 80 sphere sections still missing)",
        "calibrating: 20% (40 of 80 sphere sections still missing)",
        "calibrating: 60% (3 of 80 sphere sections still missing)",
        "bridge: Too much motion: turn slower / steadier",
        "calibrating: 67% (2 of 80 sphere sections still missing)",
    ]
    assert "'udpout:10.0.0.2:14551' in mavlink.endpoints" in no_bridge_hint("udpin:10.0.0.2:14551")
    assert "'tcpin:127.0.0.1:5760' in mavlink.endpoints" in no_bridge_hint("tcp:127.0.0.1:5760")


def test_a_calibration_that_does_not_move_on_is_still_said_every_15_s() -> None:
    """A unit turned level only never reaches 20 %: MAVProxy must not stay silent."""
    from bridge.calibration.sessions.snapshot import CalibratorSnapshot
    from bridge.calibration.sessions.state import Phase
    from bridge.mavlink.commands import PROGRESS_TEXT_REMIND_S

    t = [100.0]
    relay = CalibrationRelay(clock=lambda: t[0])
    relay.begin("ardupilot")
    snap = CalibratorSnapshot(
        mode="mag", phase=Phase.COLLECTING, step=1, running=True, attempt=1,
        completion_pct=3.4, completion_mask=bytes(10), direction=(0.0, 0.0, 1.0),
        onboard=False, faces_done=(), report=None, pending_accept=False,
        calibration_source="none (identity)", calibration_age_s=None, calibration_saved=False,
    )  # fmt: skip

    def texts_at(now: float) -> list[str]:
        t[0] = now
        msgs = relay.keepalive(now, lambda: snap)
        assert msgs[0].get_type() == "MAG_CAL_PROGRESS"  # as before, every time
        return [m.text for m in msgs if m.get_type() == "STATUSTEXT"]

    said = [(now, texts_at(now)) for now in (100.0 + 0.5 * i for i in range(1, 81))]
    reminders = [now for now, texts in said if texts]
    assert reminders == [100.0 + PROGRESS_TEXT_REMIND_S, 100.0 + 2 * PROGRESS_TEXT_REMIND_S]
    assert said[29][1] == ["Mag calibration 3%: keep turning it"]
    relay.begin("px4")  # QGroundControl has its progress bar from the [cal] lines
    assert texts_at(200.0) == [] and texts_at(230.0) == []
