"""Method 3, scalar calibration: 9 parameters per sensor from |B| and |g| alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.scalar import (
    ScalarParameters,
    field_spread_nT,
    fit_scalar,
    fit_scalar_accel,
    fit_scalar_mag,
    gravity_spread_mg,
)
from bridge.core import sensor
from bridge.core.geometry import euler_to_dcm_batch, random_rotations
from bridge.sim.physics import SensorModel, UnitErrors

B_NED = np.array([0.2156, 0.0077, 0.4333])
B_TOTAL = float(np.linalg.norm(B_NED))

MAG_TRUE = ScalarParameters((0.06, -0.04, 0.025), (1.07, 0.94, 1.03), (1.5, -2.0, 2.5))
ACC_TRUE = ScalarParameters((0.03, -0.02, 0.015), (1.04, 0.97, 1.02), (0.8, -0.6, 1.1))


def _forward(p: ScalarParameters) -> np.ndarray:
    """S @ P, the forward model matrix of a parameter set."""
    return np.linalg.inv(p.to_calibration().matrix_array)


def _unit(
    mag: ScalarParameters = MAG_TRUE, acc: ScalarParameters = ACC_TRUE, noise: float = 0.0005
) -> UnitErrors:
    return UnitErrors(
        hard_iron_G=np.array(mag.offset),
        soft_iron=_forward(mag),
        acc_offset_g=np.array(acc.offset),
        acc_matrix=_forward(acc),
        mag_noise_G=noise,
        acc_noise_g=0.001,
    )


def _tumble(unit: UnitErrors, n: int = 1000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    s = SensorModel(unit, B_NED).sample(random_rotations(rng, n), rng)
    assert not s.saturated.any()
    return sensor.mag_counts_to_gauss(s.mag_counts), sensor.acc_counts_to_g(s.acc_counts)


def test_parameter_round_trip() -> None:
    back = ScalarParameters.from_calibration(MAG_TRUE.to_calibration())
    assert back.offset == pytest.approx(MAG_TRUE.offset)
    assert back.sensitivity == pytest.approx(MAG_TRUE.sensitivity)
    assert back.nonorth_deg == pytest.approx(MAG_TRUE.nonorth_deg)
    with pytest.raises(ValueError):
        ScalarParameters((0, 0, 0), (1, 1, 1), (0, 60, 60)).to_calibration()


def test_magnetometer_offsets_sensitivities_and_angles_recovered() -> None:
    mag, _ = _tumble(_unit())
    res = fit_scalar_mag(mag, B_TOTAL)
    assert res.report.ok, res.report.notes
    got = ScalarParameters.from_calibration(res.calibration.mag)
    np.testing.assert_allclose(got.offset, MAG_TRUE.offset, atol=2e-4)  # 0.2 mG
    np.testing.assert_allclose(got.sensitivity, MAG_TRUE.sensitivity, rtol=2e-3)
    np.testing.assert_allclose(got.nonorth_deg, MAG_TRUE.nonorth_deg, atol=0.15)
    assert res.report.radius_G == B_TOTAL
    assert res.report.fitness_mG < 0.8  # the 0.5 mG noise
    assert res.report.iterations >= 1


def test_accelerometer_recovered_from_gravity_magnitude() -> None:
    _, acc = _tumble(_unit())
    res = fit_scalar_accel(acc)
    assert res.report.ok
    got = ScalarParameters.from_calibration(res.calibration.accel)
    np.testing.assert_allclose(got.offset, ACC_TRUE.offset, atol=1e-3)  # 1 mg
    np.testing.assert_allclose(got.sensitivity, ACC_TRUE.sensitivity, rtol=3e-3)
    np.testing.assert_allclose(got.nonorth_deg, ACC_TRUE.nonorth_deg, atol=0.3)
    assert res.report.gravity_rms_after_mg < 2.0 < res.report.gravity_rms_before_mg
    assert res.calibration.mag.matrix_array.tolist() == np.eye(3).tolist()


def test_both_sensors_and_the_spreads_reported() -> None:
    mag, acc = _tumble(_unit(), seed=7)
    res = fit_scalar(mag, acc, B_TOTAL)
    r = res.report
    assert r.ok
    assert (r.field_spread_before_nT, r.field_rms_before_nT) == pytest.approx(field_spread_nT(mag))
    assert r.field_spread_before_nT > 3000.0
    # after: noise-limited, 0.5 mG = 50 nT per axis
    assert r.field_rms_after_nT < 70.0
    assert r.field_spread_after_nT < 250.0
    assert (r.gravity_spread_before_mg, r.gravity_rms_before_mg) == pytest.approx(
        gravity_spread_mg(acc)
    )
    assert r.gravity_spread_after_mg < 6.0
    assert any(n.startswith("mag offset") for n in r.notes) and any(
        n.startswith("accel offset") for n in r.notes
    )
    # the corrected magnitudes are what the report says
    after = np.linalg.norm(res.calibration.mag.apply(mag), axis=1) * 1e5
    assert float(np.std(after)) == pytest.approx(r.field_rms_after_nT)


def test_seed_paper_figure_700_down_to_100_nanotesla() -> None:
    # A roughly calibrated instrument with small residual errors and quiet (averaged)
    # samples: the situation of the seed paper's +-700 nT -> +-100 nT.
    small = ScalarParameters((0.004, -0.003, 0.002), (1.004, 0.997, 1.002), (0.1, -0.08, 0.12))
    mag, _ = _tumble(_unit(mag=small, noise=0.0001), n=1500, seed=3)
    res = fit_scalar_mag(mag, B_TOTAL)
    r = res.report
    assert r.field_spread_before_nT > 500.0
    assert r.field_spread_after_nT < 100.0
    assert r.field_spread_before_nT / r.field_spread_after_nT > 7.0


def test_without_reference_the_shape_is_still_corrected() -> None:
    mag, _ = _tumble(_unit())
    res = fit_scalar_mag(mag)
    assert res.report.ok
    r = res.report
    assert r.field_rms_after_nT / (r.radius_G * 1e5) < 2e-3  # a sphere, whatever its radius
    # the metric matches the truth up to the unknown scale
    L = res.calibration.mag.matrix_array
    Lt = MAG_TRUE.to_calibration().matrix_array
    k = B_TOTAL / r.radius_G
    np.testing.assert_allclose(
        k * k * L.T @ L, Lt.T @ Lt, rtol=5e-3, atol=2e-3 * float(np.abs(Lt).max()) ** 2
    )


def test_failures_are_reported_not_nan() -> None:
    mag, _ = _tumble(_unit(), n=20)
    res = fit_scalar_mag(mag, B_TOTAL)
    assert res.report.status == "MAG_CAL_FAILED" and "too few" in res.report.notes[0]

    # a level yaw turn only: the z axis never changes, the model is not observable
    yaw = np.linspace(0.0, 2 * math.pi, 400, endpoint=False)
    R = euler_to_dcm_batch(np.zeros_like(yaw), np.zeros_like(yaw), yaw)
    rng = np.random.default_rng(1)
    s = SensorModel(_unit(), B_NED).sample(R, rng)
    res = fit_scalar_mag(sensor.mag_counts_to_gauss(s.mag_counts), B_TOTAL)
    assert res.report.status == "MAG_CAL_FAILED"
    assert np.all(np.isfinite(res.calibration.mag.matrix_array))

    # both: the accelerometer part fails (all still, one orientation) -> named in the notes
    mag, _ = _tumble(_unit())
    still_acc = np.tile([0.0, 0.0, 1.0], (mag.shape[0], 1)) + rng.normal(0, 0.001, mag.shape)
    both = fit_scalar(mag, still_acc, B_TOTAL)
    assert both.report.status == "MAG_CAL_FAILED"
    assert any(n.startswith("accel:") for n in both.report.notes)

    with pytest.raises(ValueError):
        fit_scalar_mag(np.zeros((100, 2)))
    with pytest.raises(ValueError):
        fit_scalar_mag(mag, -0.5)
    mag[3] = np.nan
    assert fit_scalar_mag(mag, B_TOTAL).report.n_rejected == 1
