"""ArduPilot Rotation enum and trim: each value maps the axes the way ArduPilot does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.core.mounting import (
    ROTATION_EULER_DEG,
    Mounting,
    Rotation,
    parse_rotation,
    rotation_matrix,
)

S = math.sqrt(0.5)
V = np.array([1.0, 2.0, 3.0])  # the vector ArduPilot's own rotations test uses

# Hand-derived from the meaning "v_vehicle = M @ v_sensor" (x fwd, y right, z down):
# e.g. YAW_90 = the sensor's x axis points to the vehicle's right, so sensor x -> vehicle +y.
HAND = {
    Rotation.ROTATION_NONE: lambda x, y, z: (x, y, z),
    Rotation.ROTATION_YAW_45: lambda x, y, z: (S * (x - y), S * (x + y), z),
    Rotation.ROTATION_YAW_90: lambda x, y, z: (-y, x, z),
    Rotation.ROTATION_YAW_180: lambda x, y, z: (-x, -y, z),
    Rotation.ROTATION_YAW_270: lambda x, y, z: (y, -x, z),
    Rotation.ROTATION_YAW_315: lambda x, y, z: (S * (x + y), S * (y - x), z),
    Rotation.ROTATION_ROLL_180: lambda x, y, z: (x, -y, -z),
    Rotation.ROTATION_ROLL_180_YAW_45: lambda x, y, z: (S * (x + y), S * (x - y), -z),
    Rotation.ROTATION_ROLL_180_YAW_90: lambda x, y, z: (y, x, -z),
    Rotation.ROTATION_PITCH_180: lambda x, y, z: (-x, y, -z),
    Rotation.ROTATION_ROLL_180_YAW_270: lambda x, y, z: (-y, -x, -z),
    Rotation.ROTATION_ROLL_90: lambda x, y, z: (x, -z, y),
    Rotation.ROTATION_ROLL_270: lambda x, y, z: (x, z, -y),
    Rotation.ROTATION_PITCH_90: lambda x, y, z: (z, y, -x),
    Rotation.ROTATION_PITCH_270: lambda x, y, z: (-z, y, x),
    Rotation.ROTATION_ROLL_90_YAW_90: lambda x, y, z: (z, x, y),
    Rotation.ROTATION_ROLL_90_PITCH_90: lambda x, y, z: (y, -z, -x),
    Rotation.ROTATION_PITCH_315: lambda x, y, z: (S * (x - z), y, S * (x + z)),
    Rotation.ROTATION_ROLL_45: lambda x, y, z: (x, S * (y - z), S * (y + z)),
    Rotation.ROTATION_ROLL_315: lambda x, y, z: (x, S * (y + z), S * (z - y)),
}


@pytest.mark.parametrize("rot", list(HAND), ids=lambda r: r.name)
def test_right_angle_and_45_rotations_map_axes_by_hand(rot: Rotation) -> None:
    got = rotation_matrix(rot) @ V
    np.testing.assert_allclose(got, HAND[rot](*V), atol=1e-12)


@pytest.mark.parametrize("rot", [r for r in Rotation if not r.is_custom], ids=lambda r: r.name)
def test_every_fixed_rotation_is_proper_and_named_by_its_euler(rot: Rotation) -> None:
    m = rotation_matrix(rot)
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m) == pytest.approx(1.0)
    # The name says which rotations apply, ZYX order: check roll, pitch, yaw one at a time.
    r, p, y = (math.radians(a) for a in ROTATION_EULER_DEG[rot])
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    np.testing.assert_allclose(m, rz @ ry @ rx, atol=1e-12)


def test_enum_numbers_match_mav_sensor_orientation() -> None:
    assert Rotation.ROTATION_ROLL_180 == 8
    assert Rotation.ROTATION_PITCH_180 == 12
    assert Rotation.ROTATION_ROLL_90_PITCH_68_YAW_293 == 38
    assert Rotation.ROTATION_ROLL_315 == 43
    assert Rotation.ROTATION_CUSTOM_1 == 101
    assert len(ROTATION_EULER_DEG) == 44  # 0..43, every fixed value has its angles


def test_documented_duplicates_are_the_same_matrix() -> None:
    # rotations.h: 26 "same as ROTATION_ROLL_180_YAW_270", 27 "same as ROTATION_ROLL_180_YAW_90"
    np.testing.assert_allclose(
        rotation_matrix(Rotation.ROTATION_PITCH_180_YAW_90),
        rotation_matrix(Rotation.ROTATION_ROLL_180_YAW_270),
        atol=1e-12,
    )
    np.testing.assert_allclose(
        rotation_matrix(Rotation.ROTATION_PITCH_180_YAW_270),
        rotation_matrix(Rotation.ROTATION_ROLL_180_YAW_90),
        atol=1e-12,
    )


def test_odd_board_rotation_matches_ardupilot_published_matrix() -> None:
    # The matrix rows ArduPilot hard-codes for ROTATION_ROLL_90_PITCH_68_YAW_293.
    expected = np.array(
        [
            [0.143038972, 0.368776487, -0.918446381],
            [-0.332132778, -0.856289421, -0.395545503],
            [-0.932323801, 0.361624570, 0.0],
        ]
    )
    np.testing.assert_allclose(
        rotation_matrix(Rotation.ROTATION_ROLL_90_PITCH_68_YAW_293), expected, atol=1e-6
    )


def test_parse_rotation_accepts_numbers_and_names_and_refuses_the_rest() -> None:
    assert parse_rotation(8) is Rotation.ROTATION_ROLL_180
    assert parse_rotation("roll_180") is Rotation.ROTATION_ROLL_180
    assert parse_rotation("ROTATION_YAW_90") is Rotation.ROTATION_YAW_90
    for bad in (44, 99, 103, -1, "ROLL_181", True, 8.0):
        with pytest.raises(ValueError):
            parse_rotation(bad)  # type: ignore[arg-type]  # wrong values and types, on purpose


def test_custom_rotations_use_their_angles() -> None:
    for rot in (
        Rotation.ROTATION_CUSTOM_OLD,
        Rotation.ROTATION_CUSTOM_1,
        Rotation.ROTATION_CUSTOM_2,
    ):
        np.testing.assert_allclose(
            rotation_matrix(rot, (0.0, 0.0, 90.0)),
            rotation_matrix(Rotation.ROTATION_YAW_90),
            atol=1e-12,
        )
    m = Mounting(Rotation.ROTATION_CUSTOM_1, custom_roll_deg=180.0, custom_yaw_deg=45.0)
    np.testing.assert_allclose(
        m.matrix(), rotation_matrix(Rotation.ROTATION_ROLL_180_YAW_45), atol=1e-12
    )
    with pytest.raises(ValueError):
        rotation_matrix(Rotation.ROTATION_CUSTOM_1, (math.nan, 0.0, 0.0))
    # custom angles are ignored by a fixed rotation
    np.testing.assert_allclose(
        Mounting(Rotation.ROTATION_NONE, custom_yaw_deg=90.0).matrix(), np.eye(3), atol=1e-12
    )


def test_trim_undoes_a_sensor_pitched_up_on_its_bracket() -> None:
    # Sensor tipped 2 deg nose-up relative to a level vehicle: it reads gravity as
    # R_s.T @ down with R_s = pitch(+2 deg).
    p = math.radians(2.0)
    reading = np.array([-math.sin(p), 0.0, math.cos(p)])
    m = Mounting(trim_pitch_deg=2.0)
    np.testing.assert_allclose(m.to_vehicle(reading), [0.0, 0.0, 1.0], atol=1e-12)
    # trim comes after the enum rotation: upside-down sensor, then the same bracket
    flipped = Mounting(Rotation.ROTATION_ROLL_180, trim_pitch_deg=2.0)
    sensor_reading = rotation_matrix(Rotation.ROTATION_ROLL_180).T @ reading
    np.testing.assert_allclose(flipped.to_vehicle(sensor_reading), [0.0, 0.0, 1.0], atol=1e-12)


def test_mounting_validates_inputs() -> None:
    with pytest.raises(ValueError):
        Mounting(44)  # type: ignore[arg-type]  # not a rotation: refused
    with pytest.raises(ValueError):
        Mounting(trim_roll_deg=math.inf)
    assert Mounting(8).orientation is Rotation.ROTATION_ROLL_180  # type: ignore[arg-type]  # a plain number is taken
