"""``python -m benchmarks fuzz``: a tiny run against a real daemon, and its judges."""

from __future__ import annotations

import json
import logging
import math
import random
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from benchmarks.__main__ import main as benchmarks_main
from benchmarks.fuzz import Effects, MavlinkFuzz, SerialFuzz, false_frames, main, palette
from bridge.protocol.gmr import AttitudeFrame, GmrDecoder


@pytest.mark.integration
def test_small_run_against_the_daemon_finds_nothing(tmp_path: Path) -> None:
    """A daemon that crashed, leaked a traceback, decoded a false frame, changed state no
    message asked for or grew by 16 MB fails this run (each is a figure that must be 0)."""
    out = tmp_path / "fuzz.json"
    code = main(
        ["--chunks", "4000", "--messages", "600", "--json", str(out), "--no-progress",
         "--angles", "none"]
    )  # fmt: skip
    doc = json.loads(out.read_text())
    figs = {f["name"]: f for f in doc["figures"]}
    assert set(figs) == {"false_frames", "crashes", "tracebacks", "state_changes", "memory_growth"}
    assert figs["false_frames"]["detail"]["valid_frames_sent"] > 500
    assert figs["false_frames"]["detail"]["attitude_checked"] > 0  # the judge saw ATTITUDE
    assert figs["crashes"]["detail"]["answers_param_read"] is True
    for name in ("false_frames", "crashes", "tracebacks", "state_changes"):
        assert figs[name]["value"] == 0, figs[name]
    assert figs["memory_growth"]["passed"] is True, figs["memory_growth"]
    assert code == 0 and doc["passed"] is True


#: Each round-two angle: the figures that must be 0 (small sizes here; the defaults: 1000
#: datagrams/s, 50 clients, 100 queries, 3000 sets/s).
ROUND_TWO = {
    "crowd": ("crowd_tracebacks",),
    "zenoh": ("zenoh_not_bad_arguments", "zenoh_tracebacks"),
    "silent": ("silent_said_streaming", "silent_flaps", "silent_tracebacks"),
    "late": ("late_device_resets", "late_commands_resent", "late_left_calibrating",
             "late_tracebacks"),
    "params": ("params_lost_at_shutdown", "params_tracebacks"),
}  # fmt: skip


@pytest.mark.integration
@pytest.mark.parametrize("angle", sorted(ROUND_TWO))
def test_the_round_two_angles_print_their_figures(tmp_path: Path, angle: str) -> None:
    """Many-peer junk with a TCP crowd, oversized Zenoh arguments, a silent and a late
    compass, a PARAM_SET storm: each against its own daemon, each a figure. One angle a test,
    so the angles (seconds of real time each) run side by side."""
    out = tmp_path / "fuzz2.json"
    main(
        ["--chunks", "10", "--messages", "10", "--angles", angle,
         "--junk-rate", "300", "--tcp-crowd", "10", "--oversized", "30", "--angle-seconds", "3", "--set-rate", "1000",
         "--json", str(out), "--no-progress"]
    )  # fmt: skip
    figs = {f["name"]: f for f in json.loads(out.read_text())["figures"]}
    for name in ROUND_TWO[angle]:
        assert figs[name]["value"] == 0, figs[name]
    if angle == "crowd":
        assert figs["crowd_gcs_attitude"]["value"] is not None  # measured (its bound: a test of
        assert figs["crowd_tcp_newcomer_wait"]["value"] is not None  # its own, without load)
    elif angle == "zenoh":
        assert figs["zenoh_not_bad_arguments"]["detail"]["answered_bad_arguments"] > 0
    elif angle == "silent":
        assert figs["silent_said_streaming"]["detail"]["zenoh_status_docs"] > 0
    elif angle == "late":
        assert figs["late_device_resets"]["detail"]["late_answers"] >= 1
    else:
        assert figs["params_writes_per_s"]["passed"] is True, figs["params_writes_per_s"]


def test_false_frame_judge_counts_what_was_never_sent() -> None:
    bins = {round(0.5 * 1000): [(0.01, -0.02, 0.5)], round(-math.pi * 1000): [(0.0, 0.0, -math.pi)]}
    sent = [(0.01, -0.02, 0.5), (0.0, 0.0, math.pi)]  # +pi is -pi: the same heading
    assert false_frames(sent, bins) == 0
    assert false_frames([(0.01, -0.02, 0.51), (0.2, -0.02, 0.5)], bins) == 2


def test_serial_fuzz_mixes_valid_frames_with_damage() -> None:
    gen = SerialFuzz(random.Random(3))
    chunks = [gen.chunk() for _ in range(3000)]
    dec = GmrDecoder()
    frames = [f for c in chunks for f in dec.feed(c) if isinstance(f, AttitudeFrame)]
    assert 500 < len(frames) < 1500  # about a quarter are valid frames
    assert dec.counters.dropped.total > 500  # and plenty is not
    assert {(f.mx, f.my, f.mz, f.ax, f.ay, f.az) for f in frames} >= set(palette()[:10])
    assert SerialFuzz(random.Random(3)).chunk() == chunks[0]  # repeatable for a seed


def test_mavlink_fuzz_notes_only_what_can_change_state() -> None:
    fuzz = MavlinkFuzz(random.Random(5), ["COMPASS_OFS_X", "BRG_SR_ATT"])
    packets = [fuzz.packet() for _ in range(2000)]
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    kinds = {m.get_type() for p in packets for m in (parser.parse_buffer(p) or [])}
    assert {"PARAM_SET", "COMMAND_LONG", "BAD_DATA"} <= kinds
    e = Effects()
    e.note(mav.MAVLink_param_set_message(1, 1, b"BRG_SR_HUD", 3.0, 9))
    e.note(mav.MAVLink_command_long_message(1, 1, 511, 0, 30, 1e5, 0, 0, 0, 0, 0))
    assert e.allows("BRG_SR_HUD") and e.allows("BRG_SR_ATT")
    assert not e.allows("COMPASS_OFS_X") and not e.calibration
    e.note(mav.MAVLink_command_long_message(1, 1, 42424, 0, 0, 0, 0, 0, 0, 0, 0))
    assert e.allows("COMPASS_OFS_X") and e.calibration and not e.allows("BRG_HDG_FEED")
    e.note(mav.MAVLink_command_long_message(1, 1, 245, 0, 2, 0, 0, 0, 0, 0, 0))
    assert e.allows("BRG_HDG_FEED")


def test_wired_as_a_benchmark(capsys: pytest.CaptureFixture[str]) -> None:
    # main() sets up the root logger on this test's captured stderr: put it back after.
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        assert benchmarks_main(["fuzz", "--chunks", "0"]) == 2  # its own parser, via the table
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
    assert "--chunks and --messages must be >= 1" in capsys.readouterr().err
