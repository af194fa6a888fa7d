"""The per-frame path with every MAVLink stream encoded stays above 5000 frames/s.

Measured in CPU time of the measuring thread (``time.thread_time``), so other
processes on the machine do not make it flaky; best of two short runs.
"""

from __future__ import annotations

from typing import Any

from test_mavlink_rig import M

from benchmarks.mavlink import STREAMS, TARGET_FPS, frame_lines, main, run


def test_frames_are_real_pgmra_lines() -> None:
    data = frame_lines(50)
    lines = data.split(b"\r\n")[:-1]
    assert len(lines) == 50 and all(line.startswith(b"$PGMRA,") for line in lines)


def test_throughput_with_every_stream_encoded() -> None:
    r = run(3000, repeat=2)
    assert r.frames == 3000
    # every stream on (nearly) every frame: the feed skips only saturated frames
    assert len(STREAMS) - 0.1 <= r.packets_per_frame <= len(STREAMS)
    assert r.cpu_fps >= TARGET_FPS, r
    assert r.passed


def test_signed_throughput(capsys: Any) -> None:
    assert main(["--frames", "2000", "--repeat", "2", "--signed", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"signed": true' in out and '"passed": true' in out
    assert M.MAVLINK_MSG_ID_ATTITUDE in STREAMS
