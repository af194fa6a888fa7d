"""``python -m benchmarks reads``: the drift monitor on frames read as they come, in the
compass link's bursts, and on a busy host -- given each frame's arrival or the instant it
was sampled.

At 100 Hz with the outputs' streams at 10 Hz the link holds the port until shortly before
the frame the next output falls due on, reads the frames that waited with one read (all
stamped with its time), then reads the due one as it comes
(:class:`bridge.link.serial_link.CompassLink`, ``_read_loop`` and ``_hold``).
:class:`LinkReads` runs the link's own decisions (:class:`~bridge.link.serial_link.BurstReads`:
when a hold ends, the compass's rhythm, how many frames a hold holds, how a late read is
stamped, the burst's lead) on a simulated clock, with the due
time from a real :class:`~bridge.mavlink.schedule.StreamSchedule` fed the stamps as the
MAVLink output feeds it (:class:`Paced`, an output on the pipeline). No port, no thread:
the wake-ups are where the rules put them, plus a lateness the caller chooses (a busy
host: :func:`busy`). ``tests/test_drift_bursts.py`` uses the same rig.

The figures (:func:`run`): one simulated unit (``benchmarks.drift.Unit``) at 100 Hz
drives, its hard iron moves 40 mG, the drift monitor learns it back; per read and per
time handed to the monitor: its samples per second, how far their times are from the
instants the frames were sampled, how many it judged steady (and how many of those the
estimator's rule judges otherwise at the true instants), when drift was detected and
learned, and what was left.
"""

from __future__ import annotations

import argparse
import logging
import math
import random
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import bridge.app.calibration.drift as drift_module
from benchmarks.drift import Unit
from benchmarks.figures import json_option, write_json
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.pipeline import Pipeline
from bridge.app.sample import CompassSample
from bridge.app.settings import EngineSettings
from bridge.calibration.drift.estimator import DriftEstimate, DriftEstimator, Reference
from bridge.core.attitude import AttitudeEngine, AttitudeSolution
from bridge.core.calibration import Calibration
from bridge.core.wmm import earth_field
from bridge.events import Event, EventBus
from bridge.link.serial_link import BurstReads
from bridge.mavlink.schedule import ATTITUDE, StreamSchedule
from bridge.protocol.device import Received
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.sim.physics import DEFAULT_LOCATION
from bridge.types import FloatArray


class Paced:
    """An output paced as the MAVLink output is: a 10 Hz ATTITUDE stream whose slots a
    sample takes by its own time (``sample.t``), ``due_at`` the schedule's next."""

    name = "paced"

    def __init__(self, rate_hz: float = 10.0) -> None:
        self.schedule = StreamSchedule({ATTITUDE: rate_hz})
        self.schedule.set_sample_streams([ATTITUDE])
        self.sent: list[float] = []  #: the times of the samples that took a slot

    def start(self) -> None:
        """Nothing to start."""

    def publish(self, sample: CompassSample) -> None:
        """The MAVLink output's pacing (``MavlinkOutput.publish``) without the encoding."""
        if sample.t < self.schedule.sample_due_at:
            return
        if self.schedule.due_samples(sample.t):
            self.sent.append(sample.t)

    @property
    def due_at(self) -> float:
        """When the stream next falls due."""
        return self.schedule.sample_due_at

    def close(self, timeout: float) -> None:
        """Nothing to stop."""


