"""Speed and footprint of the whole bridge: ``python -m benchmarks pipeline``.

Nine figures, each printed with its target (four without) and PASS/FAIL (``--json`` writes
them as one JSON object too):

* **throughput** (:func:`benchmarks.throughput.shipped`) -- the daemon's per-frame path
  at the shipped configuration: each frame's bytes into the link's state machine at
  100 Hz on the frames' clock, every frame through
  :meth:`bridge.app.pipeline.Pipeline.on_frame` to the running MAVLink (``udpout``)
  and Zenoh (a subscriber in a child process) outputs at the shipped stream rates.
  Frames per second of process CPU time, best of ``--repeat``. Target 10 000.
* **throughput_every_stream** (:func:`benchmarks.throughput.every_stream`) -- every
  MAVLink stream encoded and framed and the three Zenoh documents put for every frame
  (no configuration asks that of the daemon): no target.
* **latency** -- a real daemon (a child process, ``compass-bridge run``) with
  ATTITUDE at 50 Hz, the highest rate the configuration allows, reads the
  simulated compass at 100 Hz on a pseudo-terminal; this process notes when
  each frame's first byte is written to the pty and when the ATTITUDE
  datagram carrying that frame's yaw arrives on a UDP socket. The unit turns
  at 300 deg/s, so every frame has its own yaw and the datagram names its
  frame. p99 target 1 ms.
* **CPU and RSS** -- a second child, MAVLink and zenoh outputs on at the
  shipped stream rates (config/compass-bridge.toml: ATTITUDE 10 Hz, ...), the
  compass at 100 Hz: its user+system CPU time (its CPU-time clock, to the ns)
  over a wall-clock window as a percentage of one core (target 3 %), and its
  resident set (``VmRSS``, target 80 MB; the larger of the two children).
  The latency child's CPU is printed too (``daemon_cpu_att50``, no target).
* **first ATTITUDE** -- from spawning a child to its first ATTITUDE
  datagram, the slower of the two (target 1.5 s).
* **calibration fit** -- the default method (``best``) on 10 000 samples of a
  drawn unit at random attitudes (no target: a figure for docs/performance.md).
* **cold frame** (:mod:`benchmarks.cold`) -- decode and :meth:`bridge.app.pipeline.Pipeline.process` of the live
  run's frames (the unit turning at 300 deg/s), thread CPU per frame, median: with
  10 ms of sleep before each frame, as the daemon's reader runs them at 100 Hz
  (other threads and processes take the caches meanwhile), and back to back (hot).
  No target: what a frame costs in service is the cold figure, and a change that
  is faster hot can be slower cold (docs/performance.md).
* **simulated frame** -- the simulated compass's one frame
  (:meth:`bridge.sim.physics.SensorModel.sample` at one attitude, the simulated firmware's
  per-frame path, ``_sample_one``) against the same frames through the stack path, thread
  CPU per frame, best of three, the counts compared bit for bit: the figure the faster
  twin stands on (no target).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import throughput
from benchmarks.figures import Figure, Step, no_step, process_cpu, report, report_options
from benchmarks.procstat import (
    AttitudeTap,
    free_port,
    process_cpu_s,
    process_rss_mb,
    stop_child,
)

log = logging.getLogger(__name__)

TARGET_FPS = 10000.0
TARGET_P99_MS = 1.0
TARGET_CPU_PCT = 3.0
TARGET_RSS_MB = 80.0
TARGET_FIRST_ATTITUDE_S = 1.5

#: Yaw rate of the simulated unit in the live run: 3 deg per 100 Hz frame, one yaw per frame.
LIVE_YAW_RATE_DPS = 300.0
LIVE_RATE_HZ = 100

# ---------------------------------------------------------------------------
# Calibration fit
# ---------------------------------------------------------------------------


def fit_time(n: int = 10000, method: str = "best", seed: int = 3) -> Figure:
    """Seconds for one fit of ``method`` on ``n`` samples of a drawn unit at random attitudes."""
    from bridge.calibration.fits.methods import CalibrationData, calibrate
    from bridge.core.geometry import random_rotations
    from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
    from bridge.core.wmm import earth_field
    from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors

    rng = np.random.default_rng(seed)
    sensor = SensorModel.at_location(UnitErrors.draw(rng), DEFAULT_LOCATION)
    s = sensor.sample(random_rotations(rng, n), rng)
    data = CalibrationData(
        mag_G=mag_counts_to_gauss(s.mag_counts),
        acc_g=acc_counts_to_g(s.acc_counts),
        saturated=s.saturated,
        reference=earth_field(*DEFAULT_LOCATION),
    )
    c0, w0 = process_cpu(), time.perf_counter()
    res = calibrate(method, data)
    cpu, wall = process_cpu() - c0, time.perf_counter() - w0
    return Figure(
        "calibration_fit",
        wall,
        "s",
        None,
        detail={
            "samples": n,
            "method": res.report.method,
            "status": res.report.status,
            "cpu_s": round(cpu, 4),
            "fitness_mG": round(res.report.fitness_mG, 3),
        },
    )


def cold_frame(n: int = 300, gap_s: float = 0.01) -> Figure:
    """One frame's decode + process after ``gap_s`` of sleep, and hot (:mod:`benchmarks.cold`)."""
    from benchmarks.cold import cold_frame_us

    m = cold_frame_us(n, gap_s, LIVE_YAW_RATE_DPS, LIVE_RATE_HZ)
    (hd, hp), (cd, cp) = m["hot"], m["cold"]
    return Figure(
        "cold_frame",
        cd + cp,
        "us per frame (thread CPU)",
        None,
        detail={
            "frames": n,
            "sleep_ms": round(1000.0 * gap_s, 1),
            "decode_us": round(cd, 1),
            "process_us": round(cp, 1),
            "hot_decode_us": round(hd, 1),
            "hot_process_us": round(hp, 1),
            "cold_over_hot": round((cd + cp) / (hd + hp), 1) if hd + hp > 0 else None,
        },
    )


