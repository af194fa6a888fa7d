"""The drift monitor (bridge.app.calibration.drift) fed simulated drives, and its place in the bridge.

The frames go through the real attitude engine to :meth:`DriftMonitor.observe`,
as the pipeline does, with drive time as the samples' time: minutes of driving
take a fraction of a second, no clock, no sleeps. The bridge-level tests run
the application (parameters, calibration store and controller) on a state
directory, without starting its threads.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from benchmarks.drift import Unit
from bridge.app.calibration.drift import LEARNED, DriftMonitor, DriftStatus
from bridge.app.settings import EngineSettings
from bridge.calibration.drift.estimator import DriftSettings
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import Calibration
from bridge.core.wmm import earth_field
from bridge.events import Event, EventBus, Severity
from bridge.sim.physics import DEFAULT_LOCATION

FIELD = earth_field(*DEFAULT_LOCATION)
CHANGE_G = (0.012, -0.028, 0.025)  # 40 mG, sensor axes


class Rig:
    """A unit driving through the engine into a monitor; learned calibrations applied."""

    def __init__(
        self,
        seed: int = 2,
        mode: str = "detect",
        calibrating: Callable[[], bool] = lambda: False,
        **kw: Any,
    ) -> None:
        self.unit = Unit(seed, 10.0, FIELD)
        self.start_cal = kw.pop("calibration", None) or self.unit.errors.true_calibration()
        self.engine = AttitudeEngine(self.start_cal)
        self.settings = EngineSettings(self.engine, field=FIELD)
        self.events = EventBus()
        self.log: list[Event] = []
        self.events.subscribe(self.log.append)
        self.applied: list[tuple[Calibration, str]] = []
        self.t = 0.0
        self.monitor = DriftMonitor(
            self.settings,
            self.events,
            apply=self._apply,
            calibrating=calibrating,
            mode=mode,
            **kw,
        )

    def _apply(self, cal: Calibration, source: str, report: Any, view: Any) -> str:
        self.applied.append((cal, source))
        self.settings.update_calibration(cal, source)
        return ""

    def drive(self, seconds: float, changed: bool = False) -> None:
        model = self.unit.model.with_hard_iron_change(CHANGE_G) if changed else None
        ts, s = self.unit.frames(self.t, self.t + seconds, model)
        # (As Python numbers, as the decoder gives them: numpy scalars through the engine's
        # plain-float formulas give the same values at three times the cost.)
        mc, ac, sat = s.mag_counts.tolist(), s.acc_counts.tolist(), s.saturated.tolist()
        for t, m, a, sa in zip(ts.tolist(), mc, ac, sat, strict=True):
            self.monitor.observe(self.engine.solve_counts(*m, *a), t, sa)
        self.t += seconds

    def kinds(self) -> list[str]:
        return [e.kind for e in self.log]

    def truth_left_mG(self) -> np.ndarray:
        """The change left in the calibration in use (body axes), from the simulator's truth."""
        true = self.unit.model.with_hard_iron_change(CHANGE_G).errors.true_calibration()
        m = self.engine.calibration.mag
        return np.asarray(1000.0 * m.matrix_array @ (true.mag.offset_array - m.offset_array))


def test_a_change_is_announced_once_as_a_warning_with_the_change_and_heading_error() -> None:
    rig = Rig()
    rig.drive(120.0)
    assert rig.kinds() == [] and rig.monitor.status().state == "ok"
    rig.drive(90.0, changed=True)
    drift = [e for e in rig.log if e.kind == "calibration.drift"]
    assert len(drift) == 1 and rig.applied == []  # detect only: nothing applied
    e = drift[0]
    assert e.severity is Severity.WARNING and "drift" in e.text and len(e.text) <= 50
    truth = rig.truth_left_mG()
    np.testing.assert_allclose(e.data["offset_change_mG"], truth, atol=3.0)
    assert e.data["change_mG"] == pytest.approx(float(np.linalg.norm(truth)), abs=3.0)
    h = FIELD.horizontal_G
    err = math.degrees(math.asin(math.hypot(*truth[:2]) / 1000.0 / h))
    assert e.data["heading_error_deg"] == pytest.approx(err, abs=1.0)
    assert f"{e.data['change_mG']:.0f}mG" in e.text
    st = rig.monitor.status()
    assert st.state == "drift" and st.drift and st.to_dict()["detected"] is True
    assert st.change_mG == pytest.approx(e.data["change_mG"], abs=3.0)


class Learned:
    """The learning drive (120 s, then 180 s with the hard iron changed) and the modes the
    monitor was turned to (``on_mode``)."""

    def __init__(self) -> None:
        self.lowered: list[str] = []
        self.rig = Rig(mode="learn", on_mode=self.lowered.append)
        self.rig.drive(120.0)
        self.rig.drive(180.0, changed=True)


@pytest.fixture(scope="module")
def _drives() -> list[Learned]:
    """The module's costliest drive, kept (at most one, never undone) for the next test
    that asks: the learning test only reads it, the undo test takes it away and undoes it.
    In file order it is driven once; in any other order (xdist stealing the undo test)
    each test still gets a drive of its own, as before."""
    return []