class LinkReads:
    """The link's reads of frames that come at ``comes[i]`` (the last byte of frame ``i``
    on the port), each read as a list of :class:`Received` stamped as the link stamps
    them. ``due_at`` is asked after each read's frames went through the pipeline (the
    link's ``due_at`` hook: :meth:`Pipeline.due_at_time`); ``late()`` is how late the
    thread wakes from a hold (0: on time); each frame takes ``per_frame_s`` through the
    pipeline."""

    def __init__(
        self,
        rate_hz: int,
        due_at: Callable[[], float],
        late: Callable[[], float] = lambda: 0.0,
        per_frame_s: float = 5e-5,
    ) -> None:
        self.rate_hz = rate_hz
        self.due_at = due_at
        self.late = late
        self.per_frame_s = per_frame_s
        self.bursts = 0  #: reads of more than one held frame
        self.late_reads = 0  #: reads after the due time (stamped by ``_held``)

    def reads(
        self, frames: Sequence[AttitudeFrame], comes: Sequence[float]
    ) -> Iterator[list[Received]]:
        """The reads, in order (the caller puts each through the pipeline before the next)."""
        bursts = BurstReads()  # the link's own rules
        now = -math.inf
        i, n = 0, len(frames)
        while i < n:
            # after a hold, what waited through it: read at once; else a blocking read,
            # which returns when the next frame has come
            held_for = bursts.held_for
            read_at = now if held_for is not None else max(now, comes[i])
            j = i
            while j < n and comes[j] <= read_at:
                j += 1
            if j == i:  # the hold found nothing waiting: frames as they come from now on
                bursts.held_for = None
                continue
            received = [Received(frames[k], read_at) for k in range(i, j)]
            i = j
            burst = held_for is not None and len(received) > 1
            self.late_reads += held_for is not None and read_at >= held_for
            received = bursts.read(received, read_at)
            self.bursts += burst
            yield received
            now = read_at + self.per_frame_s * len(received)
            if burst:
                bursts.took(now - read_at)
            # the hold (CompassLink._hold)
            until = bursts.hold(self.due_at(), self.rate_hz, now, read_at, None)
            if until is not None:
                now = until + self.late()


def feed_as_read(
    pipeline: Pipeline,
    frames: Sequence[AttitudeFrame],
    comes: Sequence[float],
    link: LinkReads | None,
    seen: Callable[[Received], None] = lambda item: None,
) -> None:
    """``frames`` through ``pipeline`` as the link reads them (``link``), or each with the
    time it came (``None``: read as it comes, on time); ``seen`` is told each frame as it
    is read, before it goes in."""
    if link is None:
        for f, c in zip(frames, comes, strict=True):
            item = Received(f, c)
            seen(item)
            pipeline.on_frame(item)
        return
    for read in link.reads(frames, comes):
        for item in read:
            seen(item)
            pipeline.on_frame(item)


def busy(seed: int) -> Callable[[], float]:
    """How late a busy host wakes the reader from a hold: 4 ms on average (exponential),
    and 20-150 ms more one time in 20 (seeded)."""
    rng = random.Random(seed)

    def late() -> float:
        spike = rng.uniform(0.02, 0.15) if rng.random() < 0.05 else 0.0
        return rng.expovariate(1.0 / 0.004) + spike

    return late


# -- the drift monitor on a drive, read one way ---------------------------------------------

FIELD = earth_field(*DEFAULT_LOCATION)
CHANGE_G = (0.012, -0.028, 0.025)  # 40 mG, sensor axes
RATE_HZ = 100
T0 = 1000.0  # the monotonic clock at the first frame
LATENCY_S = 0.0006  # a frame's last byte reaches the host this long after it was sampled


def drive(
    seed: int, before_s: float, after_s: float
) -> tuple[Unit, list[AttitudeFrame], list[float]]:
    """The frames of a drive at 100 Hz (the hard iron changed by :data:`CHANGE_G` after
    ``before_s``) and the instant each was sampled; a frame's ``seq`` is its index."""
    if (before_s + after_s) * RATE_HZ >= 65536:
        raise ValueError("a drive of at most 655 s: seq counts the frames")
    unit = Unit(seed, float(RATE_HZ), FIELD)
    t1, s1 = unit.frames(0.0, before_s)
    t2, s2 = unit.frames(before_s, before_s + after_s, unit.model.with_hard_iron_change(CHANGE_G))
    mc = np.concatenate([s1.mag_counts, s2.mag_counts]).tolist()
    ac = np.concatenate([s1.acc_counts, s2.acc_counts]).tolist()
    sat = np.concatenate([s1.saturated, s2.saturated]).tolist()
    frames = [
        AttitudeFrame(i, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, Flags.SAT if s else Flags(0))
        for i, ((mx, my, mz), (ax, ay, az), s) in enumerate(zip(mc, ac, sat, strict=True))
    ]
    return unit, frames, (T0 + np.concatenate([t1, t2])).tolist()


