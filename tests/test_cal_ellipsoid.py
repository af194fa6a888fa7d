"""Ellipsoid fit: recovers hard iron and the symmetric soft-iron matrix from synthetic data.

Data follow docs/architecture.md: a unit at attitude R reads ``A @ (R.T @ B_ned) + h``
(nominal gauss) plus noise; the true calibration is ``offset = h``, ``matrix = inv(A)``.
An ellipsoid fit can only find the symmetric factor ``S`` of ``inv(A) = Q S`` (polar form).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.ellipsoid import (
    fit_ellipsoid,
    fit_ellipsoid_geometry,
    fit_quadric,
    fit_sphere,
    reference_total_G,
)
from bridge.calibration.fits.sanity import MagCalStatus
from bridge.core.geometry import axis_angle_to_dcm, random_rotations
from bridge.core.wmm import EarthField

B_NED = np.array([0.2152, 0.0138, 0.4333])  # Zurich, gauss
B_TOTAL = float(np.linalg.norm(B_NED))
HARD = np.array([0.061, -0.094, 0.118])
NOISE_G = 5e-4


def _unit_matrix() -> np.ndarray:
    gains = np.diag([1.08, 0.93, 1.04])
    nonorth = np.array([[1.0, 0.0, 0.0], [0.04, 1.0, 0.0], [-0.03, 0.05, 1.0]])
    rot = axis_angle_to_dcm([0.3, -0.5, 0.8], math.radians(2.0))
    return gains @ nonorth @ rot


def _symmetric_factor(m: np.ndarray) -> np.ndarray:
    _, s, Vt = np.linalg.svd(m)
    return np.asarray(Vt.T @ np.diag(s) @ Vt)


def _tumble(n: int, seed: int, noise: float = NOISE_G) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = random_rotations(rng, n)
    body = np.einsum("nji,j->ni", R, B_NED)
    return body @ _unit_matrix().T + HARD + rng.normal(0.0, noise, size=(n, 3))


def test_recovers_offsets_and_symmetric_matrix() -> None:
    x = _tumble(800, 1)
    res = fit_ellipsoid(x, reference_field_G=B_NED)
    rep = res.report
    assert rep.ok and rep.method == "ellipsoid"
    mag = res.calibration.mag
    assert np.abs(mag.offset_array - HARD).max() < 2e-4  # < 0.2 mG
    expected = _symmetric_factor(np.linalg.inv(_unit_matrix()))
    assert np.abs(mag.matrix_array - expected).max() < 1e-3
    assert np.allclose(mag.matrix_array, mag.matrix_array.T)
    # fitness is the RMS radial residual: the noise itself
    assert 0.8 * NOISE_G * 1e3 < rep.fitness_mG < 1.2 * NOISE_G * 1e3
    # radius: field seen at nominal gain (gains ~ geometric mean of the unit's);
    # scale_factor brings it to the WMM total
    assert math.isclose(rep.radius_G * rep.scale_factor, B_TOTAL, rel_tol=1e-9)
    assert 0.95 * B_TOTAL < rep.radius_G < 1.05 * B_TOTAL
    corrected = np.linalg.norm(mag.apply(x), axis=1)
    assert abs(corrected.mean() - B_TOTAL) < 1e-4
    assert rep.field_spread_before_nT > 5000.0 and rep.field_spread_after_nT < 250.0
    assert rep.field_rms_after_nT < 60.0 < rep.field_rms_before_nT
    assert rep.n_samples == 800 and rep.n_rejected == 0 and rep.coverage_pct == 100.0


def test_without_reference_the_radius_is_kept() -> None:
    x = _tumble(400, 2)
    res = fit_ellipsoid(x)
    assert res.report.scale_factor == 1.0
    assert any("no reference field" in n for n in res.report.notes)
    corrected = np.linalg.norm(res.calibration.mag.apply(x), axis=1)
    assert abs(corrected.mean() - res.report.radius_G) < 1e-4


def test_saturated_and_non_finite_samples_are_ignored() -> None:
    x = _tumble(600, 3)
    sat = np.zeros(600, dtype=bool)
    sat[:40] = True
    x[:40] = [0.639, 0.639, -0.96]  # rail readings would drag the fit
    x[40] = [np.nan, 0.0, 0.0]
    res = fit_ellipsoid(x, reference_field_G=B_TOTAL, saturated=sat)
    assert res.report.n_rejected == 41 and res.report.n_samples == 559
    assert np.abs(res.calibration.mag.offset_array - HARD).max() < 3e-4


def test_outliers_are_removed_after_the_first_fit() -> None:
    x = _tumble(600, 4)
    rng = np.random.default_rng(44)
    spikes = rng.choice(600, size=12, replace=False)
    # 30 mG disturbances along the field (a disturbance tangent to the sphere leaves
    # |B| unchanged and no magnitude fit can see it)
    radial = (x[spikes] - HARD) / np.linalg.norm(x[spikes] - HARD, axis=1, keepdims=True)
    x[spikes] += rng.choice([-1.0, 1.0], size=(12, 1)) * 0.03 * radial
    fit = fit_ellipsoid_geometry(x)
    assert fit is not None
    assert fit.n_outliers >= 12 and not fit.inliers[spikes].any()
    assert np.abs(fit.offset - HARD).max() < 3e-4
    no_rejection = fit_ellipsoid_geometry(x, outlier_k=None)
    assert no_rejection is not None and no_rejection.fitness_mG > 3.0 * fit.fitness_mG


def test_fitness_is_ardupilot_rms_residual() -> None:
    x = _tumble(500, 5, noise=2e-3)
    fit = fit_ellipsoid_geometry(x, outlier_k=None)
    assert fit is not None
    r = fit.radius_G - np.linalg.norm((x - fit.offset) @ fit.matrix.T, axis=1)
    assert math.isclose(fit.fitness_mG, 1000.0 * math.sqrt(float(np.mean(r * r))), rel_tol=1e-9)
    assert math.isclose(float(np.linalg.det(fit.matrix)), 1.0, rel_tol=1e-9)


def test_sphere_and_quadric_building_blocks() -> None:
    rng = np.random.default_rng(6)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sph = fit_sphere(HARD + 0.47 * d)
    assert sph is not None
    assert np.allclose(sph[0], HARD, atol=1e-12) and math.isclose(sph[1], 0.47)
    quad = fit_quadric(HARD + 0.47 * d @ np.diag([1.1, 0.9, 1.0]))
    assert quad is not None
    c, Q = quad
    assert np.allclose(c, HARD, atol=1e-9)
    assert np.allclose(Q, np.diag([1 / 1.1**2, 1 / 0.9**2, 1.0]) / 0.47**2, rtol=1e-6)
    # A flat ring (a level turn only) is no ellipsoid
    ring = np.column_stack(
        [np.cos(np.linspace(0, 6, 100)), np.sin(np.linspace(0, 6, 100)), np.zeros(100)]
    )
    assert fit_quadric(ring) is None


def test_data_that_define_no_ellipsoid_fail_cleanly() -> None:
    few = _tumble(8, 7)
    res = fit_ellipsoid(few)
    assert res.report.status == MagCalStatus.MAG_CAL_FAILED.name and not res.report.ok
    assert res.report.n_samples == 8
    with pytest.raises(ValueError):
        fit_ellipsoid(np.zeros((10, 2)))


def test_implausible_result_gets_a_failure_code() -> None:
    # A field a tenth of the Earth's (sensor far too insensitive): radius < 150 mG.
    x = 0.1 * _tumble(400, 8)
    assert fit_ellipsoid(x).report.status == MagCalStatus.MAG_CAL_FAILED_RADIUS.name
    # Same data against the WMM field: a 10x scale factor is refused too.
    res = fit_ellipsoid(x, reference_field_G=B_TOTAL)
    assert res.report.status == MagCalStatus.MAG_CAL_FAILED_RADIUS.name
    assert any("scale factor" in n for n in res.report.notes)


def test_reference_field_forms() -> None:
    ef = EarthField(0.2, 0.01, 0.43, 2.9, 63.0)
    assert math.isclose(reference_total_G(ef) or 0.0, ef.total_G)
    assert reference_total_G(0.48) == 0.48
    assert math.isclose(reference_total_G([0.3, 0.0, 0.4]) or 0.0, 0.5)
    assert reference_total_G(None) is None
    for bad in (-0.5, math.nan, [1.0, 2.0]):
        with pytest.raises(ValueError):
            reference_total_G(bad)


def test_a_small_cap_of_the_sphere_is_refused_not_fitted_to_noise() -> None:
    rng = np.random.default_rng(9)
    R = random_rotations(rng, 6000)
    body = np.einsum("nji,j->ni", R, B_NED)
    cap = body[body[:, 2] > 0.7 * B_TOTAL][:600]  # the unit never turned far from one pose
    x = cap @ _unit_matrix().T + HARD + rng.normal(0.0, NOISE_G, size=cap.shape)
    res = fit_ellipsoid(x, reference_field_G=B_NED)
    assert res.report.status == MagCalStatus.MAG_CAL_FAILED.name
    assert any("undetermined" in n for n in res.report.notes)
    assert res.report.coverage_pct < 40.0
    # the same unit, tumbled: well determined
    full = fit_ellipsoid_geometry(_tumble(600, 10))
    assert full is not None and full.offset_sd_G < 1e-4 and full.matrix_sd < 5e-4
