"""The drift monitor watches a drive as well when the link reads its frames in bursts as when
it reads each frame as it comes.

At 100 Hz with the outputs' streams at 10 Hz the link holds the port and reads nine frames
at once, then the due one as it comes (docs/architecture.md, "How a frame travels"). The
monitor keeps about one sample per 0.1 s and judges the heading's steadiness from the time
steps between its samples. Handed each frame's arrival, it took the oldest frame of every
burst (10 Hz) stamped 85 ms after it was sampled, where the frames read as they come gave
mostly every ninth frame (11 Hz) at its instant: other samples, other fits, the learning
seconds apart. The pipeline hands it the instant each frame was sampled (its frame clock,
from ``seq``), as it hands the attitude engine and the calibration controller, and it keeps
every ninth frame of that clock at 100 Hz: the same frames at the same instants, however
they were read.

In memory: the application's pipeline, a 10 Hz output paced as the MAVLink output is, the
link's stamping worked out by its own rules (``link_reads``), and the monitor, on one
simulated drive whose hard iron changes and is learned back, read two ways.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from link_reads import LinkReads, Paced, feed_as_read

import bridge.app.calibration.drift as drift_module
from benchmarks.drift import Unit
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.pipeline import Pipeline
from bridge.app.settings import EngineSettings
from bridge.calibration.drift.estimator import DriftEstimate, DriftEstimator, Reference
from bridge.calibration.model import Calibration
from bridge.core.attitude import AttitudeEngine
from bridge.core.wmm import earth_field
from bridge.events import Event, EventBus
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.sim.physics import DEFAULT_LOCATION

FIELD = earth_field(*DEFAULT_LOCATION)
CHANGE_G = (0.012, -0.028, 0.025)  # 40 mG, sensor axes
RATE_HZ = 100
T0 = 1000.0  # the monotonic clock at the first frame
LATENCY_S = 0.0006  # a frame's last byte reaches the host this long after it was sampled
#: The monitor is switched on this far into the drive: the frame clock has learnt the
#: compass's rate (4 s of arrivals), as it has long before anyone watches a running bridge.
LEAD_S = 6.0
BEFORE_S, AFTER_S = 60.0, 110.0  # the drive before and after its hard iron changes


@dataclass
class Watched:
    """What the monitor did with one read of the drive."""

    rows: list[np.ndarray] = field(default_factory=list)  #: the samples its recent fit got
    fits: list[DriftEstimate] = field(default_factory=list)  #: ... and the recent fits
    events: list[Event] = field(default_factory=list)
    applied: list[Calibration] = field(default_factory=list)
    status: dict[str, Any] = field(default_factory=dict)
    bursts: int = 0  #: the link's reads of more than one held frame

    @property
    def samples(self) -> np.ndarray:
        return np.concatenate(self.rows)


def drive() -> tuple[Unit, list[AttitudeFrame], list[float]]:
    """The frames of a drive at 100 Hz (the hard iron changed after ``BEFORE_S``) and when
    each was sampled."""
    unit = Unit(2, float(RATE_HZ), FIELD)
    t1, s1 = unit.frames(0.0, BEFORE_S)
    changed = unit.model.with_hard_iron_change(CHANGE_G)
    t2, s2 = unit.frames(BEFORE_S, BEFORE_S + AFTER_S, changed)
    mc = np.concatenate([s1.mag_counts, s2.mag_counts]).tolist()
    ac = np.concatenate([s1.acc_counts, s2.acc_counts]).tolist()
    sat = np.concatenate([s1.saturated, s2.saturated]).tolist()
    frames = [
        AttitudeFrame(
            i % 65536, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, Flags.SAT if s else Flags(0)
        )
        for i, ((mx, my, mz), (ax, ay, az), s) in enumerate(zip(mc, ac, sat, strict=True))
    ]
    return unit, frames, (T0 + np.concatenate([t1, t2])).tolist()


def watch(
    mp: pytest.MonkeyPatch,
    unit: Unit,
    frames: list[AttitudeFrame],
    sampled: list[float],
    bursts: bool,
) -> Watched:
    """The drive through the pipeline into a learning drift monitor, read as it comes or in
    the link's bursts."""
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

    mp.setattr(drift_module, "DriftEstimator", Recorded)
    engine = AttitudeEngine(unit.errors.true_calibration())
    settings = EngineSettings(engine, field=FIELD)
    bus = EventBus()
    bus.subscribe(seen.events.append)

    def apply(cal: Calibration, source: str, report: Any, view: Any) -> str:
        seen.applied.append(cal)
        settings.update_calibration(cal, source)
        return ""

    monitor = DriftMonitor(settings, bus, apply=apply, calibrating=lambda: False, mode="off")
    pipeline = Pipeline(
        engine, bus, feed=lambda f, t: None, calibrating=lambda: False, observe=monitor.observe
    )
    pipeline.set_outputs([Paced()])
    link = LinkReads(RATE_HZ, pipeline.due_at_time) if bursts else None
    comes = [t + LATENCY_S for t in sampled]
    lead = round(LEAD_S * RATE_HZ)
    feed_as_read(pipeline, frames[:lead], comes[:lead], link)
    monitor.set_mode("learn")
    feed_as_read(pipeline, frames[lead:], comes[lead:], link)
    seen.status = monitor.status().to_dict()
    seen.bursts = 0 if link is None else link.bursts
    return seen


