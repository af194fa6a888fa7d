"""Method 2, twelve positions: the full 12-parameter model from known attitudes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.twelve_position import (
    TWELVE_POSITIONS,
    fit_twelve_position,
    twelve_position_attitudes,
)
from bridge.core import sensor
from bridge.core.attitude import tilt_compensated_heading
from bridge.core.geometry import angle_diff_deg, euler_to_dcm_batch, random_rotations
from bridge.sim.physics import SensorModel, UnitErrors

B_NED = np.array([0.2156, 0.0077, 0.4333])


def _collect(unit: UnitErrors, R: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    s = SensorModel(unit, B_NED).sample(R, np.random.default_rng(seed))
    assert not s.saturated.any()
    return sensor.mag_counts_to_gauss(s.mag_counts), sensor.acc_counts_to_g(s.acc_counts)


def test_the_twelve_stops_are_six_faces_times_north_and_south() -> None:
    assert len(TWELVE_POSITIONS) == 12
    R = twelve_position_attitudes()
    gravity = R[:, 2, :]  # body reading of gravity at each stop
    faces = {tuple(np.round(g).astype(int)) for g in gravity}
    assert faces == {(0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)}
    yaws = sorted({round(math.degrees(y)) % 360 for _, _, y in TWELVE_POSITIONS})
    assert yaws == [0, 180]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), (12, 3, 3)), atol=1e-12
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_recovers_offsets_full_matrix_and_misalignment(seed: int) -> None:
    rng = np.random.default_rng(seed)
    unit = UnitErrors.draw(rng, misalign_deg=3.0)
    R = np.repeat(twelve_position_attitudes(), 20, axis=0)
    mag, acc = _collect(unit, R, seed)
    res = fit_twelve_position(mag, R, B_NED, acc_g=acc)
    assert res.report.ok, res.report.notes
    truth = unit.true_calibration()
    np.testing.assert_allclose(res.calibration.mag.offset_array, truth.mag.offset_array, atol=3e-4)
    np.testing.assert_allclose(res.calibration.mag.matrix_array, truth.mag.matrix_array, atol=2e-3)
    np.testing.assert_allclose(
        res.calibration.accel.offset_array, truth.accel.offset_array, atol=2e-3
    )
    np.testing.assert_allclose(
        res.calibration.accel.matrix_array, truth.accel.matrix_array, atol=3e-3
    )
    r = res.report
    assert r.n_samples == 240 and r.radius_G == pytest.approx(float(np.linalg.norm(B_NED)))
    assert r.fitness_mG < 1.5  # ~ the 0.5 mG noise
    assert r.field_spread_after_nT < 0.1 * r.field_spread_before_nT
    assert r.gravity_rms_after_mg < 5.0

    # Heading on fresh attitudes: the misalignment (up to 3 deg) is gone.
    Rt = random_rotations(rng, 300)
    Rt = Rt[np.abs(Rt[:, 2, 0]) < math.sin(math.radians(60))]
    mag_t, acc_t = _collect(unit, Rt, seed + 100)
    _, _, hdg = tilt_compensated_heading(
        res.calibration.mag.apply(mag_t), res.calibration.accel.apply(acc_t)
    )
    truth_hdg = np.degrees(np.arctan2(Rt[:, 1, 0], Rt[:, 0, 0])) - math.degrees(
        math.atan2(B_NED[1], B_NED[0])
    )
    err = np.abs(angle_diff_deg(hdg, truth_hdg))
    assert float(np.sqrt(np.mean(err**2))) < 0.4


def test_accelerometer_left_alone_when_stops_do_not_span_gravity() -> None:
    unit = UnitErrors.draw(np.random.default_rng(4))
    # level, upside down and right side only: gravity directions lie in one plane
    roll = np.radians([0, 0, 0, 0, 180, 180, 180, 180, 90, 90, 90, 90])
    yaw = np.radians([0, 90, 180, 270] * 3)
    R = np.repeat(euler_to_dcm_batch(roll, np.zeros(12), yaw), 10, axis=0)
    mag, acc = _collect(unit, R, 4)
    res = fit_twelve_position(mag, R, B_NED, acc_g=acc)
    assert res.report.ok
    assert any("accelerometer not fitted" in n for n in res.report.notes)
    assert res.calibration.accel.matrix_array.tolist() == np.eye(3).tolist()
    np.testing.assert_allclose(
        res.calibration.mag.offset_array, unit.true_calibration().mag.offset_array, atol=5e-4
    )


def test_degenerate_and_bad_input() -> None:
    unit = UnitErrors.draw(np.random.default_rng(5))
    one = np.repeat(twelve_position_attitudes()[:1], 30, axis=0)  # never moved
    mag, _ = _collect(unit, one, 5)
    res = fit_twelve_position(mag, one, B_NED)
    assert res.report.status == "MAG_CAL_FAILED_ORIENTATION"
    assert res.calibration.mag.matrix_array.tolist() == np.eye(3).tolist()
    assert all(math.isfinite(v) for v in res.calibration.mag.offset)

    R = twelve_position_attitudes()
    mag, _ = _collect(unit, R, 6)
    assert fit_twelve_position(mag[:3], R[:3], B_NED).report.status == "MAG_CAL_FAILED"
    with pytest.raises(ValueError):
        fit_twelve_position(mag, R[:11], B_NED)
    with pytest.raises(ValueError):
        fit_twelve_position(mag, R * 1.1, B_NED)  # not rotations
    with pytest.raises(ValueError):
        fit_twelve_position(mag, R, np.zeros(3))
    mag[2] = np.nan
    res = fit_twelve_position(mag, R, B_NED)
    assert res.report.ok and res.report.n_rejected == 1
