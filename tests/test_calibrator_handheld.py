"""The live calibration by real hands: frames of a shaken tumble through the controller.

Every flow that fits a magnetometer calibration (ArduPilot's DO_START_MAG_CAL,
PX4's PREFLIGHT_CALIBRATION, zenoh's remote calibration, ``compass-bridge
calibrate``) drives :class:`CalibrationController.start_mag`; here its frames
come straight from the simulator's physics, on a simulated clock, so a
minute of tumbling takes a fraction of a second. The bar and the truth are
the simulator's (``handheld_rig``).
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field

import numpy as np
import pytest
from handheld_rig import FIELD, Tumbled, held, tumble

from bridge.app.calibration import CalibrationController
from bridge.calibration.fits.sanity import MagCalStatus
from bridge.calibration.sessions import CalibratorSettings, Failure, Phase
from bridge.calibration.sessions.motion import MOTION_TEXT, FrameSeries, MotionJudge
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import Calibration
from bridge.events import Event, EventBus, Severity
from bridge.mavlink import calmap
from bridge.mavlink.commands import CalibrationRelay

WAIT_S = 30.0  #: real seconds any wait may take before the test fails


@dataclass
class Clock:
    """The controller's clock: the simulated time of the frame being fed."""

    t: float = 1000.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Events:
    """A bus subscriber keeping every event; waits are bounded."""

    items: list[Event] = field(default_factory=list)
    cond: threading.Condition = field(default_factory=threading.Condition)

    def __call__(self, e: Event) -> None:
        with self.cond:
            self.items.append(e)
            self.cond.notify_all()

    def of(self, kind: str) -> list[Event]:
        with self.cond:
            return [e for e in self.items if e.kind == kind]

    def wait_any(self, kinds: tuple[str, ...], timeout: float = WAIT_S) -> Event:
        with self.cond:
            ok = self.cond.wait_for(lambda: any(e.kind in kinds for e in self.items), timeout)
            assert ok, f"none of {kinds} within {timeout} s"
            return next(e for e in self.items if e.kind in kinds)


# The simulation is deterministic in its arguments and no test changes a recording: the
# tumble that three tests calibrate (each with its own limits) is simulated once.
_tumble = functools.cache(tumble)


def calibrate_live(
    rec: Tumbled, settings: CalibratorSettings | None = None, fit_limit_mG: float | None = None
) -> tuple[CalibrationController, Events, Calibration]:
    """Start a host magnetometer calibration and feed it the tumble until it ends; accept it.

    ``fit_limit_mG`` is COMPASS_CAL_FIT (None: ArduPilot's default, 16 mG)."""
    clock, events, bus = Clock(), Events(), EventBus()
    bus.subscribe(events)
    ctl = CalibrationController(AttitudeEngine(), bus, field=FIELD, settings=settings, clock=clock)
    ctl.run_inline()  # the fits run in this thread, on the tumble's clock
    if fit_limit_mG is not None:
        ctl.fitness_limit_mG = fit_limit_mG
    assert ctl.start_mag().ok
    step_one = True
    for t, frame in zip(rec.t.tolist(), rec.frames(), strict=True):
        clock.t = 1000.0 + t
        ctl.feed(frame)
        snap = ctl.snapshot()
        if step_one and snap.completion_pct >= 33.2:
            # step one's buffer is full: the worker fits its sphere before going on
            step_one = False
            ctl.step()
            assert ctl.snapshot().step != 1 or not ctl.snapshot().running
        if not snap.running or (snap.step == 2 and snap.completion_pct >= 98.9):
            break
    ctl.step()  # the final fit
    done = ctl.snapshot()
    assert not done.running, done
    events.wait_any(("calibration.done", "calibration.failed"))
    before = ctl._engine.calibration
    if done.phase is Phase.SUCCEEDED:
        assert ctl.accept().ok
    return ctl, events, before


def test_shaken_tumble_through_the_controller_reaches_the_floor() -> None:
    rec = _tumble(3, 0.05, seconds=150.0)
    ctl, events, _ = calibrate_live(rec)
    try:
        done = events.of("calibration.done")
        assert len(done) == 1, [e.text for e in events.items if e.kind != "calibration.progress"]
        report = done[0].data["report"]
        cal = ctl._engine.calibration
        s = held(rec, {"bridge": cal})
        assert s["bridge"].rms_deg <= 1.3 * s["floor"].rms_deg, s
        assert s["bridge"].max_deg <= s["floor"].max_deg + 0.15, s
        assert s["bridge"].tilt_max_deg <= s["floor"].tilt_max_deg + 0.05, s
        # the report (MAG_CAL_REPORT's fields) says how good it is and what it saw
        assert 0.03 < report["motion_g"] < 0.06 and 0.0 < report["heading_error_deg"] < 0.25
        assert report["residual_mG"] <= report["fitness"] < 1.5 * report["residual_mG"]
        # a hand's usual shake is nothing to warn about
        assert not events.of("calibration.motion")
    finally:
        ctl.close()


