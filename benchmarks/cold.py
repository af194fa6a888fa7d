"""What one frame costs as the daemon runs it, cold, against hot (``pipeline``'s ``cold_frame``).

At 100 Hz the reader thread sleeps 10 ms between frames while other threads and
processes take the caches, branch predictors and translation buffers; so a frame
costs several times what the same code costs back to back, and nearly in
proportion to how much distinct code and data it touches. This runs the live
run's frames (the ideal unit turning at 300 deg/s) through decode and
:meth:`bridge.app.pipeline.Pipeline.process` one at a time, with ``gap_s`` of sleep before
each and without, and reports the median thread CPU per frame of both
(docs/performance.md: "Where a frame's CPU goes"). ``python -m benchmarks pipeline``
prints it as ``cold_frame``.
"""

from __future__ import annotations

import tempfile
import time

import numpy as np


def _turning_lines(n: int, yaw_rate_dps: float, rate_hz: int, seed: int = 1) -> list[bytes]:
    """``n`` ``$PGMRA`` lines of an ideal unit turning at ``yaw_rate_dps``, ``rate_hz`` frames/s."""
    from bridge.protocol.gmr import CommandFrame, encode
    from bridge.sim.firmware import make_firmware
    from bridge.sim.motion import YawTurns

    fw = make_firmware(seed, motion=YawTurns(yaw_rate_dps), ideal=True)
    fw.receive(encode(CommandFrame("RATE", (str(rate_hz),))), 0.0)
    out = bytearray()
    t = 0.0
    while out.count(b"$PGMRA") < n + 1:
        t += 1.0 / rate_hz
        out += fw.poll(t)
    return [line + b"\n" for line in bytes(out).split(b"\n") if line.startswith(b"$PGMRA")][:n]


def cold_frame_us(
    n: int, gap_s: float, yaw_rate_dps: float, rate_hz: int
) -> dict[str, tuple[float, float]]:
    """``{"hot": (decode, process), "cold": (decode, process)}``: median thread CPU of one
    frame, microseconds, back to back and after ``gap_s`` of sleep."""
    from benchmarks.mavlink import bench_config
    from bridge.daemon import build_daemon
    from bridge.protocol.gmr import GmrDecoder

    lines = _turning_lines(n, yaw_rate_dps, rate_hz)
    clock = time.thread_time_ns
    medians: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, gap in (("hot", 0.0), ("cold", gap_s)):
            daemon = build_daemon(
                bench_config(tmp)
            )  # never started: process() is the per-frame work
            decoder = GmrDecoder(direction="host")
            dec_ns: list[float] = []
            proc_ns: list[float] = []
            for i, line in enumerate(lines):
                if gap:
                    time.sleep(gap)
                t0 = clock()
                frames = decoder.feed(line)
                t1 = clock()
                for frame in frames:
                    daemon.bridge.pipeline.process(frame, i / rate_hz)
                t2 = clock()
                dec_ns.append(t1 - t0)
                proc_ns.append(t2 - t1)
            medians[label] = (
                float(np.median(dec_ns)) / 1e3,
                float(np.median(proc_ns)) / 1e3,
            )
    return medians