@dataclass
class Watched:
    """What the monitor did with one read of the drive."""

    rows: list[FloatArray] = field(default_factory=list)  #: the samples its recent fit got
    fits: list[DriftEstimate] = field(default_factory=list)  #: ... and the recent fits
    events: list[tuple[Event, int]] = field(default_factory=list)  #: (event, frame index)
    applied: list[Calibration] = field(default_factory=list)
    status: dict[str, Any] = field(default_factory=dict)
    bursts: int = 0  #: the link's reads of more than one held frame
    #: the frame each time handed to the monitor first came with
    frame_at: dict[float, int] = field(default_factory=dict)

    @property
    def samples(self) -> FloatArray:
        """The samples, rows of ``(t, hx, hy, hz, gx, gy, gz)``."""
        return np.concatenate(self.rows)

    def kinds(self, prefix: str) -> list[tuple[str, dict[str, Any]]]:
        """The events whose kind starts with ``prefix``, with their data."""
        return [(e.kind, e.data) for e, _ in self.events if e.kind.startswith(prefix)]


def watch(
    unit: Unit,
    frames: list[AttitudeFrame],
    sampled: list[float],
    *,
    bursts: bool,
    late: Callable[[], float] | None = None,
    arrival: bool = False,
    lead_s: float = 0.0,
) -> Watched:
    """The drive through the pipeline into a learning drift monitor, read as it comes or in
    the link's bursts (waking ``late()`` late), the monitor switched on ``lead_s`` in and
    handed each frame's sampled instant (the pipeline's) or its ``arrival``."""
    seen = Watched()
    window_s = drift_module.DriftSettings().window_s

    class Recorded(DriftEstimator):
        """The monitor's estimators, the recent one's samples and fits recorded."""

        def add(self, rows: Any) -> None:
            if self.window_s == window_s:
                seen.rows.append(np.array(rows, dtype=np.float64))
            super().add(rows)

        def estimate(self, reference: Reference | None = None) -> DriftEstimate | None:
            est = super().estimate(reference)
            if est is not None and self.window_s == window_s:
                seen.fits.append(est)
            return est

    engine = AttitudeEngine(unit.errors.true_calibration())
    settings = EngineSettings(engine, field=FIELD)
    bus = EventBus()
    now = Received(frames[0], 0.0)  # the frame going in (its seq is its index: one drive)
    bus.subscribe(lambda e: seen.events.append((e, now.frame.seq)))  # type: ignore[union-attr]

    def apply(cal: Calibration, source: str, report: Any, view: Any) -> str:
        seen.applied.append(cal)
        settings.update_calibration(cal, source)
        return ""

    built = drift_module.DriftEstimator
    drift_module.DriftEstimator = Recorded  # type: ignore[misc]  # (the monitor builds its own)
    try:
        monitor = DriftMonitor(settings, bus, apply=apply, calibrating=lambda: False, mode="off")
    finally:
        drift_module.DriftEstimator = built  # type: ignore[misc]

    def observe(a: AttitudeSolution, t: float, saturated: bool) -> None:
        if arrival:
            t = now.t
        seen.frame_at.setdefault(t, now.frame.seq)  # type: ignore[union-attr]
        monitor.observe(a, t, saturated)

    def going_in(item: Received) -> None:
        nonlocal now
        now = item

    pipeline = Pipeline(
        engine, bus, feed=lambda f, t: None, calibrating=lambda: False, observe=observe
    )
    pipeline.set_outputs([Paced()])
    link = LinkReads(RATE_HZ, pipeline.due_at_time, late or (lambda: 0.0)) if bursts else None
    comes = [t + LATENCY_S for t in sampled]
    lead = round(lead_s * RATE_HZ)
    if lead:
        feed_as_read(pipeline, frames[:lead], comes[:lead], link, going_in)
    monitor.set_mode("learn")
    feed_as_read(pipeline, frames[lead:], comes[lead:], link, going_in)
    seen.status = monitor.status().to_dict()
    seen.bursts = 0 if link is None else link.bursts
    return seen


# -- the figures ------------------------------------------------------------------------------

READS = ("as they come", "in bursts", "busy host")


def _steady(rows: FloatArray) -> int:
    """How many of ``rows`` the estimator judges steady (its dip rows) in one fit of all."""
    est = DriftEstimator(window_s=1e9)
    est.add(rows)
    fit = est.estimate()
    return 0 if fit is None else fit.n_dip


