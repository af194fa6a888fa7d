"""Throughput of the per-frame path with MAVLink: ``python -m benchmarks.mavlink``.

Every frame goes the daemon's whole way and then into every MAVLink stream:
``$PGMRA`` bytes -> :class:`~bridge.protocol.gmr.GmrDecoder` ->
:meth:`bridge.app.pipeline.Pipeline.process` (nominal transfer, stored calibration,
tilt-compensated attitude, quality flags) -> :class:`~bridge.app.sample.CompassSample`
-> ATTITUDE, ATTITUDE_QUATERNION, VFR_HUD, SCALED_IMU, RAW_IMU, HIGHRES_IMU and
the heading feed encoded once -> framed (and signed with ``--signed``) for one
link. In service the streams go out at their configured rates, so this is the
worst case: every stream at the frame rate.

Frames come from the simulator's physics (a drawn unit at random attitudes,
calibrated with its true parameters), so the numbers move as they do on a
real unit and every stream, the heading feed included, is encoded. The figure is frames per second of
CPU time of the measuring thread (other processes on the machine do not
distort it), best of ``--repeat`` runs; wall-clock frames per second are shown
too. The target is 5000 frames/s.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from benchmarks.figures import json_option, write_json
from bridge.app.sample import CompassSample
from bridge.config import Config, config_from_mapping
from bridge.core.geometry import random_rotations
from bridge.daemon import build_daemon
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.mavlink.dialect import mavlink as mavlink_dialect
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings
from bridge.mavlink.signing import Signing, sign_outgoing
from bridge.protocol.gmr import AttitudeFrame, Flags, GmrDecoder, encode
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors

TARGET_FPS = 5000.0
STREAMS = S.SAMPLE_STREAMS


@dataclass(frozen=True, slots=True)
class BenchResult:
    """Frames per second (thread CPU time and wall clock), packets per frame, bytes per frame."""

    frames: int
    cpu_fps: float
    wall_fps: float
    packets_per_frame: float
    bytes_per_frame: float
    signed: bool

    @property
    def passed(self) -> bool:
        """At least :data:`TARGET_FPS` frames per CPU second."""
        return self.cpu_fps >= TARGET_FPS


def unit(seed: int = 1) -> UnitErrors:
    """The simulated unit the frames come from (drawn errors, as a real unit has)."""
    return UnitErrors.draw(np.random.default_rng([seed, 7]))


def frame_lines(n: int, seed: int = 1) -> bytes:
    """``n`` ``$PGMRA`` lines of :func:`unit` at random attitudes."""
    rng = np.random.default_rng(seed)
    sensor = SensorModel.at_location(unit(seed), DEFAULT_LOCATION)
    s = sensor.sample(random_rotations(rng, n), rng)
    out = bytearray()
    for i in range(n):
        m, a = s.mag_counts[i], s.acc_counts[i]
        out += encode(
            AttitudeFrame(
                i % 65536, 0.0, 0.0, 0.0,
                int(m[0]), int(m[1]), int(m[2]), int(a[0]), int(a[1]), int(a[2]),
                Flags.SAT if bool(s.saturated[i]) else Flags(0),
            )
        )  # fmt: skip
    return bytes(out)


def pack_every_stream(out: MavlinkOutput, framer: Any, sample: CompassSample) -> tuple[int, int]:
    """Every MAVLink sample stream of ``sample`` encoded by ``out`` and framed by ``framer``:
    (packets, bytes)."""
    packets = nbytes = 0
    for msgid in STREAMS:
        p = out.encode_sample(msgid, sample)
        if p is not None:
            nbytes += len(p.pack(framer))
            packets += 1
    return packets, nbytes


def bench_config(state_dir: str) -> Config:
    """The benches' daemon: the simulated compass at the default site, zenoh off, state in
    ``state_dir`` (the daemon is never started: its per-frame work is called directly)."""
    lat, lon, alt = DEFAULT_LOCATION
    return config_from_mapping(
        {
            "device": {"port": "sim"},
            "storage": {"dir": state_dir},
            "location": {"latitude": lat, "longitude": lon, "altitude_m": alt},
            "zenoh": {"enabled": False},
        },
        env={},
        hostname="bench",
    )


def run(n: int = 20000, *, signed: bool = False, repeat: int = 3) -> BenchResult:
    """Push ``n`` frames through decode -> process -> every stream's encode -> framing."""
    data = frame_lines(n)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = bench_config(tmp)
        # Never started: process() is the pipeline's per-frame work. The unit's own calibration,
        # as after a good calibration: the field is the Earth's, so the heading feed goes too.
        daemon = build_daemon(cfg, calibration=unit().true_calibration())
        out = MavlinkOutput(MavlinkSettings(), daemon.bridge.services)
        signing = Signing(bytes(range(32))) if signed else None
        framer = mavlink_dialect.MAVLink(None, 1, 1)
        if signing is not None:
            sign_outgoing(framer, signing, 0)
        best_cpu = best_wall = math.inf
        packets = nbytes = frames = 0
        for _ in range(repeat):
            decoder = GmrDecoder(direction="host")
            packets = nbytes = frames = 0
            w0, c0 = time.perf_counter(), time.thread_time()
            for frame in decoder.feed(data):
                sample = daemon.bridge.pipeline.process(frame, w0)
                if not isinstance(sample, CompassSample):
                    continue
                frames += 1
                n, size = pack_every_stream(out, framer, sample)
                packets, nbytes = packets + n, nbytes + size
            best_cpu = min(best_cpu, time.thread_time() - c0)
            best_wall = min(best_wall, time.perf_counter() - w0)
    return BenchResult(
        frames=frames,
        cpu_fps=frames / best_cpu if best_cpu > 0 else math.inf,
        wall_fps=frames / best_wall if best_wall > 0 else math.inf,
        packets_per_frame=packets / max(1, frames),
        bytes_per_frame=nbytes / max(1, frames),
        signed=signed,
    )


def main(argv: list[str] | None = None) -> int:
    """Print the figures (or JSON); exit status 1 below the target."""
    ap = argparse.ArgumentParser(prog="python -m benchmarks.mavlink", description=__doc__)
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--signed", action="store_true", help="sign every packet (MAVLink 2 signing)")
    json_option(ap)
    args = ap.parse_args(argv)
    # A drawn, uncalibrated unit at random attitudes flags "disturbed" all the time: the
    # events still run (they are part of the path), their log lines are not wanted here.
    logging.disable(logging.WARNING)
    r = run(args.frames, signed=args.signed, repeat=args.repeat)
    text = (
        f"{r.frames} frames, {r.packets_per_frame:.1f} packets/frame "
        f"({r.bytes_per_frame:.0f} bytes){', signed' if r.signed else ''}: "
        f"{r.cpu_fps:,.0f} frames/s CPU, {r.wall_fps:,.0f} frames/s wall "
        f"-- target {TARGET_FPS:,.0f}: {'PASS' if r.passed else 'FAIL'}"
    )
    doc = {**asdict(r), "passed": r.passed, "target_fps": TARGET_FPS}
    if not write_json(text, doc, args.json):
        return 2
    return 0 if r.passed else 1


if __name__ == "__main__":
    sys.exit(main())
