"""The parameter table and the calibration the COMPASS_* parameters describe (pure)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from helpers import examples
from hypothesis import example, given
from hypothesis import strategies as st

from bridge.app.paramspec import (
    CAL_PARAMS,
    INT8,
    INT32,
    REAL32,
    SPECS,
    ParamTable,
    limits_from_values,
    same_calibration,
)
from bridge.core.calibration import AffineCalibration, Calibration, split_rotation
from bridge.core.geometry import euler_to_dcm, rotvec_to_dcm
from bridge.core.mounting import Rotation, rotation_matrix
from bridge.core.quality import QualityLimits
from bridge.mavlink.paramproto import param_name


def f32(v: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", v))[0])


def test_names_fit_param_id_and_are_unique() -> None:
    names = [s.name for s in SPECS]
    assert len(set(names)) == len(names)
    assert all(len(n) <= 16 and n.isascii() and n.upper() == n for n in names)
    for n in (
        "COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z", "COMPASS_DIA_X", "COMPASS_DIA_Y",
        "COMPASS_DIA_Z", "COMPASS_ODI_X", "COMPASS_ODI_Y", "COMPASS_ODI_Z", "COMPASS_SCALE",
        "COMPASS_DEC", "COMPASS_AUTODEC", "COMPASS_ORIENT", "COMPASS_CAL_FIT", "COMPASS_DEV_ID",
        "COMPASS_USE", "AHRS_ORIENTATION", "BRG_CAL_ONBOARD",
    ):  # fmt: skip
        assert n in names
    assert all(n.startswith(("COMPASS_", "AHRS_", "BRG_")) for n in names)


def test_set_validates_type_value_range_and_read_only() -> None:
    t = ParamTable()
    ok = t.set("COMPASS_OFS_X", 123.25)
    assert ok.accepted and t.get("COMPASS_OFS_X") == 123.25 and ok.index == t.index("COMPASS_OFS_X")
    before = t.values()
    refusals = [
        ("COMPASS_OFS_X", math.nan, REAL32, "not finite"),
        ("COMPASS_OFS_X", math.inf, REAL32, "not finite"),
        ("COMPASS_OFS_X", 1e9, REAL32, "outside"),
        ("COMPASS_USE", 2, INT8, "outside"),
        ("COMPASS_USE", 0.5, INT8, "whole number"),
        ("COMPASS_ORIENT", 44, INT8, "outside"),  # ROTATION_MAX is not a rotation
        ("COMPASS_DEV_ID", 5, INT32, "read-only"),
        ("AHRS_ORIENTATION", 300, INT8, "does not fit"),
    ]
    for name, value, _ptype, why in refusals:
        out = t.set(name, value)
        assert not out.accepted and why in out.reason, (name, out)
        assert out.value == before[name]  # the echo carries the unchanged value
    assert t.values() == before
    unknown = t.set("NO_SUCH_PARAM", 1.0)
    assert not unknown.accepted and unknown.spec is None


def test_values_are_what_the_wire_carries() -> None:
    t = ParamTable()
    out = t.set("COMPASS_OFS_Y", 0.1)
    assert out.value == f32(0.1) != 0.1  # stored as the float32 the echo will carry
    # pi as REAL32 is slightly above pi: still accepted as the range's end
    assert t.set("COMPASS_DEC", f32(math.pi)).accepted
    assert t.set("AHRS_ORIENTATION", 2.0).value == 2.0


def test_overrides_replace_defaults_and_are_validated() -> None:
    t = ParamTable(overrides={"BRG_SR_ATT": 25.0, "BRG_CAL_ONBOARD": 1})
    assert t.get("BRG_SR_ATT") == 25.0 and t.defaults["BRG_CAL_ONBOARD"] == 1.0
    with pytest.raises(ValueError, match="BRG_SR_ATT"):
        ParamTable(overrides={"BRG_SR_ATT": -1.0})
    with pytest.raises(KeyError):
        ParamTable(overrides={"NOPE": 1.0})


def _mag(rot: np.ndarray) -> AffineCalibration:
    S = np.array([[1.08, 0.03, -0.01], [0.03, 0.94, 0.02], [-0.01, 0.02, 1.01]])
    return AffineCalibration.from_arrays([0.12, -0.07, 0.21], rot @ S)


@pytest.mark.parametrize(
    ("rot", "orient"),
    [
        (euler_to_dcm(0.02, -0.01, 0.03), Rotation.ROTATION_NONE),  # a real misalignment
        (
            rotation_matrix(Rotation.ROTATION_YAW_90) @ euler_to_dcm(0.01, 0.0, 0.02),
            Rotation.ROTATION_YAW_90,
        ),
        (
            rotation_matrix(Rotation.ROTATION_ROLL_180) @ euler_to_dcm(0.0, 0.02, 0.0),
            Rotation.ROTATION_ROLL_180,
        ),
    ],
)
def test_view_round_trip_and_orientation_split(rot: np.ndarray, orient: Rotation) -> None:
    mag = _mag(rot)
    v = Calibration(mag=mag).ardupilot_parameters()
    assert set(v) == set(CAL_PARAMS)
    assert v["COMPASS_ORIENT"] == int(orient)
    assert np.linalg.norm([v["BRG_ALIGN_X"], v["BRG_ALIGN_Y"], v["BRG_ALIGN_Z"]]) < math.radians(5)
    assert v["COMPASS_OFS_X"] == pytest.approx(-120.0) and v["COMPASS_OFS_Z"] == pytest.approx(
        -210.0
    )
    back = Calibration.from_ardupilot_parameters(v).mag
    assert np.allclose(back.matrix_array, mag.matrix_array, atol=1e-12)
    assert np.allclose(back.offset_array, mag.offset_array, atol=1e-12)


@examples(60)
@given(st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3))
@example([0.0, 0.0, 1.9513015845369315e-09])  # once lost by acos in dcm_to_rotvec
def test_split_rotation_recomposes(rv: list[float]) -> None:
    R = rotvec_to_dcm(rv)
    orient, residual = split_rotation(R)
    assert np.allclose(rotation_matrix(orient) @ rotvec_to_dcm(residual), R, atol=1e-9)
    assert np.linalg.norm(residual) <= math.radians(65.0)  # the table is 45 deg apart at worst


def test_a_table_written_back_as_float32_keeps_the_calibration() -> None:
    """A GCS that reads every COMPASS_* value and writes it back changes nothing that matters."""
    mag = _mag(euler_to_dcm(0.02, -0.01, 0.03))
    t = ParamTable()
    for name, v in Calibration(mag=mag).ardupilot_parameters().items():
        t.put(name, v)
    cal = Calibration.from_ardupilot_parameters(t.values(), AffineCalibration())
    assert same_calibration(cal, Calibration(mag=mag), tol=1e-5)
    assert not same_calibration(cal, Calibration(), tol=1e-5)


def test_singular_calibration_is_refused() -> None:
    t = ParamTable()
    for n in ("COMPASS_DIA_X", "COMPASS_DIA_Y"):
        t.put(n, 1.0)
    t.put("COMPASS_ODI_X", 1.0)  # rows x and y equal: singular
    with pytest.raises(ValueError, match="singular"):
        Calibration.from_ardupilot_parameters(t.values())


def test_limits_from_values() -> None:
    t = ParamTable()
    assert limits_from_values(t.values()) == QualityLimits()  # defaults are the engine's
    t.set("BRG_FIELD_TOL", 0.3)
    t.set("BRG_DEGR_PITCH", 80.0)
    lim = limits_from_values(t.values(), QualityLimits(raise_after=7))
    assert lim.field_tolerance == pytest.approx(0.3) and lim.degraded_pitch_deg == 80.0
    assert lim.raise_after == 7  # not a parameter: kept from the base


def test_param_name_decoding() -> None:
    assert param_name(b"COMPASS_OFS_X\x00\x00\x00") == "COMPASS_OFS_X"
    assert param_name(b"ABCDEFGHIJKLMNOP") == "ABCDEFGHIJKLMNOP"  # 16 chars: no NUL
    assert param_name("BRG_SR_ATT") == "BRG_SR_ATT"