@pytest.fixture(scope="module")
def read_two_ways() -> tuple[Watched, Watched]:
    """The drive read as it comes, and in the link's bursts."""
    unit, frames, sampled = drive()
    with pytest.MonkeyPatch.context() as mp:
        even = watch(mp, unit, frames, sampled, bursts=False)
        held = watch(mp, unit, frames, sampled, bursts=True)
    # nine frames a burst, ten bursts a second
    assert even.bursts == 0 and held.bursts >= 9.9 * (BEFORE_S + AFTER_S)
    return even, held


def test_a_drive_read_in_bursts_is_watched_as_one_read_as_it_comes(
    read_two_ways: tuple[Watched, Watched],
) -> None:
    even, held = read_two_ways
    # the same frames (the calibrated field and gravity of each) at the same instants:
    # one sample per 0.09 s of the compass's clock, and that instant the frame's own
    a, b = even.samples, held.samples
    seconds = BEFORE_S + AFTER_S - LEAD_S
    assert a.shape == b.shape, f"{len(a) / seconds:.2f} vs {len(b) / seconds:.2f} samples/s"
    np.testing.assert_array_equal(b[:, 1:], a[:, 1:])
    np.testing.assert_allclose(b[:, 0], a[:, 0], rtol=0.0, atol=1e-6)
    assert np.diff(a[:, 0]) == pytest.approx(0.09, abs=1e-6)  # every ninth frame, always
    # ... sampled when the frames were (their clock: the least-delayed arrival)
    assert a[0, 0] - LATENCY_S == pytest.approx(T0 + LEAD_S, abs=1e-6)

    # the same fits: the same steadiness verdicts (the dip rows are the samples judged
    # steady), the same offsets
    assert [f.n_dip for f in held.fits] == [f.n_dip for f in even.fits]
    assert [f.n_field for f in held.fits] == [f.n_field for f in even.fits]
    np.testing.assert_allclose(
        [f.offset_G for f in held.fits], [f.offset_G for f in even.fits], rtol=0.0, atol=1e-9
    )

    # the same alarms, the same learning, the same state at the end
    def drift_events(w: Watched) -> list[tuple[str, dict[str, Any]]]:
        return [(e.kind, e.data) for e in w.events if e.kind.startswith("calibration.")]

    kinds = [k for k, _ in drift_events(even)]
    assert "calibration.drift" in kinds and "calibration.learned" in kinds, kinds
    assert drift_events(held) == drift_events(even)
    assert held.applied == even.applied and len(even.applied) >= 2
    assert held.status == even.status


def test_a_drive_read_in_bursts_gets_the_same_disturbance_events(
    read_two_ways: tuple[Watched, Watched],
) -> None:
    # The pipeline's disturbance events: at most one per 5 s, a change within the hold-off
    # told when it ends -- on the first frame after it, read either way.
    even, held = read_two_ways

    def disturbance(w: Watched) -> list[tuple[str, dict[str, Any]]]:
        return [(e.kind, e.data) for e in w.events if e.kind.startswith("disturbance.")]

    assert len(disturbance(even)) >= 4  # the drive's magnets, and held-off ends among them
    assert disturbance(held) == disturbance(even)
