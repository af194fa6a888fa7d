"""Method 6: PX4 face names, face detection, six-face fit, level trim."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.accel_faces import (
    Face,
    detect_face,
    face_from_px4_side,
    fit_six_face,
    level_trim,
)
from bridge.core import sensor
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.geometry import angle_diff_deg, axis_angle_to_dcm, euler_to_dcm
from bridge.sim.physics import SensorModel, UnitErrors

B_NED = np.array([0.2156, 0.0077, 0.4333])

# (roll, pitch) in degrees that put the unit on each face, written out by hand
FACE_ATTITUDE = {
    Face.LEVEL: (0.0, 0.0),
    Face.UPSIDE_DOWN: (180.0, 0.0),
    Face.NOSE_DOWN: (0.0, -90.0),
    Face.NOSE_UP: (0.0, 90.0),
    Face.LEFT_SIDE: (-90.0, 0.0),
    Face.RIGHT_SIDE: (90.0, 0.0),
}


def _acc_window(
    unit: UnitErrors, roll: float, pitch: float, n: int = 50, seed: int = 0
) -> np.ndarray:
    R = euler_to_dcm(math.radians(roll), math.radians(pitch), 0.3)
    s = SensorModel(unit, B_NED).sample(np.broadcast_to(R, (n, 3, 3)), np.random.default_rng(seed))
    return sensor.acc_counts_to_g(s.acc_counts)


def test_face_names_are_px4s() -> None:
    # PX4 detect_orientation_str: back, front, left, right, up, down
    assert {f.px4_side for f in Face} == {"down", "up", "front", "back", "left", "right"}
    assert Face.LEVEL.px4_side == "down"  # PX4 "right-side up"
    assert Face.UPSIDE_DOWN.px4_side == "up"
    assert Face.NOSE_DOWN.px4_side == "front"
    assert Face.NOSE_UP.px4_side == "back"  # PX4 "tail down"
    assert face_from_px4_side(" Left ") is Face.LEFT_SIDE
    with pytest.raises(ValueError):
        face_from_px4_side("sideways")
    # gravity vectors with the datasheet's sign (level = +1 g on z): PX4's negated
    assert Face.LEVEL.gravity_body == (0.0, 0.0, 1.0)
    assert Face.NOSE_DOWN.gravity_body == (1.0, 0.0, 0.0)
    assert Face.LEFT_SIDE.gravity_body == (0.0, -1.0, 0.0)
    assert Face.LEFT_SIDE.label == "on its left side"


@pytest.mark.parametrize("face", list(Face), ids=lambda f: f.name)
def test_detect_face_on_each_face(face: Face) -> None:
    # a realistic raw unit (offsets up to 0.2 g, gains +-5 %) is still recognised
    unit = UnitErrors.draw(np.random.default_rng(1))
    roll, pitch = FACE_ATTITUDE[face]
    assert detect_face(_acc_window(unit, roll, pitch)) is face
    # an ideal unit tipped away from the face about a horizontal axis: 15 deg counts, 25 does not
    ideal = UnitErrors(acc_noise_g=0.001)
    R_face = euler_to_dcm(math.radians(roll), math.radians(pitch), 0.0)
    rng = np.random.default_rng(2)
    for angle, expected in ((15.0, face), (25.0, None)):
        R = axis_angle_to_dcm([1.0, 1.0, 0.0], math.radians(angle)) @ R_face
        s = SensorModel(ideal, B_NED).sample(np.broadcast_to(R, (30, 3, 3)), rng)
        assert detect_face(sensor.acc_counts_to_g(s.acc_counts)) is expected


def test_detect_face_needs_stillness_and_gravity() -> None:
    ideal = UnitErrors(acc_noise_g=0.001)
    still = _acc_window(ideal, 0.0, 0.0)
    assert detect_face(still) is Face.LEVEL
    rng = np.random.default_rng(2)
    shaking = still + rng.normal(0.0, 0.05, still.shape)  # 50 mg vibration
    assert detect_face(shaking) is None
    assert detect_face(shaking, still_tol=0.1) is Face.LEVEL
    moving = np.array([_acc_window(ideal, 0.0, p, n=1)[0] for p in np.linspace(0, 15, 20)])
    assert detect_face(moving) is None
    assert detect_face(np.tile([0.0, 0.0, 0.02], (20, 1))) is None  # free fall
    assert detect_face(still[:3]) is None  # too short to judge
    bad = still.copy()
    bad[4, 1] = np.nan
    assert detect_face(bad) is None
    with pytest.raises(ValueError):
        detect_face(np.zeros((10, 2)))


def _face_means(unit: UnitErrors, n: int = 200) -> dict[Face, np.ndarray]:
    return {
        f: _acc_window(unit, *FACE_ATTITUDE[f], n=n, seed=i).mean(axis=0)
        for i, f in enumerate(Face)
    }


def test_six_face_recovers_offsets_gains_and_misalignment() -> None:
    gains = np.diag([1.05, 0.96, 1.03])
    nonorth = np.array([[1.0, 0.0, 0.0], [0.02, 1.0, 0.0], [-0.015, 0.01, 1.0]])
    tilt = axis_angle_to_dcm([0.3, -0.8, 0.5], math.radians(1.5))  # chip rotated in its case
    unit = UnitErrors(
        acc_offset_g=np.array([0.025, -0.018, 0.03]),
        acc_matrix=gains @ nonorth @ tilt,
        acc_adc_zero=np.array([12.0, -30.0, 7.0]),
        acc_noise_g=0.002,
    )
    res = fit_six_face(_face_means(unit))
    assert res.report.ok, res.report.notes
    truth = unit.true_calibration().accel
    np.testing.assert_allclose(res.calibration.accel.offset_array, truth.offset_array, atol=1e-3)
    np.testing.assert_allclose(res.calibration.accel.matrix_array, truth.matrix_array, atol=2e-3)
    assert res.calibration.mag.matrix_array.tolist() == np.eye(3).tolist()
    r = res.report
    assert r.n_samples == 6
    assert r.gravity_spread_before_mg > 20.0
    assert r.gravity_spread_after_mg < 2.0
    # a level reading now comes out level to within a milli-g
    level = res.calibration.accel.apply(_face_means(unit)[Face.LEVEL])
    np.testing.assert_allclose(level, [0.0, 0.0, 1.0], atol=1.5e-3)


def test_six_face_failures() -> None:
    means = _face_means(UnitErrors.draw(np.random.default_rng(3)), n=20)
    partial: dict[Face, np.ndarray] = {f: v for f, v in means.items() if f is not Face.NOSE_UP}
    res = fit_six_face(partial)
    assert res.report.status == "MAG_CAL_FAILED" and "back" in res.report.notes[0]
    swapped = dict(means)
    swapped[Face.LEVEL], swapped[Face.UPSIDE_DOWN] = means[Face.UPSIDE_DOWN], means[Face.LEVEL]
    res = fit_six_face(swapped)
    assert not res.report.ok and "does not point" in res.report.notes[0]
    assert res.calibration.accel.matrix_array.tolist() == np.eye(3).tolist()
    broken = dict(means)
    broken[Face.LEFT_SIDE] = np.array([np.nan, -1.0, 0.0])
    assert not fit_six_face(broken).report.ok
    with pytest.raises(ValueError):
        fit_six_face({**means, Face.RIGHT_SIDE: np.zeros(2)})


def test_level_trim_makes_the_current_mean_level_for_both_sensors() -> None:
    # sensor sits 3 deg rolled and 2 deg nose-down inside a vehicle standing level, heading 40
    crooked = euler_to_dcm(math.radians(3.0), math.radians(-2.0), 0.0)
    vehicle = euler_to_dcm(0.0, 0.0, math.radians(40.0))
    R_sensor = vehicle @ crooked
    acc = R_sensor.T @ np.array([0.0, 0.0, 1.0])
    mag = R_sensor.T @ B_NED
    counts = (*sensor.gauss_to_mag_counts(mag), *sensor.g_to_acc_counts(acc))
    cal = Calibration(
        mag=AffineCalibration((0.01, 0.0, -0.02)), accel=AffineCalibration((0.0, 0.0, 0.0))
    )
    counts = (*sensor.gauss_to_mag_counts(mag + np.array([0.01, 0.0, -0.02])), *counts[3:])

    before = AttitudeEngine(cal).solve_counts(*(float(c) for c in counts))
    assert math.degrees(before.roll) == pytest.approx(3.0, abs=1e-6)

    trimmed = level_trim(acc, cal)
    after = AttitudeEngine(trimmed).solve_counts(*(float(c) for c in counts))
    assert math.degrees(after.roll) == pytest.approx(0.0, abs=1e-9)
    assert math.degrees(after.pitch) == pytest.approx(0.0, abs=1e-9)
    # the magnetometer turned with it, so the heading is the vehicle's
    magnetic_north = math.degrees(math.atan2(B_NED[1], B_NED[0]))
    assert float(
        angle_diff_deg(after.heading_magnetic_deg, 40.0 - magnetic_north)
    ) == pytest.approx(0.0, abs=1e-6)
    assert trimmed.mag.offset == cal.mag.offset  # offsets untouched, only the frame turns


def test_level_trim_refuses_a_tilted_or_bad_reading() -> None:
    cal = Calibration()
    tilted = euler_to_dcm(math.radians(15.0), 0.0, 0.0).T @ np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="level-trim limit"):
        level_trim(tilted, cal)
    with pytest.raises(ValueError):
        level_trim(np.zeros(3), cal)
    with pytest.raises(ValueError):
        level_trim(np.array([0.0, math.nan, 1.0]), cal)
