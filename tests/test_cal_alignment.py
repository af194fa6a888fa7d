"""Mag-to-accel alignment: a known rotation from the constant gravity/field angle, and the best fit.

Synthetic data follow docs/architecture.md: at attitude R the accelerometer reads
``R.T @ (0, 0, 1)`` g and the magnetometer ``A @ (R.T @ B_ned) + h`` gauss.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.alignment import fit_alignment, fit_ellipsoid_aligned, linear_alignment
from bridge.calibration.fits.ellipsoid import fit_ellipsoid
from bridge.calibration.fits.sanity import MagCalStatus
from bridge.core.calibration import AffineCalibration
from bridge.core.geometry import axis_angle_to_dcm, euler_to_dcm_batch, random_rotations

B_NED = np.array([0.2152, 0.0138, 0.4333])
DIP_DEG = math.degrees(math.atan2(B_NED[2], math.hypot(B_NED[0], B_NED[1])))
TRUE_ROT = axis_angle_to_dcm([0.4, -0.7, 0.6], math.radians(2.0))  # mag axes -> accel axes


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (float(np.trace(Ra.T @ Rb)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _frames(
    R: np.ndarray, rng: np.random.Generator, mag_noise: float = 5e-4, acc_noise: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    body_b = np.einsum("nji,j->ni", R, B_NED)
    body_g = R[:, 2, :]  # R.T @ (0, 0, 1)
    mag = body_b @ TRUE_ROT + rng.normal(0.0, mag_noise, size=body_b.shape)  # TRUE_ROT.T @ b
    acc = body_g + rng.normal(0.0, acc_noise, size=body_g.shape)
    return mag, acc


def test_recovers_a_known_two_degree_rotation() -> None:
    rng = np.random.default_rng(11)
    mag, acc = _frames(random_rotations(rng, 1000), rng)
    al = fit_alignment(mag, acc)
    assert al.observable
    assert _angle_deg(al.rotation, TRUE_ROT) < 0.1
    assert abs(al.angle_deg - 2.0) < 0.1
    assert abs(al.dip_deg - DIP_DEG) < 0.05
    assert math.isclose(al.dot_mean, B_NED[2], rel_tol=2e-3)  # vertical field component
    # misaligned, the angle between g and B wobbles with attitude; aligned, only noise
    assert al.dot_spread_before > 4.0 * al.dot_spread_after
    assert al.n_samples == 1000 and al.n_rejected == 0 and al.iterations >= 1


def test_linear_solution_alone_is_already_close() -> None:
    rng = np.random.default_rng(12)
    mag, acc = _frames(random_rotations(rng, 500), rng)
    mu = mag / np.linalg.norm(mag, axis=1, keepdims=True)
    au = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    R, s = linear_alignment(au, mu)
    assert _angle_deg(R, TRUE_ROT) < 0.3
    assert abs(math.degrees(math.asin(s)) - DIP_DEG) < 0.3


def test_accelerating_and_disturbed_samples_are_dropped() -> None:
    rng = np.random.default_rng(13)
    mag, acc = _frames(random_rotations(rng, 800), rng)
    acc[:60] *= 1.3  # the unit was being swung: |g| = 1.3
    for i in range(60, 70):  # a nearby magnet: the field tilted 8 deg towards gravity
        mag[i] = axis_angle_to_dcm(np.cross(mag[i], acc[i]), math.radians(8.0)) @ mag[i]
    al = fit_alignment(mag, acc)
    assert not al.inliers[:70].any()
    assert al.n_rejected == 70
    assert _angle_deg(al.rotation, TRUE_ROT) < 0.1


def test_level_turns_cannot_show_the_rotation() -> None:
    rng = np.random.default_rng(14)
    yaw = rng.uniform(0, 2 * math.pi, 400)
    R = euler_to_dcm_batch(np.zeros(400), np.zeros(400), yaw)
    mag, acc = _frames(R, rng)
    al = fit_alignment(mag, acc)
    assert not al.observable
    assert np.array_equal(al.rotation, np.eye(3))


def test_bad_input_is_refused_clearly() -> None:
    with pytest.raises(ValueError, match="at least 20"):
        fit_alignment(np.ones((10, 3)), np.ones((10, 3)) / math.sqrt(3))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_alignment(np.ones((30, 3)), np.ones((31, 3)))


def _unit_matrix() -> np.ndarray:
    gains = np.diag([1.07, 0.94, 1.03])
    nonorth = np.array([[1.0, 0.0, 0.0], [0.05, 1.0, 0.0], [-0.04, 0.03, 1.0]])
    return gains @ nonorth @ TRUE_ROT.T


def test_aligned_fit_recovers_the_full_matrix_the_symmetric_one_cannot() -> None:
    rng = np.random.default_rng(15)
    R = random_rotations(rng, 1000)
    body_b = np.einsum("nji,j->ni", R, B_NED)
    hard = np.array([-0.08, 0.05, 0.11])
    A = _unit_matrix()
    mag = body_b @ A.T + hard + rng.normal(0.0, 5e-4, size=body_b.shape)
    acc_offset = np.array([0.02, -0.015, 0.01])
    acc = R[:, 2, :] * 1.02 + acc_offset + rng.normal(0.0, 1e-3, size=body_b.shape)
    acc_cal = AffineCalibration.from_arrays(acc_offset, np.eye(3) / 1.02)

    best = fit_ellipsoid_aligned(mag, acc, acc_cal, B_NED)
    sym = fit_ellipsoid(mag, reference_field_G=B_NED)
    truth = np.linalg.inv(A)
    err_best = np.abs(best.calibration.mag.matrix_array - truth).max()
    err_sym = np.abs(sym.calibration.mag.matrix_array - truth).max()
    assert err_best < 1.5e-3 and err_sym > 10.0 * err_best
    assert best.report.ok and best.report.method == "ellipsoid_aligned"
    assert best.calibration.accel == acc_cal
    view = best.calibration.mag.ardupilot_view()
    assert 1.0 < math.degrees(float(np.linalg.norm(view.rotation_rotvec))) < 6.0
    assert best.report.gravity_spread_after_mg < 10.0 < best.report.gravity_spread_before_mg
    # The corrected field, compared with the truth: the symmetric fit leaves degrees.
    got = best.calibration.mag.apply(mag)
    ang = np.degrees(
        np.arccos(
            np.clip(
                np.sum(got * body_b, 1)
                / np.linalg.norm(got, axis=1)
                / np.linalg.norm(body_b, axis=1),
                -1,
                1,
            )
        )
    )
    assert np.sqrt(np.mean(ang**2)) < 0.15


def test_a_wrong_orientation_is_reported() -> None:
    rng = np.random.default_rng(16)
    R = random_rotations(rng, 600)
    body_b = np.einsum("nji,j->ni", R, B_NED)
    turned = axis_angle_to_dcm([0, 0, 1], math.radians(45.0))  # compass mounted yawed 45 deg
    mag = body_b @ turned + rng.normal(0.0, 5e-4, size=body_b.shape)
    res = fit_ellipsoid_aligned(mag, R[:, 2, :], None, B_NED)
    assert res.report.status == MagCalStatus.MAG_CAL_FAILED_ORIENTATION.name
    assert any("no accelerometer calibration" in n for n in res.report.notes)
