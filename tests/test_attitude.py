"""Attitude engine: datasheet formulas, quadrants, tilt, gimbal zone, mounting, declination."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.core import sensor
from bridge.core.attitude import (
    AttitudeEngine,
    FieldReference,
    attitude_matrix_from_vectors,
    tilt_compensated_heading,
)
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.geometry import (
    angle_diff_deg,
    euler_to_dcm,
    euler_to_quaternion,
    quaternion_to_dcm,
    random_rotations,
)
from bridge.core.mounting import Mounting, Rotation, rotation_matrix
from bridge.core.wmm import earth_field
from bridge.sim.physics import SensorModel, UnitErrors

BN, BD = 0.20, 0.45  # a mid-latitude field: 0.2 G north, 0.45 G down (dip ~66 deg)
B_NED = np.array([BN, 0.0, BD])


def counts(mag_body_G: np.ndarray, acc_body_g: np.ndarray) -> tuple[float, ...]:
    """Unquantised counts of an ideal unit (nominal transfer), as floats."""
    m = sensor.gauss_to_mag_counts(mag_body_G)
    a = sensor.g_to_acc_counts(acc_body_g)
    return (*(float(v) for v in m), *(float(v) for v in a))


def frame_at(
    roll_deg: float, pitch_deg: float, yaw_deg: float, B: np.ndarray = B_NED
) -> tuple[float, ...]:
    R = euler_to_dcm(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    return counts(R.T @ B, R.T @ np.array([0.0, 0.0, 1.0]))


# -- hand-computed cases ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("heading", "body_xy"),
    [
        (0.0, (BN, 0.0)),  # nose north: the whole horizontal field on +x
        (45.0, (BN * math.sqrt(0.5), -BN * math.sqrt(0.5))),
        (90.0, (0.0, -BN)),  # nose east: north is to the left (-y)
        (135.0, (-BN * math.sqrt(0.5), -BN * math.sqrt(0.5))),
        (180.0, (-BN, 0.0)),
        (225.0, (-BN * math.sqrt(0.5), BN * math.sqrt(0.5))),
        (270.0, (0.0, BN)),  # nose west: north is to the right
        (315.0, (BN * math.sqrt(0.5), BN * math.sqrt(0.5))),
    ],
)
def test_level_heading_in_every_quadrant(heading: float, body_xy: tuple[float, float]) -> None:
    eng = AttitudeEngine()
    sol = eng.solve_counts(*counts(np.array([*body_xy, BD]), np.array([0.0, 0.0, 1.0])))
    assert float(angle_diff_deg(sol.heading_magnetic_deg, heading)) == pytest.approx(0.0, abs=1e-9)
    assert 0.0 <= sol.heading_magnetic_deg < 360.0
    assert sol.roll == pytest.approx(0.0, abs=1e-12)
    assert sol.pitch == pytest.approx(0.0, abs=1e-12)
    assert sol.heading_reference == "magnetic"
    assert not sol.degraded


def test_nose_up_30_deg_by_hand() -> None:
    # Nose up 30 deg, heading north: gravity (-sin30, 0, cos30); the field turns with the
    # body about y: x = Bn cos30 - Bd sin30, z = Bn sin30 + Bd cos30.
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    sol = AttitudeEngine().solve_counts(
        *counts(np.array([BN * c - BD * s, 0.0, BN * s + BD * c]), np.array([-s, 0.0, c]))
    )
    assert math.degrees(sol.pitch) == pytest.approx(30.0, abs=1e-9)
    assert math.degrees(sol.roll) == pytest.approx(0.0, abs=1e-9)
    assert float(angle_diff_deg(sol.heading_magnetic_deg, 0.0)) == pytest.approx(0.0, abs=1e-9)


def test_right_wing_down_45_deg_heading_east_by_hand() -> None:
    # Roll +45 (right wing down), heading east: gravity (0, sin45, cos45). Level-frame field
    # for heading east is (0, -Bn, Bd); rolling by +45 about x: y' = c*y + s*z, z' = -s*y + c*z.
    c = s = math.sqrt(0.5)
    mag = np.array([0.0, c * -BN + s * BD, -s * -BN + c * BD])
    sol = AttitudeEngine().solve_counts(*counts(mag, np.array([0.0, s, c])))
    assert math.degrees(sol.roll) == pytest.approx(45.0, abs=1e-9)
    assert math.degrees(sol.pitch) == pytest.approx(0.0, abs=1e-9)
    assert sol.heading_magnetic_deg == pytest.approx(90.0, abs=1e-9)


def test_datasheet_formulas_term_by_term() -> None:
    # pitch = -asin(gx/|g|), roll = atan2(gy, gz), heading = atan2(-Y, X) with the
    # datasheet's X, Y -- evaluated here by hand on one arbitrary calibrated frame.
    g = np.array([0.3, -0.2, 0.9])
    H = np.array([0.1, 0.25, 0.4])
    th = -math.asin(g[0] / np.linalg.norm(g))
    ga = math.atan2(g[1], g[2])
    X = (
        H[0] * math.cos(th)
        + H[1] * math.sin(th) * math.sin(ga)
        + H[2] * math.sin(th) * math.cos(ga)
    )
    Y = H[1] * math.cos(ga) - H[2] * math.sin(ga)
    hdg = math.degrees(math.atan2(-Y, X)) % 360.0
    sol = AttitudeEngine().solve_counts(*counts(H, g))
    assert sol.pitch == pytest.approx(th, abs=1e-12)
    assert sol.roll == pytest.approx(ga, abs=1e-12)
    assert sol.heading_magnetic_deg == pytest.approx(hdg, abs=1e-9)
    r, p, h = tilt_compensated_heading(H[np.newaxis], g[np.newaxis])
    assert (r[0], p[0], h[0]) == pytest.approx((ga, th, hdg), abs=1e-9)


# -- tilt sweep, gimbal zone ----------------------------------------------------------------


def test_tilt_sweep_to_80_deg_recovers_euler_angles() -> None:
    eng = AttitudeEngine()
    worst = 0.0
    for roll in (-80.0, -45.0, 0.0, 30.0, 80.0):
        for pitch in (-80.0, -60.0, -10.0, 0.0, 25.0, 80.0):
            for yaw in (0.0, 47.0, 133.0, 181.0, 269.0, 359.0):
                sol = eng.solve_counts(*frame_at(roll, pitch, yaw))
                assert not sol.degraded
                worst = max(
                    worst,
                    abs(math.degrees(sol.roll) - roll),
                    abs(math.degrees(sol.pitch) - pitch),
                    abs(float(angle_diff_deg(sol.heading_magnetic_deg, yaw))),
                )
    assert worst < 1e-6


@pytest.mark.parametrize("pitch", [86.0, 89.9, 90.0, -90.0, -88.0])
def test_gimbal_zone_is_finite_and_flagged(pitch: float) -> None:
    sol = AttitudeEngine().solve_counts(*frame_at(20.0, pitch, 100.0))
    values = [sol.roll, sol.pitch, sol.yaw, sol.heading_magnetic_deg, *sol.quaternion, sol.dip_deg]
    assert all(math.isfinite(v) for v in values)
    assert sol.degraded
    assert math.degrees(sol.pitch) == pytest.approx(pitch, abs=1e-6)
    # whatever roll/yaw split it picked, the attitude it describes is the true one
    R = quaternion_to_dcm(sol.quaternion)
    truth = euler_to_dcm(math.radians(20.0), math.radians(pitch), math.radians(100.0))
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ truth) - 1) / 2, -1, 1))) < 0.01


def test_no_gravity_is_level_and_degraded_not_nan() -> None:
    c = counts(np.array([BN, 0.0, BD]), np.zeros(3))
    sol = AttitudeEngine().solve_counts(*c)
    assert sol.degraded
    assert sol.roll == 0.0 and sol.pitch == 0.0
    assert math.isfinite(sol.heading_magnetic_deg)


def test_non_finite_counts_are_refused() -> None:
    eng = AttitudeEngine()
    with pytest.raises(ValueError):
        eng.solve_counts(math.nan, 2458, 2458, 2458, 2458, 2949.5)


# -- quaternion -----------------------------------------------------------------------------


def test_quaternion_matches_euler_and_rotates_field_to_magnetic_north() -> None:
    eng = AttitudeEngine()
    rng = np.random.default_rng(5)
    for R in random_rotations(rng, 200):
        sol = eng.solve_counts(*counts(R.T @ B_NED, R.T @ np.array([0.0, 0.0, 1.0])))
        w, x, y, z = sol.quaternion
        assert w >= 0.0
        assert w * w + x * x + y * y + z * z == pytest.approx(1.0, abs=1e-12)
        Rq = quaternion_to_dcm(sol.quaternion)
        np.testing.assert_allclose(Rq, euler_to_dcm(sol.roll, sol.pitch, sol.yaw), atol=1e-9)
        np.testing.assert_allclose(Rq, R, atol=1e-6)
        # body -> NED with the quaternion puts the calibrated field back on magnetic north
        np.testing.assert_allclose(Rq @ np.array(sol.mag_G), B_NED, atol=1e-7)


def test_quaternion_is_made_on_first_use_from_the_solutions_own_angles() -> None:
    """Made when asked for (most frames' solutions never are), bit for bit the one
    conversion of the package, once per solution; a copy with other angles has its own."""
    eng = AttitudeEngine()
    rng = np.random.default_rng(7)
    for R in random_rotations(rng, 50):
        sol = eng.solve_counts(*counts(R.T @ B_NED, R.T @ np.array([0.0, 0.0, 1.0])))
        q = sol.quaternion
        assert q == euler_to_quaternion(sol.roll, sol.pitch, sol.yaw)  # exact, not approx
        assert sol.quaternion is q
        assert "quaternion" not in repr(sol)
        turned = dataclasses.replace(sol, yaw=sol.yaw / 2.0)
        assert turned.quaternion == euler_to_quaternion(sol.roll, sol.pitch, sol.yaw / 2.0)
        assert turned == dataclasses.replace(sol, yaw=sol.yaw / 2.0)


# -- declination and labelling ---------------------------------------------------------------


def test_true_heading_adds_declination_and_is_labelled() -> None:
    ref = FieldReference(declination_deg=10.0, total_G=float(np.linalg.norm(B_NED)), dip_deg=66.0)
    eng = AttitudeEngine(reference=ref, heading_reference="true")
    sol = eng.solve_counts(*frame_at(0.0, 0.0, 355.0))
    assert sol.heading_magnetic_deg == pytest.approx(355.0, abs=1e-9)
    assert sol.heading_true_deg == pytest.approx(5.0, abs=1e-9)  # folded through north
    assert sol.declination_deg == 10.0
    assert sol.heading_reference == "true"
    assert sol.heading_deg == pytest.approx(5.0, abs=1e-9)
    assert math.degrees(sol.yaw) == pytest.approx(5.0, abs=1e-9)

    eng.set_heading_reference("magnetic")
    sol = eng.solve_counts(*frame_at(0.0, 0.0, 355.0))
    assert sol.heading_reference == "magnetic"
    assert math.degrees(sol.yaw) == pytest.approx(-5.0, abs=1e-9)  # (-180, 180]
    assert sol.heading_true_deg == pytest.approx(5.0, abs=1e-9)  # still reported


def test_true_requested_without_declination_publishes_magnetic_labelled_so() -> None:
    eng = AttitudeEngine(heading_reference="true")
    sol = eng.solve_counts(*frame_at(0.0, 0.0, 120.0))
    assert sol.heading_reference == "magnetic"
    assert sol.heading_true_deg is None and sol.declination_deg is None
    assert sol.heading_deg == pytest.approx(120.0, abs=1e-9)


def test_update_position_takes_the_wmm_declination() -> None:
    eng = AttitudeEngine(heading_reference="true")
    ref = eng.update_position(47.397742, 8.545594, 488.0, when=2026.0)
    wmm = earth_field(47.397742, 8.545594, 488.0, when=2026.0)
    assert ref.source == "wmm"
    assert ref.declination_deg == pytest.approx(wmm.declination_deg)
    assert ref.dip_deg == pytest.approx(wmm.inclination_deg)
    sol = eng.solve_counts(*frame_at(0.0, 0.0, 90.0, B=wmm.ned_G))
    # the frame was built from the true field vector, so the body sees true-north geometry
    # rotated by the declination: magnetic heading = 90 - declination
    assert sol.heading_reference == "true"
    assert sol.heading_true_deg == pytest.approx(90.0, abs=1e-6)
    assert sol.heading_magnetic_deg == pytest.approx(90.0 - wmm.declination_deg, abs=1e-6)
    # a bad position is refused and the old reference kept
    with pytest.raises(ValueError):
        eng.update_position(95.0, 0.0)
    assert eng.reference == ref


def test_bad_heading_reference_is_refused() -> None:
    with pytest.raises(ValueError):
        AttitudeEngine(heading_reference="grid")  # type: ignore[arg-type]  # not a reference: refused at run time


# -- calibration and mounting in the chain ----------------------------------------------------


def test_calibration_is_applied_before_the_formulas() -> None:
    rng = np.random.default_rng(11)
    unit = UnitErrors.draw(rng, mag_noise_G=0.0, acc_noise_g=0.0)
    model = SensorModel(unit, B_NED)
    Rs = random_rotations(rng, 50)
    # keep away from the gimbal zone, where heading is ill-conditioned anyway
    Rs = Rs[np.abs(Rs[:, 2, 0]) < math.sin(math.radians(70))]
    s = model.sample(Rs, rng)
    assert not s.saturated.any()
    raw = AttitudeEngine()
    cal = AttitudeEngine(unit.true_calibration())
    err_raw: list[float] = []
    err_cal: list[float] = []
    for R, mc, ac in zip(Rs, s.mag_counts, s.acc_counts, strict=True):
        truth = math.degrees(math.atan2(R[1, 0], R[0, 0])) % 360.0
        for eng, errs in ((raw, err_raw), (cal, err_cal)):
            sol = eng.solve_counts(*(float(v) for v in (*mc, *ac)))
            errs.append(abs(float(angle_diff_deg(sol.heading_magnetic_deg, truth))))
    assert max(err_cal) < 0.5  # quantisation only
    assert max(err_raw) > 5.0  # the unit's errors matter, so the calibration did the work

    # update_calibration switches the chain
    raw.update_calibration(unit.true_calibration())
    sol = raw.solve_counts(*(float(v) for v in (*s.mag_counts[0], *s.acc_counts[0])))
    truth0 = math.degrees(math.atan2(Rs[0][1, 0], Rs[0][0, 0])) % 360.0
    assert abs(float(angle_diff_deg(sol.heading_magnetic_deg, truth0))) < 0.5


@pytest.mark.parametrize(
    "rot", [Rotation.ROTATION_ROLL_180, Rotation.ROTATION_YAW_90, Rotation.ROTATION_PITCH_270]
)
def test_mounted_unit_reports_the_vehicle_attitude(rot: Rotation) -> None:
    M = rotation_matrix(rot)  # v_vehicle = M @ v_sensor
    eng = AttitudeEngine(mounting=Mounting(rot))
    plain = AttitudeEngine()
    for roll, pitch, yaw in ((10.0, -20.0, 30.0), (-35.0, 15.0, 250.0), (0.0, 0.0, 0.0)):
        Rv = euler_to_dcm(math.radians(roll), math.radians(pitch), math.radians(yaw))
        mag_sensor = M.T @ Rv.T @ B_NED  # what the rotated unit measures
        acc_sensor = M.T @ Rv.T @ np.array([0.0, 0.0, 1.0])
        sol = eng.solve_counts(*counts(mag_sensor, acc_sensor))
        assert math.degrees(sol.roll) == pytest.approx(roll, abs=1e-6)
        assert math.degrees(sol.pitch) == pytest.approx(pitch, abs=1e-6)
        assert float(angle_diff_deg(sol.heading_magnetic_deg, yaw)) == pytest.approx(0.0, abs=1e-6)
        np.testing.assert_allclose(sol.accel_g, Rv.T @ np.array([0.0, 0.0, 1.0]), atol=1e-9)
    # without the mounting the same readings give a different attitude
    wrong = plain.solve_counts(*counts(M.T @ B_NED, M.T @ np.array([0.0, 0.0, 1.0])))
    assert (
        abs(math.degrees(wrong.roll))
        + abs(math.degrees(wrong.pitch))
        + abs(float(angle_diff_deg(wrong.heading_magnetic_deg, 0.0)))
        > 45.0
    )


def test_mounting_and_calibration_compose() -> None:
    # mag needs a 0.05 G offset removed and accel a 2 % gain; mounted upside down
    cal = Calibration(
        mag=AffineCalibration((0.05, -0.02, 0.01)),
        accel=AffineCalibration(matrix=((1 / 1.02, 0, 0), (0, 1 / 1.02, 0), (0, 0, 1 / 1.02))),
    )
    eng = AttitudeEngine(cal, Mounting(Rotation.ROTATION_ROLL_180))
    M = rotation_matrix(Rotation.ROTATION_ROLL_180)
    Rv = euler_to_dcm(math.radians(5), math.radians(10), math.radians(200))
    mag_sensor = M.T @ Rv.T @ B_NED + np.array([0.05, -0.02, 0.01])
    acc_sensor = 1.02 * (M.T @ Rv.T @ np.array([0.0, 0.0, 1.0]))
    sol = eng.solve_counts(*counts(mag_sensor, acc_sensor))
    assert sol.heading_magnetic_deg == pytest.approx(200.0, abs=1e-6)
    assert math.degrees(sol.roll) == pytest.approx(5.0, abs=1e-6)


# -- vectorised forms -------------------------------------------------------------------------


def test_vectorised_heading_matches_the_fast_path() -> None:
    rng = np.random.default_rng(3)
    Rs = random_rotations(rng, 100)
    mag = np.einsum("nji,j->ni", Rs, B_NED)
    acc = Rs[:, 2, :]  # R.T @ (0, 0, 1) = third row of R
    roll, pitch, hdg = tilt_compensated_heading(mag, acc)
    eng = AttitudeEngine()
    for i in range(len(Rs)):
        sol = eng.solve_counts(*counts(mag[i], acc[i]))
        assert roll[i] == pytest.approx(sol.roll, abs=1e-9)
        assert pitch[i] == pytest.approx(sol.pitch, abs=1e-9)
        assert float(angle_diff_deg(hdg[i], sol.heading_magnetic_deg)) == pytest.approx(
            0.0, abs=1e-6
        )
    R_back = attitude_matrix_from_vectors(mag, acc)
    np.testing.assert_allclose(R_back, Rs, atol=1e-9)
    with pytest.raises(ValueError):
        tilt_compensated_heading(mag, acc[:5])
    with pytest.raises(ValueError):
        attitude_matrix_from_vectors(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 1.0]))


@given(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.one_of(st.none(), st.floats(-180.0, 180.0), st.sampled_from([-180.0, 180.0, 180.000005])),
)
def test_heading_folds_match_the_one_fold(x: float, decl: float | None) -> None:
    """The per-frame path folds headings with geometry.wrap_degrees_360 (the rule:
    [0, 360), and never 360.0) for the atan2 heading and for heading + declination."""
    from bridge.core.attitude import _DEG
    from bridge.core.geometry import wrap_degrees_360 as _fold_360

    eng = AttitudeEngine(
        Calibration(), reference=FieldReference(declination_deg=decl), heading_reference="true"
    )
    # A level unit whose field points at atan2 angle x: heading = fold(-x) in degrees.
    ang = math.radians(x)
    s = eng._state
    a = eng._finish(s, math.cos(ang), math.sin(ang), 0.4, 0.0, 0.0, 1.0)
    assert 0.0 <= a.heading_magnetic_deg < 360.0
    assert a.heading_magnetic_deg == _fold_360(math.atan2(-math.sin(ang), math.cos(ang)) * _DEG)
    if decl is None:
        assert a.heading_true_deg is None
    else:
        assert a.heading_true_deg == _fold_360(a.heading_magnetic_deg + decl)