@pytest.fixture
def learned(_drives: list[Learned]) -> Learned:
    """A learning drive to judge (kept for the undo test)."""
    if not _drives:
        _drives.append(Learned())
    return _drives[0]


@pytest.fixture
def learned_to_undo(_drives: list[Learned]) -> Learned:
    """A learning drive to undo (taken: no later test sees it undone)."""
    return _drives.pop() if _drives else Learned()


def test_learning_applies_bounded_steps_and_brings_the_offsets_back(learned: Learned) -> None:
    rig = learned.rig
    kinds = rig.kinds()
    assert "calibration.drift" in kinds and "calibration.learned" in kinds
    assert kinds.index("calibration.drift") < kinds.index("calibration.learn_step")
    steps = [e for e in rig.log if e.kind == "calibration.learn_step"]
    assert 2 <= len(steps) == len(rig.applied)
    cfg = rig.monitor.config
    assert all(np.linalg.norm(e.data["step_mG"]) <= cfg.learn_step_mG + 0.02 for e in steps)
    assert all(source == LEARNED for _, source in rig.applied)
    assert np.linalg.norm(rig.truth_left_mG()) < 2.0  # was 40
    # only the offsets moved: the soft iron and the accelerometer are the calibration's own
    cal = rig.engine.calibration
    assert cal.mag.matrix == rig.start_cal.mag.matrix and cal.accel == rig.start_cal.accel
    st = rig.monitor.status()
    assert st.steps == len(steps) and st.learned_mG == pytest.approx(40.0, abs=3.0)


def test_nothing_is_judged_while_a_calibration_runs() -> None:
    calibrating = [True]
    rig = Rig(mode="learn", calibrating=lambda: calibrating[0])
    rig.drive(120.0)
    rig.drive(120.0, changed=True)  # a "change" seen only while calibrating
    assert rig.kinds() == [] and rig.applied == []
    assert rig.monitor.status().state == "collecting"
    # afterwards the drive is watched again; the calibration did not change, so what
    # changed meanwhile is drift all the same
    calibrating[0] = False
    rig.drive(120.0, changed=True)
    assert rig.kinds()[0] == "calibration.drift"


def test_off_watches_nothing_and_a_new_calibration_starts_over() -> None:
    rig = Rig(mode="off")
    rig.drive(60.0)
    rig.drive(120.0, changed=True)
    assert rig.kinds() == [] and rig.monitor.status() == DriftStatus("off", "off")
    rig.monitor.set_mode("detect")
    assert rig.monitor.status().state == "collecting"
    rig.drive(120.0, changed=True)  # a change made while nobody watched is still drift
    assert rig.monitor.status().state == "drift"
    # someone else's calibration (an accepted fit): the monitor forgets and starts over
    rig.settings.update_calibration(rig.unit.model.with_hard_iron_change(CHANGE_G)
                                    .errors.true_calibration(), "mag")  # fmt: skip
    rig.drive(10.0, changed=True)
    assert rig.monitor.status().state == "collecting"
    rig.drive(120.0, changed=True)  # the new calibration holds: no drift
    assert rig.monitor.status().state == "ok" and rig.kinds() == ["calibration.drift"]
    with pytest.raises(ValueError):
        rig.monitor.set_mode("sometimes")


def test_undo_goes_back_to_where_learning_started_once(learned_to_undo: Learned) -> None:
    # before any drive (a fresh monitor, learning as the drive's): nothing to undo
    assert Rig(mode="learn").monitor.undo() == (False, "Nothing learned to undo")
    rig, lowered = learned_to_undo.rig, learned_to_undo.lowered
    assert rig.applied
    done, text = rig.monitor.undo()
    assert done and "detect" in text
    assert rig.engine.calibration == rig.start_cal  # no state directory: the one in memory
    assert rig.monitor.mode == "detect" and lowered == ["detect"]
    assert rig.log[-1].kind == "calibration.undo" and rig.log[-1].data["done"] is True
    assert rig.monitor.undo()[0] is False  # a repeated request finds nothing to undo


@pytest.mark.integration
def test_the_monitor_thread_processes_the_blocks() -> None:
    rig = Rig()
    seen = threading.Event()
    rig.events.subscribe(lambda e: seen.set() if e.kind == "calibration.drift" else None)
    rig.monitor.start()
    try:
        rig.drive(120.0)
        rig.drive(90.0, changed=True)
        assert seen.wait(10.0), "no drift event from the monitor's thread"
    finally:
        rig.monitor.close(2.0)
    assert rig.monitor.errors == 0


def test_deferred_blocks_wait_for_drain() -> None:
    rig = Rig(deferred=True, config=DriftSettings(block_s=5.0))
    rig.drive(60.0)
    assert rig.monitor.status().state == "collecting"  # nothing processed yet
    assert rig.monitor.drain() == 11  # 60 s of 5 s blocks (the last one still filling)
    assert rig.monitor.status().state == "ok" and rig.monitor.drain() == 0


def test_an_uncalibrated_unit_is_not_watched() -> None:
    rig = Rig(mode="learn", calibration=Calibration())  # the identity: nothing to drift from
    rig.drive(120.0)
    rig.drive(60.0, changed=True)
    assert rig.kinds() == [] and rig.applied == []
    assert rig.monitor.status().state == "uncalibrated"