def test_violent_motion_is_told_while_it_happens_and_the_calibration_fails() -> None:
    rec = tumble(4, 0.3, seconds=150.0, dps=90.0)
    ctl, events, before = calibrate_live(rec)
    try:
        warnings = events.of("calibration.motion")
        assert warnings, "no motion warning"
        started = events.of("calibration.started")[0].t_monotonic
        failed = events.of("calibration.failed")
        assert len(failed) == 1 and not events.of("calibration.done")
        for w in warnings:
            assert w.severity is Severity.WARNING and w.text == MOTION_TEXT
            assert len(w.text) <= 50 and "slower" in w.text and "steadier" in w.text
            assert w.data["accel_rms_g"] > w.data["limit_g"] == 0.09
            assert w.data["mode"] == "mag"
        # told while collecting, and not more than once per 5 s of the tumble
        assert all(started <= w.t_monotonic <= failed[0].t_monotonic for w in warnings)
        seconds = float(rec.t[-1])
        assert len(warnings) <= seconds / 5.0 + 1
        f = failed[0].data
        assert f["failure"] == "failed_residuals"  # MAVLink: MAG_CAL_FAILED_RESIDUALS_HIGH
        assert "slower / steadier" in f["reason"]
        assert ctl._engine.calibration == before
    finally:
        ctl.close()


def test_a_tight_accuracy_limit_fails_a_calibration_that_cannot_reach_it() -> None:
    rec = _tumble(3, 0.05, seconds=150.0)
    ctl, events, before = calibrate_live(rec, CalibratorSettings(max_heading_error_deg=0.001))
    try:
        failed = events.of("calibration.failed")
        assert len(failed) == 1
        # the limit is the operator's 0.001 deg, or what this quiet sensor's noise over
        # its thousands of frames allows (3x the floor): still far below what it leaves
        report = failed[0].data["report"]
        assert 0.001 <= report["heading_limit_deg"] < 0.02
        assert report["predicted_heading_deg"] > report["heading_limit_deg"]
        assert failed[0].data["reason"].startswith("heading error ~")
        assert failed[0].data["reason"].endswith(": turn slower / steadier")
        assert report["heading_error_deg"] > 0.001
        assert ctl.accept().result.value == "failed"
        assert ctl._engine.calibration == before
    finally:
        ctl.close()


def test_a_fit_above_compass_cal_fit_fails_as_ardupilot_fails_it() -> None:
    # The fitness limit is COMPASS_CAL_FIT (the application keeps it so); a fit above it
    # fails with MAG_CAL_FAILED_RESIDUALS_HIGH, saying which limit it broke.
    rec = _tumble(3, 0.05, seconds=150.0)
    ctl, events, before = calibrate_live(rec, fit_limit_mG=0.3)
    try:
        failed = events.of("calibration.failed")
        assert len(failed) == 1 and not events.of("calibration.done")
        f = failed[0].data
        assert f["failure"] == "failed_residuals"
        assert calmap.mag_cal_status(Phase.FAILED, 2, Failure(f["failure"])) == (
            MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH
        )
        assert "above COMPASS_CAL_FIT 0.3" in f["reason"]
        assert f["reason"].endswith(": keep iron away while turning, or raise COMPASS_CAL_FIT")
        assert f["report"]["fitness"] > 0.3  # the good fit of the first test, judged stricter
        assert ctl.accept().result.value == "failed"
        assert ctl._engine.calibration == before
        with pytest.raises(ValueError):
            ctl.fitness_limit_mG = math.nan
    finally:
        ctl.close()


def test_motion_judge_warns_over_its_limit_at_most_once_per_interval() -> None:
    judge = MotionJudge(limit_g=0.09, interval_s=5.0)
    shaken = tumble(2, 0.2, seconds=30.0)
    got = [judge.feed(float(t), tuple(a)) for t, a in zip(shaken.t, shaken.acc, strict=True)]
    times = [float(shaken.t[i]) for i, w in enumerate(got) if w is not None]
    assert len(times) >= 5 and np.all(np.diff(times) >= 5.0)
    assert times[0] <= 4.0  # within a few seconds of the shaking
    w = next(w for w in got if w is not None)
    assert w.level_g > 0.09 and w.data()["instruction"] == "turn slower / steadier"
    assert judge.peak_g > 0.12
    calm = MotionJudge(limit_g=0.09)
    steady = tumble(2, 0.05, seconds=60.0)
    assert all(
        calm.feed(float(t), tuple(a)) is None for t, a in zip(steady.t, steady.acc, strict=True)
    )
    assert 0.02 < calm.peak_g < 0.09
    assert MotionJudge().feed(0.0, (0.0, 0.0, 1.0)) is None  # nothing to judge yet
    with pytest.raises(ValueError):
        MotionJudge(limit_g=0.0)


def test_frame_series_keeps_the_newest_frames_in_order() -> None:
    s = FrameSeries(capacity=4)
    for k in range(6):
        s.add(float(k), (k, 0.0, 0.0), (0.0, 0.0, 1.0), k == 5)
    t, mag, acc, sat = s.arrays()
    assert t.tolist() == [2.0, 3.0, 4.0, 5.0] and len(s) == 4
    assert mag[:, 0].tolist() == [2.0, 3.0, 4.0, 5.0] and sat.tolist() == [0, 0, 0, 1]
    assert np.all(acc[:, 2] == 1.0)


def test_the_ardupilot_flow_relays_the_warning_as_statustext() -> None:
    relay = CalibrationRelay()
    relay.begin("ardupilot")
    e = Event("calibration.motion", MOTION_TEXT, Severity.WARNING, {"accel_rms_g": 0.2})
    packets = relay.packets(e)
    assert packets and any(p.text == MOTION_TEXT for p in packets)