def simulated_frame(n: int = 2000, seed: int = 4) -> Figure:
    """The simulated compass's one-frame sample and the stack path's on the same ``n``
    frames (random attitudes, a small linear acceleration each): thread CPU per frame."""
    from bridge.core.geometry import random_rotations
    from bridge.sim.physics import DEFAULT_LOCATION, Sample, SensorModel, UnitErrors

    rng = np.random.default_rng(seed)
    sensor = SensorModel.at_location(UnitErrors.draw(rng), DEFAULT_LOCATION)
    Rs = list(random_rotations(rng, n))  # C-ordered (3, 3) views, as a motion's attitudes
    lins = list(rng.normal(0.0, 0.05, size=(n, 3)))

    def run(stack: bool) -> tuple[float, list[bytes]]:
        best, out = math.inf, list[Sample]()
        for _ in range(3):
            noise = np.random.default_rng([seed, 1])  # the same draws for both paths
            out = []
            t0 = time.thread_time()
            for R, lin in zip(Rs, lins, strict=True):
                out.append(sensor.sample(R[np.newaxis] if stack else R, noise, lin))
            best = min(best, time.thread_time() - t0)
        # (each repeat draws the same noise: the last one's counts are every one's)
        return 1e6 * best / n, [s.mag_counts.tobytes() + s.acc_counts.tobytes() for s in out]

    one_us, one = run(stack=False)
    stack_us, stacked = run(stack=True)
    return Figure(
        "simulated_frame",
        one_us,
        "us per frame (thread CPU)",
        None,
        detail={
            "frames": n,
            "stack_path_us": round(stack_us, 1),
            "stack_over_one": round(stack_us / one_us, 2) if one_us > 0 else None,
            "same_counts": one == stacked,
        },
    )


# ---------------------------------------------------------------------------
# The live daemon: latency, CPU, RSS, first ATTITUDE
# ---------------------------------------------------------------------------


