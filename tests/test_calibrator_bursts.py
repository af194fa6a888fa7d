"""A live hand-held calibration is as good when the link reads its frames in bursts as when
it reads each frame as it comes.

At 100 Hz with the outputs' streams at 10 Hz the link holds the port and reads nine frames
at once, then the tenth as it comes (docs/architecture.md, "How a frame travels"); a USB
serial adapter or a busy host delivers frames in bunches too. The calibration's series fits
split the frames into runs where time jumps and take the frames within a run as evenly
spaced. When they were handed each frame's arrival, nine frames looked sampled within a
millisecond and the tenth 0.1 s later, every run was one burst long, and a hand-held
tumble that calibrates to 0.03 deg read as evenly came out at 1.0 deg, over the limit. The
pipeline hands the controller the instant each frame was sampled (its frame clock, from
``seq``), as it hands the attitude engine.

In memory: the application's pipeline and calibration controller on a manual clock, fed
the simulated frames of one hand-held tumble, read two ways.
"""

from __future__ import annotations

from collections.abc import Callable

from handheld_rig import FIELD, tumble
from harness import ManualClock

from bridge.app.calibration import CalibrationController
from bridge.app.pipeline import Pipeline
from bridge.calibration.sessions import Phase
from bridge.core.attitude import AttitudeEngine
from bridge.events import Event, EventBus
from bridge.protocol.gmr import AttitudeFrame

RATE_HZ = 100.0
#: Frames before the calibration starts: the frame clock learns the compass's rate (4 s of
#: arrivals), as it has long before anyone starts a calibration on a running bridge.
LEAD_FRAMES = 600


def as_they_come(i: int) -> float:
    """Frame ``i`` read as it comes: at its sampling instant."""
    return i / RATE_HZ


def in_bursts(i: int) -> float:
    """Frame ``i`` read as the link reads at 100 Hz with streams at 10 Hz: nine frames held
    and read together 1 ms before the tenth is sampled (0.05 ms apart, as the pipeline
    takes them), the tenth as it comes (0.5 ms after it was sampled)."""
    burst, k = divmod(i, 10)
    return burst / 10.0 + (0.0905 if k == 9 else 0.089 + k * 5e-5)


def calibrate(frames: list[AttitudeFrame], arrival: Callable[[int], float]) -> dict[str, object]:
    """A host magnetometer calibration of a tumble's ``frames`` read at ``arrival(i)``: the
    ``calibration.done`` or ``calibration.failed`` event's data."""
    clock = ManualClock(0.0)
    seen: list[Event] = []
    bus = EventBus()
    bus.subscribe(seen.append)
    engine = AttitudeEngine()
    ctl = CalibrationController(engine, bus, field=FIELD, clock=clock)
    ctl.run_inline()  # its fits in this thread, on the manual clock
    pipeline = Pipeline(engine, bus, feed=ctl.feed, calibrating=ctl.calibrating)
    try:
        step_one = True
        for i, frame in enumerate(frames):
            clock.t = arrival(i)
            pipeline.process(frame, clock.t)
            if i == LEAD_FRAMES:
                assert ctl.start_mag().ok
            if i <= LEAD_FRAMES:
                continue
            snap = ctl.snapshot()
            if step_one and snap.completion_pct >= 33.2:
                step_one = False
                ctl.step()  # step one's sphere, as the worker fits it
            if not snap.running or (snap.step == 2 and snap.completion_pct >= 98.9):
                break
        ctl.step()  # the final fit
        assert ctl.snapshot().phase in (Phase.SUCCEEDED, Phase.FAILED), ctl.snapshot()
        ends = [e for e in seen if e.kind in ("calibration.done", "calibration.failed")]
        assert len(ends) == 1, [e.kind for e in seen]
        return {"kind": ends[0].kind, **ends[0].data}
    finally:
        ctl.close()


def test_a_tumble_read_in_bursts_calibrates_as_well_as_one_read_as_it_comes() -> None:
    # a steady hand (0.05 g RMS of shake), 45 deg/s, the compass at 100 Hz
    rec = tumble(3, 0.05, seconds=150.0, rate_hz=RATE_HZ, dps=45.0)
    frames = rec.frames()  # (frozen: both readings get the same frames, built once)
    even = calibrate(frames, as_they_come)
    bursts = calibrate(frames, in_bursts)
    assert even["kind"] == "calibration.done", even.get("reason")
    assert bursts["kind"] == "calibration.done", bursts.get("reason")
    predicted = {}
    for name, result in (("even", even), ("bursts", bursts)):
        report = result["report"]
        assert isinstance(report, dict)
        predicted[name] = float(report["predicted_heading_deg"])
    # the same fit of the same frames: the bursts cost it nothing (it was 30 times worse)
    assert predicted["bursts"] <= 1.1 * predicted["even"], predicted
    assert predicted["even"] < 0.1, predicted
