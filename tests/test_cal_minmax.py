"""Method 1, min/max: the device's MAGCAL arithmetic on simulated turns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.minmax import fit_minmax
from bridge.core import sensor
from bridge.core.geometry import euler_to_dcm_batch
from bridge.sim.physics import SensorModel, UnitErrors

B_NED = np.array([0.21, 0.01, 0.43])
HARD = np.array([0.08, -0.05, 0.03])
GAINS = np.array([1.06, 0.93, 1.02])


def _unit(noise: float = 0.0005) -> UnitErrors:
    # diagonal errors only: what min/max can model
    return UnitErrors(
        hard_iron_G=HARD, soft_iron=np.diag(GAINS), mag_noise_G=noise, acc_noise_g=0.001
    )


def _device_procedure(n_per_turn: int = 360, extra_tilted: int = 0) -> np.ndarray:
    """One level turn, then on its right side one turn (the datasheet's MAGCAL motion)."""
    yaw = np.linspace(0.0, 2 * math.pi, n_per_turn, endpoint=False)
    level = euler_to_dcm_batch(np.zeros_like(yaw), np.zeros_like(yaw), yaw)
    side = euler_to_dcm_batch(np.full_like(yaw, math.pi / 2), np.zeros_like(yaw), yaw)
    parts = [level, side]
    if extra_tilted:
        y = np.linspace(0.0, 2 * math.pi, extra_tilted, endpoint=False)
        parts.append(euler_to_dcm_batch(np.full_like(y, 0.8), np.full_like(y, -0.7), y))
    return np.concatenate(parts)


def _sample(R: np.ndarray, seed: int = 1, noise: float = 0.0005) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    s = SensorModel(_unit(noise), B_NED).sample(R, rng)
    assert not s.saturated.any()
    return sensor.mag_counts_to_gauss(s.mag_counts), sensor.acc_counts_to_g(s.acc_counts)


def _check_recovered(
    res_cal_offset: np.ndarray, diag: np.ndarray, tol_off: float, tol_gain: float
) -> None:
    np.testing.assert_allclose(res_cal_offset, HARD, atol=tol_off)
    # K normalised to x: Ky = span_x / span_y = gain_x / gain_y
    np.testing.assert_allclose(diag, [1.0, GAINS[0] / GAINS[1], GAINS[0] / GAINS[2]], rtol=tol_gain)


def test_device_procedure_recovers_offsets_and_gain_ratios() -> None:
    mag, acc = _sample(_device_procedure())
    res = fit_minmax(mag, acc_g=acc)
    assert res.report.ok, res.report.notes
    cal = res.calibration.mag
    m = cal.matrix_array
    assert np.count_nonzero(m - np.diag(np.diag(m))) == 0  # diagonal, as the device's K
    _check_recovered(cal.offset_array, np.diag(m), tol_off=0.002, tol_gain=0.015)
    assert res.calibration.accel.matrix_array.tolist() == np.eye(3).tolist()
    r = res.report
    assert r.method == "minmax" and r.n_samples == 720
    assert r.field_spread_after_nT < r.field_spread_before_nT
    # x-normalised gains keep the x axis' own sensitivity: radius = gain_x * |B|
    assert r.radius_G == pytest.approx(GAINS[0] * float(np.linalg.norm(B_NED)), rel=0.01)
    # the device-equivalent parameters: Xoff = 2458 + 2560 * offset
    xoff = 2458.0 + 2560.0 * cal.offset[0]
    assert f"{xoff:.1f}" in r.notes[0]


def test_accelerometer_gating_ignores_tilted_samples() -> None:
    mag, acc = _sample(_device_procedure(extra_tilted=200))
    gated = fit_minmax(mag, acc_g=acc)
    _check_recovered(
        gated.calibration.mag.offset_array,
        np.diag(gated.calibration.mag.matrix_array),
        0.002,
        0.015,
    )
    assert gated.report.n_rejected == 200
    # without gating the tilted samples stretch the x/y extremes and bias the result
    ungated = fit_minmax(mag)
    off_err = np.abs(ungated.calibration.mag.offset_array - HARD).max()
    gain_err = np.abs(
        np.diag(ungated.calibration.mag.matrix_array)[1:]
        - [GAINS[0] / GAINS[1], GAINS[0] / GAINS[2]]
    )
    assert off_err > 0.005 or gain_err.max() > 0.05


def test_a_tumble_without_gating_also_works() -> None:
    rng = np.random.default_rng(3)
    from bridge.core.geometry import random_rotations

    mag, _ = _sample(random_rotations(rng, 4000))
    res = fit_minmax(mag)
    assert res.report.ok
    # a tumble reaches |B| on every axis, so the ratios are right and offsets close
    _check_recovered(
        res.calibration.mag.offset_array, np.diag(res.calibration.mag.matrix_array), 0.004, 0.02
    )


def test_range_failure_like_the_device() -> None:
    # level turn only: no samples on the side -> the z axis is never tracked
    R = _device_procedure()[:360]
    mag, acc = _sample(R)
    res = fit_minmax(mag, acc_g=acc)
    assert res.report.status == "MAG_CAL_FAILED"
    assert "RANGE" in res.report.notes[0]
    assert res.calibration.mag.matrix_array.tolist() == np.eye(3).tolist()
    # a +-10 deg wiggle spans far under 400 counts
    yaw = np.radians(np.linspace(-10, 10, 50))
    mag, _ = _sample(euler_to_dcm_batch(yaw * 0, yaw * 0, yaw))
    res = fit_minmax(mag)
    assert not res.report.ok and "400 counts" in res.report.notes[0]
    assert all(math.isfinite(v) for v in res.calibration.mag.offset)


def test_bad_input() -> None:
    assert fit_minmax(np.zeros((1, 3))).report.status == "MAG_CAL_FAILED"
    with pytest.raises(ValueError):
        fit_minmax(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        fit_minmax(np.zeros((10, 3)), acc_g=np.zeros((9, 3)))
    mag, acc = _sample(_device_procedure())
    mag[5] = np.nan
    acc[7] = np.inf
    res = fit_minmax(mag, acc_g=acc)
    assert res.report.ok and res.report.n_rejected == 2