class _TimedPty:
    """The simulated compass on a pty, noting when each write (a frame's first byte) happens."""

    def __init__(self, link: Path, seed: int) -> None:
        from bridge.sim.firmware import make_firmware
        from bridge.sim.motion import YawTurns
        from bridge.sim.pty import PtyCompass

        writes: list[tuple[float, bytes]] = []
        self.writes = writes

        class Timed(PtyCompass):
            def _write(self, p: Any, data: bytes) -> None:
                # The stamp is taken right before the bytes enter the pty.
                writes.append((time.monotonic(), data))
                super()._write(p, data)

        fw = make_firmware(seed, motion=YawTurns(LIVE_YAW_RATE_DPS), ideal=True)
        self.pty = Timed(fw, link)


def _expected_yaws(writes: list[tuple[float, bytes]]) -> list[tuple[float, float]]:
    """``(t_written, yaw_rad)`` of every ``$PGMRA`` written, as the daemon will compute it."""
    from bridge.core.attitude import AttitudeEngine
    from bridge.core.calibration import Calibration
    from bridge.protocol.gmr import AttitudeFrame, GmrDecoder

    engine = AttitudeEngine(Calibration(), reference=None, heading_reference="magnetic")
    dec = GmrDecoder(direction="host")
    out: list[tuple[float, float]] = []
    for t, data in writes:
        for f in dec.feed(data):
            if isinstance(f, AttitudeFrame):
                a = engine.solve_counts(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
                out.append((t, math.radians(a.heading_deg)))
    return out


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2.0 * math.pi) - math.pi)


def match_latencies(
    expected: list[tuple[float, float]], received: list[tuple[float, float]]
) -> tuple[list[float], int]:
    """Latency (s) of each received ``(t, yaw)`` against the frame with that yaw written last.

    Returns the latencies and the number of datagrams no written frame explains
    (a yaw off by more than 0.05 deg from every frame of the preceding 0.5 s).
    """
    lat: list[float] = []
    unmatched = 0
    j0 = 0
    tol = math.radians(0.05)
    for t_rx, yaw in received:
        while j0 < len(expected) and expected[j0][0] < t_rx - 0.5:
            j0 += 1
        best: tuple[float, float] | None = None
        j = j0
        while j < len(expected) and expected[j][0] <= t_rx:
            d = _angle_diff(expected[j][1], yaw)
            if d <= tol and (best is None or expected[j][0] > best[0]):
                best = (expected[j][0], d)
            j += 1
        if best is None:
            unmatched += 1
        else:
            lat.append(t_rx - best[0])
    return lat, unmatched


