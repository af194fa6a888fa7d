"""Method 7: magnetometer-only attitude from a field database (constrained motion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.field_database import FieldDatabase
from bridge.core import sensor
from bridge.core.geometry import angle_diff_deg, dcm_to_euler, euler_to_dcm, random_rotations
from bridge.sim.physics import SensorModel, UnitErrors

B_NED = np.array([0.2156, 0.0077, 0.4333])
PITCH, YAW = math.radians(10.0), math.radians(60.0)  # the known spin axis: body x at this attitude


def spin_attitudes(rolls_rad: np.ndarray) -> np.ndarray:
    """A body spinning about its x axis, which points at heading 60, 10 deg up."""
    return np.array([euler_to_dcm(float(r), PITCH, YAW) for r in rolls_rad])


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(Ra.T @ Rb)) - 1.0) / 2.0))))


def _recorded_spin_database(step_deg: float, seed: int = 0) -> tuple[FieldDatabase, UnitErrors]:
    """Record like a user would: a calibrated unit turned through known roll angles."""
    rng = np.random.default_rng(seed)
    unit = UnitErrors.draw(rng)
    rolls = np.radians(np.arange(-180.0, 180.0, step_deg))
    R = spin_attitudes(rolls)
    s = SensorModel(unit, B_NED).sample(R, rng)
    mag = unit.true_calibration().mag.apply(sensor.mag_counts_to_gauss(s.mag_counts))
    db = FieldDatabase()
    assert db.add(mag, R) == len(rolls)
    return db, unit


def test_spinning_body_roll_within_3_deg_and_attitude_within_5() -> None:
    db, unit = _recorded_spin_database(5.0)
    rng = np.random.default_rng(1)
    rolls = rng.uniform(-math.pi, math.pi, 200)
    R = spin_attitudes(rolls)
    s = SensorModel(unit, B_NED).sample(R, rng)
    mag = unit.true_calibration().mag.apply(sensor.mag_counts_to_gauss(s.mag_counts))
    roll_err, att_err = [], []
    for Ri, m, r in zip(R, mag, rolls, strict=True):
        Re, match = db.attitude_from_field(m)
        assert match.ok, match.reason
        roll_err.append(
            abs(float(angle_diff_deg(math.degrees(dcm_to_euler(Re)[0]), math.degrees(r))))
        )
        att_err.append(rotation_error_deg(Re, Ri))
    assert max(roll_err) < 3.0
    assert max(att_err) < 5.0
    # interpolation, not just the nearest entry (which is up to 2.5 deg off)
    assert float(np.sqrt(np.mean(np.square(roll_err)))) < 1.0


def test_sparse_database_is_flagged() -> None:
    db, _ = _recorded_spin_database(40.0)
    halfway = spin_attitudes(np.radians(np.arange(-160.0, 180.0, 40.0)))
    flags = [db.attitude_from_field(R.T @ B_NED)[1] for R in halfway]
    assert sum(not f.ok for f in flags) >= len(flags) // 2
    assert all(f.nearest_deg > 0.0 for f in flags)


def test_unconstrained_motion_is_ambiguous_and_says_so() -> None:
    rng = np.random.default_rng(2)
    db = FieldDatabase.from_field_model(B_NED, random_rotations(rng, 3000))
    results = [db.attitude_from_field(R.T @ B_NED) for R in random_rotations(rng, 50)]
    flagged = sum(not m.ok for _, m in results)
    assert flagged >= 45
    assert all("ambiguous" in m.reason or "sparse" in m.reason for _, m in results if not m.ok)
    assert all(np.all(np.isfinite(R)) for R, _ in results)


def test_add_validates_counts_and_converts_true_north() -> None:
    db = FieldDatabase()
    R = euler_to_dcm(0.0, 0.0, math.radians(30.0))
    assert db.add(R.T @ B_NED, R) == 1
    bad_mag = np.array([[np.nan, 0.0, 0.4], [0.0, 0.0, 0.0], [0.2, 0.0, 0.4]])
    bad_R = np.array([np.eye(3), np.eye(3), 2.0 * np.eye(3)])  # last: not a rotation
    assert db.add(bad_mag, bad_R) == 0
    assert db.rejected == 3 and len(db) == 1
    with pytest.raises(ValueError):
        db.add(np.zeros((2, 3)), np.zeros((3, 3, 3)))

    # attitudes recorded against true north, declination +10: stored as magnetic
    true_db = FieldDatabase()
    true_db.add(R.T @ B_NED, R, declination_deg=10.0)
    Re, match = true_db.attitude_from_field(R.T @ B_NED)
    assert match.ok
    assert math.degrees(dcm_to_euler(Re)[2]) == pytest.approx(20.0, abs=1e-6)


def test_empty_or_zero_field_is_not_nan() -> None:
    R, match = FieldDatabase().attitude_from_field([0.2, 0.0, 0.4])
    assert not match.ok and match.reason == "empty database"
    assert R.tolist() == np.eye(3).tolist()
    db = FieldDatabase.from_field_model(B_NED, spin_attitudes(np.radians(np.arange(0, 360, 10.0))))
    R, match = db.attitude_from_field([0.0, 0.0, 0.0])
    assert not match.ok and np.all(np.isfinite(R))
    with pytest.raises(ValueError):
        FieldDatabase(k=0)