def figures(
    w: Watched, frames_sampled: list[float], seconds: float, before_s: float
) -> dict[str, Any]:
    """One read's figures (times of events in seconds of the drive)."""
    rows = w.samples
    true = np.array([frames_sampled[w.frame_at[t]] for t in rows[:, 0].tolist()])
    off = rows[:, 0] - true
    dev = np.abs(off - np.median(off))
    at_true = rows.copy()
    at_true[:, 0] = true

    def first(kind: str) -> float | None:
        hits = [i for e, i in w.events if e.kind == kind]
        return hits[0] / RATE_HZ if hits else None

    return {
        "samples_per_s": len(rows) / seconds,
        "offset_ms": 1e3 * float(np.median(off)),
        "off_2ms_pct": 100.0 * float(np.mean(dev > 0.002)),
        "off_p99_ms": 1e3 * float(np.percentile(dev, 99)),
        "off_max_ms": 1e3 * float(np.max(dev)),
        "steady": _steady(rows),
        "steady_at_true": _steady(at_true),
        "detected_s": first("calibration.drift"),
        "learned_s": first("calibration.learned"),
        "left_mG": w.status.get("change_mG"),
        "learned_mG": w.status.get("learned_mG"),
        "change_at_s": before_s,
    }


def run(seed: int = 2, before_s: float = 90.0, after_s: float = 150.0) -> list[dict[str, Any]]:
    """Every read, each with the arrival and with the sampled instant handed to the monitor
    (watched from the first frame)."""
    unit, frames, sampled = drive(seed, before_s, after_s)
    seconds = before_s + after_s
    out = []
    for arrival in (True, False):
        for read in READS:
            w = watch(
                unit,
                frames,
                sampled,
                bursts=read != "as they come",
                late=busy(5) if read == "busy host" else None,
                arrival=arrival,
            )
            f = figures(w, sampled, seconds, before_s)
            out.append({"read": read, "taken": "arrival" if arrival else "sampled", **f})
    return out


def _s(v: float | None, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def format_table(rows: list[dict[str, Any]]) -> str:
    """The figures as a Markdown table."""
    lines = [
        "| read | taken | samples/s | taken time - sampled | steady samples (at the true "
        "instants) | drift detected | learned | left / learned |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        off = f"{r['offset_ms']:.1f} ms"
        if r["off_max_ms"] > 2.0:
            off += (
                f"; {r['off_2ms_pct']:.2g} % > 2 ms off that, p99 {r['off_p99_ms']:.0f} ms, "
                f"max {r['off_max_ms']:.0f} ms"
            )
        lines.append(
            f"| {r['read']} | {r['taken']} | {r['samples_per_s']:.2f} | {off} | "
            f"{r['steady']} ({r['steady_at_true']}) | {_s(r['detected_s'])} s | "
            f"{_s(r['learned_s'])} s | {_s(r['left_mG'], '.2f')} / "
            f"{_s(r['learned_mG'], '.2f')} mG |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: prints the table."""
    p = argparse.ArgumentParser(
        prog="python -m benchmarks reads",
        description="The drift monitor on frames read as they come, in bursts, on a busy host.",
    )
    options: tuple[tuple[str, type, float, str], ...] = (
        ("--seed", int, 2, "the unit's seed"),
        ("--before", float, 90.0, "drive before the change (s)"),
        ("--after", float, 150.0, "drive after the change (s)"),
    )
    for flag, kind, default, text in options:
        p.add_argument(flag, type=kind, default=default, help=text)
    json_option(p)
    args = p.parse_args(list(argv) if argv is not None else None)
    logging.getLogger("bridge.events").setLevel(logging.ERROR)  # the events are the figures
    rows = run(args.seed, args.before, args.after)
    text = (
        f"unit seed {args.seed} at {RATE_HZ} Hz, hard iron moved 40 mG {args.before:g} s in, "
        f"learn, {args.before + args.after:g} s; times in seconds of the drive\n"
        + format_table(rows)
    )
    doc = {
        "seed": args.seed,
        "rate_hz": RATE_HZ,
        "before_s": args.before,
        "after_s": args.after,
        "rows": rows,
    }
    return 0 if write_json(text, doc, args.json, default=float) else 2