def _percentile(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    return float(np.percentile(np.asarray(values), q))


@dataclass
class _ChildRun:
    """What one live daemon child gave: start-up, ATTITUDE arrivals, CPU and memory."""

    first_s: float
    writes: list[tuple[float, float]]  # (time the frame's first byte went out, its yaw)
    window: list[tuple[float, float]]  # ATTITUDE (arrival time, yaw) in the CPU window
    cpu_s: float
    wall_s: float
    rss_mb: float
    hwm_mb: float


def live_config(
    tmp: Path,
    link: Path,
    udp_port: int,
    attitude_hz: float | None = None,
    *,
    zenoh_enabled: bool = True,
) -> Path:
    """A live daemon's configuration, written in ``tmp``: the compass on ``link`` at 100 Hz,
    MAVLink to ``udp_port`` (ATTITUDE at ``attitude_hz``; None: the shipped rates), Zenoh
    listening on a free loopback port, state in ``tmp``."""
    cfg = tmp / "bench.toml"
    cfg.write_text(
        "\n".join(
            [
                "[device]",
                f'port = "{link}"',
                f"rate_hz = {LIVE_RATE_HZ}",
                "[mavlink]",
                f'endpoints = ["udpout:127.0.0.1:{udp_port}"]',
                *([f"rate_attitude_hz = {attitude_hz}"] if attitude_hz is not None else []),
                "[zenoh]",
                f"enabled = {'true' if zenoh_enabled else 'false'}",
                f'listen = ["tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]',
                'key_prefix = "bench/compass"',
                "[storage]",
                f'dir = "{tmp}/state"',
                "",
            ]
        )
    )
    return cfg


def _run_child(
    duration_s: float,
    attitude_hz: float | None,
    *,
    seed: int,
    zenoh_enabled: bool,
    step: Step,
    label: str,
) -> _ChildRun:
    """One daemon child on the simulated compass at 100 Hz; ``attitude_hz`` None: shipped rates."""
    with tempfile.TemporaryDirectory(prefix="cb-bench-") as tmp:
        link = Path(tmp) / "compass"
        tap = AttitudeTap("bench-udp")
        udp_port = tap.port
        cfg = live_config(Path(tmp), link, udp_port, attitude_hz, zenoh_enabled=zenoh_enabled)
        timed = _TimedPty(link, seed)
        timed.pty.start()
        tap.start()
        env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
        t_spawn = time.monotonic()
        proc = subprocess.Popen(
            [sys.executable, "-m", "bridge", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        try:
            deadline = t_spawn + 15.0
            while not tap.received and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.01)
                step(0.0, f"starting the daemon ({label})")
            if not tap.received:
                raise RuntimeError(
                    "the daemon sent no ATTITUDE within 15 s"
                    + (f" (exited {proc.returncode})" if proc.poll() is not None else "")
                )
            first_s = tap.received[0][0] - t_spawn
            time.sleep(2.0)  # past start-up work (imports done, zenoh session open)
            n0 = len(tap.received)
            c0, w0 = process_cpu_s(proc.pid), time.monotonic()
            end = w0 + duration_s
            while time.monotonic() < end and proc.poll() is None:
                time.sleep(0.1)
                step(min(1.0, (time.monotonic() - w0) / duration_s), f"daemon at 100 Hz ({label})")
            c1, w1 = process_cpu_s(proc.pid), time.monotonic()
            rss, hwm = process_rss_mb(proc.pid)
            n1 = len(tap.received)
        finally:
            err = stop_child(proc)
            tap.stop()
            timed.pty.stop()
        if err:
            log.debug("daemon stderr: %s", err.decode(errors="replace")[-2000:])
        return _ChildRun(
            first_s=first_s,
            writes=_expected_yaws(timed.writes),
            window=tap.received[n0:n1],
            cpu_s=c1 - c0,
            wall_s=w1 - w0,
            rss_mb=rss,
            hwm_mb=hwm,
        )


def live(
    duration_s: float = 10.0, *, seed: int = 1, zenoh_enabled: bool = True, step: Step = no_step
) -> list[Figure]:
    """Run real daemons at 100 Hz against the simulated compass; latency, CPU, RSS, start-up.

    Two children, one after the other, each with MAVLink (to a UDP peer) and zenoh on:

    * **shipped rates** (the configuration's defaults, as config/compass-bridge.toml
      ships them: ATTITUDE 10 Hz, ...): the CPU and RSS targets.
    * **ATTITUDE at 50 Hz**, the highest the configuration allows: the latency figure
      (half the frames have their own datagram to time) and its CPU, reported without a
      target. Each extra ATTITUDE datagram costs the kernel's loopback UDP send (about
      35-41 us cold on this machine, measured in docs/performance.md).

    RSS and first ATTITUDE are the worse of the two.
    """

    def sub(lo: float, hi: float) -> Step:
        return lambda f, note: step(lo + (hi - lo) * f, note)

    fast = _run_child(
        duration_s,
        50.0,
        seed=seed,
        zenoh_enabled=zenoh_enabled,
        step=sub(0.0, 0.5),
        label="ATTITUDE 50 Hz",
    )
    shipped = _run_child(
        duration_s,
        None,
        seed=seed,
        zenoh_enabled=zenoh_enabled,
        step=sub(0.5, 1.0),
        label="shipped rates",
    )
    lat, unmatched = match_latencies(fast.writes, fast.window)
    ms = [1000.0 * x for x in lat]

    def cpu(run: _ChildRun) -> float:
        return 100.0 * run.cpu_s / run.wall_s

    def per_frame(run: _ChildRun) -> float:
        # ATTITUDE per compass frame written during the window: the stream rate on the
        # compass's own clock (a rate over wall time moves with how busy the machine is).
        t0, t1 = run.window[0][0], run.window[-1][0]
        frames = sum(1 for t, _ in run.writes if t0 <= t <= t1)
        return round((len(run.window) - 1) / frames, 3) if frames else 0.0

    def cpu_detail(run: _ChildRun) -> dict[str, Any]:
        return {
            "window_s": round(run.wall_s, 1),
            "cpu_s": round(run.cpu_s, 4),
            "attitude_hz": round(len(run.window) / run.wall_s, 1),
            "attitude_per_frame": per_frame(run),
        }

    worst_rss = max((fast, shipped), key=lambda r: r.rss_mb)
    return [
        Figure(
            "latency_p99",
            _percentile(ms, 99),
            "ms",
            TARGET_P99_MS,
            detail={
                "p50_ms": round(_percentile(ms, 50), 3),
                "max_ms": round(max(ms), 3) if ms else None,
                "matched": len(ms),
                "unmatched": unmatched,
                "attitude_hz": round(len(fast.window) / fast.wall_s, 1),
                "attitude_per_frame": per_frame(fast),
            },
        ),
        Figure(
            "daemon_cpu", cpu(shipped), "% of one core", TARGET_CPU_PCT, detail=cpu_detail(shipped)
        ),
        Figure("daemon_cpu_att50", cpu(fast), "% of one core", None, detail=cpu_detail(fast)),
        Figure(
            "daemon_rss",
            worst_rss.rss_mb,
            "MB",
            TARGET_RSS_MB,
            detail={"peak_mb": round(max(fast.hwm_mb, shipped.hwm_mb), 1)},
        ),
        Figure("first_attitude", max(fast.first_s, shipped.first_s), "s", TARGET_FIRST_ATTITUDE_S),
    ]


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks pipeline``: print the figures; exit 1 if any misses its target."""
    from bridge.tools.progress import Progress

    ap = argparse.ArgumentParser(
        prog="python -m benchmarks pipeline",
        description="Speed and footprint: throughput, latency, CPU, RSS, start-up, fit time.",
    )
    ap.add_argument("--frames", type=int, default=20000, help="frames per throughput run")
    ap.add_argument("--repeat", type=int, default=3, help="throughput runs (best is kept)")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of the live run")
    ap.add_argument("--fit-samples", type=int, default=10000, help="samples of the fit")
    ap.add_argument("--cold-frames", type=int, default=300, help="frames of the cold figure")
    ap.add_argument("--skip-live", action="store_true", help="no daemon child process")
    report_options(ap)
    args = ap.parse_args(argv)
    if (
        args.frames < 1
        or args.repeat < 1
        or args.duration <= 0
        or args.fit_samples < 100
        or args.cold_frames < 1
    ):
        ap.error("--frames, --repeat, --cold-frames >= 1, --duration > 0, --fit-samples >= 100")
    # A drawn, uncalibrated unit at random attitudes is "disturbed" all the time: the
    # events still run (they are part of the path), their log lines are not wanted here.
    logging.disable(logging.WARNING)
    figures: list[Figure] = []
    with Progress("throughput", 1.0, enabled=args.progress) as bar:
        figures.append(
            throughput.shipped(
                args.frames, repeat=args.repeat, step=lambda f, n: bar.update(f, note=n)
            )
        )
    with Progress("every stream", 1.0, enabled=args.progress) as bar:
        figures.append(
            throughput.every_stream(
                args.frames, repeat=args.repeat, step=lambda f, n: bar.update(f, note=n)
            )
        )
    with Progress("calibration fit", None, enabled=args.progress) as bar:
        bar.update(note=f"{args.fit_samples} samples")
        figures.append(fit_time(args.fit_samples))
    with Progress("cold frame", None, enabled=args.progress) as bar:
        bar.update(note=f"{args.cold_frames} frames, 10 ms apart")
        figures.append(cold_frame(args.cold_frames))
    with Progress("simulated frame", None, enabled=args.progress) as bar:
        bar.update(note="2000 frames, two paths")
        figures.append(simulated_frame())
    if not args.skip_live:
        with Progress("live daemon", 1.0, enabled=args.progress) as bar:
            figures += live(args.duration, step=lambda f, n: bar.update(f, note=n))
    logging.disable(logging.NOTSET)
    return report(figures, args.json, cpu_count=os.cpu_count())


if __name__ == "__main__":
    sys.exit(main())
