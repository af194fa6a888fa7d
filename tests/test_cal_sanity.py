"""Sanity bounds: each MAG_CAL_STATUS failure code from a crafted calibration."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge.calibration.fits.sanity import (
    MagCalStatus,
    SanityLimits,
    check_accel_calibration,
    check_mag_calibration,
)
from bridge.core.calibration import AffineCalibration
from bridge.core.geometry import axis_angle_to_dcm

GOOD_OFFSET = (0.05, -0.12, 0.08)  # gauss: 50, -120, 80 mG of hard iron


def _check(
    offset: tuple[float, float, float] = GOOD_OFFSET,
    matrix: np.ndarray | None = None,
    *,
    radius_G: float = 0.48,
    fitness_mG: float = 1.2,
    scale_factor: float | None = 1.02,
    check_rotation: bool = False,
) -> tuple[MagCalStatus, tuple[str, ...]]:
    m = np.diag([1.05, 0.97, 1.01]) if matrix is None else matrix
    res = check_mag_calibration(
        AffineCalibration.from_arrays(offset, m),
        radius_G=radius_G,
        fitness_mG=fitness_mG,
        scale_factor=scale_factor,
        check_rotation=check_rotation,
    )
    assert res.ok == (res.status is MagCalStatus.MAG_CAL_SUCCESS)
    return res.status, res.reasons


def test_status_values_match_pymavlink() -> None:
    for st in MagCalStatus:
        assert getattr(mavlink, st.name) == st.value
    assert MagCalStatus.parse("MAG_CAL_BAD_RADIUS") is MagCalStatus.MAG_CAL_FAILED_RADIUS
    assert MagCalStatus.parse("MAG_CAL_BAD_ORIENTATION") is MagCalStatus.MAG_CAL_FAILED_ORIENTATION
    assert MagCalStatus.parse(8) is MagCalStatus.MAG_CAL_FAILED_OFFSETS
    with pytest.raises(ValueError):
        MagCalStatus.parse("MAG_CAL_WHATEVER")
    # Ground stations older than codes 8-10 get MAG_CAL_FAILED, as ArduPilot sends.
    assert MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH.legacy is MagCalStatus.MAG_CAL_FAILED
    assert MagCalStatus.MAG_CAL_FAILED_RADIUS.legacy is MagCalStatus.MAG_CAL_FAILED_RADIUS
    assert MagCalStatus.MAG_CAL_FAILED_ORIENTATION.failed
    assert not MagCalStatus.MAG_CAL_SUCCESS.failed


def test_a_good_calibration_passes() -> None:
    assert _check() == (MagCalStatus.MAG_CAL_SUCCESS, ())


@pytest.mark.parametrize("radius_G", [0.14, 0.96])
def test_radius_outside_150_950_milligauss(radius_G: float) -> None:
    status, reasons = _check(radius_G=radius_G)
    assert status is MagCalStatus.MAG_CAL_FAILED_RADIUS and "field radius" in reasons[0]


@pytest.mark.parametrize("scale", [1.6, 0.6])
def test_wmm_scale_factor_beyond_1_5(scale: float) -> None:
    status, reasons = _check(scale_factor=scale)
    assert status is MagCalStatus.MAG_CAL_FAILED_RADIUS and "scale factor" in reasons[0]
    # Without a reference field there is no scale factor to check.
    assert _check(scale_factor=None)[0] is MagCalStatus.MAG_CAL_SUCCESS


def test_offsets_beyond_compass_offs_max() -> None:
    status, reasons = _check(offset=(0.05, -1.9, 0.0))  # COMPASS_OFS_Y = +1900 mG
    assert status is MagCalStatus.MAG_CAL_FAILED_OFFSETS
    assert reasons == ("COMPASS_OFS_Y 1900 mG beyond COMPASS_OFFS_MAX 1800",)
    strict = check_mag_calibration(
        AffineCalibration.from_arrays((0.7, 0.0, 0.0), np.eye(3)),
        radius_G=0.5,
        fitness_mG=1.0,
        limits=SanityLimits(offset_max_mG=600.0),  # an older vehicle default
    )
    assert strict.status is MagCalStatus.MAG_CAL_FAILED_OFFSETS


def test_diagonal_out_of_range() -> None:
    # DIA normalised to a mean of 1: (1, 1, 20) -> (0.14, 0.14, 2.7)
    status, reasons = _check(matrix=np.diag([1.0, 1.0, 20.0]))
    assert status is MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING
    assert any("COMPASS_DIA_X" in r for r in reasons)


def test_off_diagonal_beyond_one() -> None:
    m = np.array([[1.0, 0.9, 0.0], [0.9, 1.0, 0.0], [0.0, 0.0, 0.3]])  # positive definite
    status, reasons = _check(matrix=m)
    assert status is MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING
    assert any(r.startswith("COMPASS_ODI_X") for r in reasons)


def test_fitness_above_compass_cal_fit() -> None:
    status, reasons = _check(fitness_mG=16.5)
    assert status is MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH and "16.50 mG" in reasons[0]
    assert _check(fitness_mG=16.0)[0] is MagCalStatus.MAG_CAL_SUCCESS


def test_large_mag_to_accel_rotation_is_bad_orientation() -> None:
    rot = axis_angle_to_dcm([0.0, 0.0, 1.0], math.radians(45.0))  # a wrong COMPASS_ORIENT
    m = rot @ np.diag([1.02, 0.99, 1.0])
    assert _check(matrix=m)[0] is MagCalStatus.MAG_CAL_SUCCESS  # rotation not checked
    status, reasons = _check(matrix=m, check_rotation=True)
    assert status is MagCalStatus.MAG_CAL_FAILED_ORIENTATION and "45.0 deg" in reasons[0]
    small = axis_angle_to_dcm([1.0, 1.0, 0.0], math.radians(3.0)) @ np.eye(3)
    assert _check(matrix=small, check_rotation=True)[0] is MagCalStatus.MAG_CAL_SUCCESS


def test_non_finite_fit_is_plain_failure() -> None:
    assert _check(fitness_mG=math.nan)[0] is MagCalStatus.MAG_CAL_FAILED
    bad = AffineCalibration((math.nan, 0.0, 0.0))  # bypasses from_arrays' validation
    res = check_mag_calibration(bad, radius_G=0.5, fitness_mG=1.0)
    assert res.status is MagCalStatus.MAG_CAL_FAILED and res.reasons == (
        "calibration is not finite",
    )


def test_poorly_determined_parameters_fail() -> None:
    m = AffineCalibration.from_arrays(GOOD_OFFSET, np.eye(3))
    res = check_mag_calibration(m, radius_G=0.48, fitness_mG=0.5, offset_sd_mG=2.5)
    assert res.status is MagCalStatus.MAG_CAL_FAILED and "+-2.5 mG" in res.reasons[0]
    res = check_mag_calibration(m, radius_G=0.48, fitness_mG=0.5, matrix_sd=0.01)
    assert res.status is MagCalStatus.MAG_CAL_FAILED and "matrix undetermined" in res.reasons[0]
    ok = check_mag_calibration(m, radius_G=0.48, fitness_mG=0.5, offset_sd_mG=0.05, matrix_sd=1e-4)
    assert ok.ok


def test_several_failures_are_all_reported_first_one_wins() -> None:
    status, reasons = _check(offset=(2.0, 0.0, 0.0), radius_G=1.2, fitness_mG=40.0)
    assert status is MagCalStatus.MAG_CAL_FAILED_RADIUS
    assert len(reasons) == 3


def test_accelerometer_bounds() -> None:
    good = AffineCalibration.from_arrays((0.02, -0.01, 0.03), np.diag([1.03, 0.98, 1.0]))
    assert check_accel_calibration(good).ok
    bad = AffineCalibration.from_arrays((1.2, 0.0, 0.0), np.diag([1.3, 1.0, 1.0]))
    res = check_accel_calibration(bad)
    assert res.status is MagCalStatus.MAG_CAL_FAILED and len(res.reasons) == 2
