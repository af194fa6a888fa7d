"""How the compass sits in the vehicle: ArduPilot's ``Rotation`` enum plus a free trim.

The numbering and meaning follow ArduPilot's ``AP_Math/rotations.h`` (the same
values as MAVLink's ``MAV_SENSOR_ORIENTATION``), as used by ``COMPASS_ORIENT``
and ``AHRS_ORIENTATION``. Every named rotation ``ROTATION_ROLL_a_PITCH_b_YAW_c``
is the ZYX Euler matrix ``from_euler(a, b, c)`` (degrees) -- ArduPilot's own
rotations test checks each enum value against exactly that -- and it maps a
vector measured in the *sensor* axes into the *vehicle* body axes::

    v_vehicle = M @ v_sensor

So ``ROTATION_ROLL_180`` is a compass mounted upside down, ``ROTATION_YAW_90``
one whose arrow points to the vehicle's right.

Custom rotations: ArduPilot >= 4.2 has ``ROTATION_CUSTOM_1`` (101) and
``ROTATION_CUSTOM_2`` (102), whose Euler angles come from ``CUST_ROT1_ROLL/PITCH/YAW``
and ``CUST_ROT2_*`` (degrees, 321 order). ``ROTATION_CUSTOM_OLD`` (100, the
4.1-and-older ``ROTATION_CUSTOM``) is converted by ArduPilot into custom rotation
1 at boot; we treat it the same way. A :class:`Mounting` carries the one set of
custom angles its orientation needs (the config layer picks CUST_ROT1 or CUST_ROT2).

The trim is a further small rotation, applied after the enum rotation in the
same convention (``v_vehicle = T @ M @ v_sensor``): the sensor's residual
attitude in the vehicle frame, e.g. a bracket that tips it 2 deg nose up is
``trim_pitch_deg=2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from bridge.core.geometry import euler_to_dcm
from bridge.types import FloatArray


class Rotation(IntEnum):
    """ArduPilot ``enum Rotation`` (AP_Math/rotations.h) = MAVLink ``MAV_SENSOR_ORIENTATION``."""

    ROTATION_NONE = 0
    ROTATION_YAW_45 = 1
    ROTATION_YAW_90 = 2
    ROTATION_YAW_135 = 3
    ROTATION_YAW_180 = 4
    ROTATION_YAW_225 = 5
    ROTATION_YAW_270 = 6
    ROTATION_YAW_315 = 7
    ROTATION_ROLL_180 = 8
    ROTATION_ROLL_180_YAW_45 = 9
    ROTATION_ROLL_180_YAW_90 = 10
    ROTATION_ROLL_180_YAW_135 = 11
    ROTATION_PITCH_180 = 12
    ROTATION_ROLL_180_YAW_225 = 13
    ROTATION_ROLL_180_YAW_270 = 14
    ROTATION_ROLL_180_YAW_315 = 15
    ROTATION_ROLL_90 = 16
    ROTATION_ROLL_90_YAW_45 = 17
    ROTATION_ROLL_90_YAW_90 = 18
    ROTATION_ROLL_90_YAW_135 = 19
    ROTATION_ROLL_270 = 20
    ROTATION_ROLL_270_YAW_45 = 21
    ROTATION_ROLL_270_YAW_90 = 22
    ROTATION_ROLL_270_YAW_135 = 23
    ROTATION_PITCH_90 = 24
    ROTATION_PITCH_270 = 25
    ROTATION_PITCH_180_YAW_90 = 26  # same matrix as ROTATION_ROLL_180_YAW_270
    ROTATION_PITCH_180_YAW_270 = 27  # same matrix as ROTATION_ROLL_180_YAW_90
    ROTATION_ROLL_90_PITCH_90 = 28
    ROTATION_ROLL_180_PITCH_90 = 29
    ROTATION_ROLL_270_PITCH_90 = 30
    ROTATION_ROLL_90_PITCH_180 = 31
    ROTATION_ROLL_270_PITCH_180 = 32
    ROTATION_ROLL_90_PITCH_270 = 33
    ROTATION_ROLL_180_PITCH_270 = 34
    ROTATION_ROLL_270_PITCH_270 = 35
    ROTATION_ROLL_90_PITCH_180_YAW_90 = 36
    ROTATION_ROLL_90_YAW_270 = 37
    ROTATION_ROLL_90_PITCH_68_YAW_293 = 38  # a specific board; (90, 68.8, 293.3) deg
    ROTATION_PITCH_315 = 39
    ROTATION_ROLL_90_PITCH_315 = 40
    ROTATION_PITCH_7 = 41
    ROTATION_ROLL_45 = 42
    ROTATION_ROLL_315 = 43
    # 44 is ROTATION_MAX in ArduPilot: a sentinel, not a rotation.
    ROTATION_CUSTOM_OLD = 100  # ArduPilot <= 4.1 "ROTATION_CUSTOM"; treated as custom 1
    ROTATION_CUSTOM_1 = 101
    ROTATION_CUSTOM_2 = 102

    @property
    def is_custom(self) -> bool:
        """True for the custom rotations, whose angles come from CUST_ROTn_* parameters."""
        return self.value >= 100


#: ZYX Euler angles (roll, pitch, yaw) in degrees of every fixed rotation, as
#: ArduPilot's rotations test states them.
ROTATION_EULER_DEG: dict[Rotation, tuple[float, float, float]] = {
    Rotation.ROTATION_NONE: (0, 0, 0),
    Rotation.ROTATION_YAW_45: (0, 0, 45),
    Rotation.ROTATION_YAW_90: (0, 0, 90),
    Rotation.ROTATION_YAW_135: (0, 0, 135),
    Rotation.ROTATION_YAW_180: (0, 0, 180),
    Rotation.ROTATION_YAW_225: (0, 0, 225),
    Rotation.ROTATION_YAW_270: (0, 0, 270),
    Rotation.ROTATION_YAW_315: (0, 0, 315),
    Rotation.ROTATION_ROLL_180: (180, 0, 0),
    Rotation.ROTATION_ROLL_180_YAW_45: (180, 0, 45),
    Rotation.ROTATION_ROLL_180_YAW_90: (180, 0, 90),
    Rotation.ROTATION_ROLL_180_YAW_135: (180, 0, 135),
    Rotation.ROTATION_PITCH_180: (0, 180, 0),
    Rotation.ROTATION_ROLL_180_YAW_225: (180, 0, 225),
    Rotation.ROTATION_ROLL_180_YAW_270: (180, 0, 270),
    Rotation.ROTATION_ROLL_180_YAW_315: (180, 0, 315),
    Rotation.ROTATION_ROLL_90: (90, 0, 0),
    Rotation.ROTATION_ROLL_90_YAW_45: (90, 0, 45),
    Rotation.ROTATION_ROLL_90_YAW_90: (90, 0, 90),
    Rotation.ROTATION_ROLL_90_YAW_135: (90, 0, 135),
    Rotation.ROTATION_ROLL_270: (270, 0, 0),
    Rotation.ROTATION_ROLL_270_YAW_45: (270, 0, 45),
    Rotation.ROTATION_ROLL_270_YAW_90: (270, 0, 90),
    Rotation.ROTATION_ROLL_270_YAW_135: (270, 0, 135),
    Rotation.ROTATION_PITCH_90: (0, 90, 0),
    Rotation.ROTATION_PITCH_270: (0, 270, 0),
    Rotation.ROTATION_PITCH_180_YAW_90: (0, 180, 90),
    Rotation.ROTATION_PITCH_180_YAW_270: (0, 180, 270),
    Rotation.ROTATION_ROLL_90_PITCH_90: (90, 90, 0),
    Rotation.ROTATION_ROLL_180_PITCH_90: (180, 90, 0),
    Rotation.ROTATION_ROLL_270_PITCH_90: (270, 90, 0),
    Rotation.ROTATION_ROLL_90_PITCH_180: (90, 180, 0),
    Rotation.ROTATION_ROLL_270_PITCH_180: (270, 180, 0),
    Rotation.ROTATION_ROLL_90_PITCH_270: (90, 270, 0),
    Rotation.ROTATION_ROLL_180_PITCH_270: (180, 270, 0),
    Rotation.ROTATION_ROLL_270_PITCH_270: (270, 270, 0),
    Rotation.ROTATION_ROLL_90_PITCH_180_YAW_90: (90, 180, 90),
    Rotation.ROTATION_ROLL_90_YAW_270: (90, 0, 270),
    Rotation.ROTATION_ROLL_90_PITCH_68_YAW_293: (90, 68.8, 293.3),
    Rotation.ROTATION_PITCH_315: (0, 315, 0),
    Rotation.ROTATION_ROLL_90_PITCH_315: (90, 315, 0),
    Rotation.ROTATION_PITCH_7: (0, 7, 0),
    Rotation.ROTATION_ROLL_45: (45, 0, 0),
    Rotation.ROTATION_ROLL_315: (315, 0, 0),
}


def parse_rotation(value: int | str | Rotation) -> Rotation:
    """A COMPASS_ORIENT / AHRS_ORIENTATION value (number or enum name) as a :class:`Rotation`.

    Raises ``ValueError`` for anything that is not a rotation (e.g. 44, ROTATION_MAX).
    """
    if isinstance(value, Rotation):
        return value
    if isinstance(value, str):
        name = value.strip().upper()
        if not name.startswith("ROTATION_"):
            name = "ROTATION_" + name
        try:
            return Rotation[name]
        except KeyError:
            raise ValueError(f"unknown rotation name {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"rotation must be an int or a name, got {value!r}")
    try:
        return Rotation(value)
    except ValueError:
        raise ValueError(f"{value} is not an ArduPilot Rotation (0-43, 100-102)") from None


def rotation_matrix(
    rotation: Rotation | int, custom_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> FloatArray:
    """Sensor-to-vehicle matrix of an ArduPilot rotation (``v_vehicle = M @ v_sensor``).

    ``custom_rpy_deg`` (CUST_ROTn_ROLL/PITCH/YAW) is used only by the custom rotations.
    The 90-degree multiples come out as exact 0/+-1 entries (rounding the
    trigonometric noise away) so axis swaps are bit-exact.
    """
    rot = parse_rotation(rotation)
    if rot.is_custom:
        r, p, y = custom_rpy_deg
        for v in (r, p, y):
            if not math.isfinite(v):
                raise ValueError(f"custom rotation angles must be finite, got {custom_rpy_deg}")
    else:
        r, p, y = ROTATION_EULER_DEG[rot]
    m = euler_to_dcm(math.radians(r), math.radians(p), math.radians(y))
    # Snap entries that are 0/+-1 up to rounding: exact axis permutations for the
    # right-angle rotations, harmless for the others (|error| < 1e-12).
    snapped = np.round(m)
    close = np.abs(m - snapped) < 1e-12
    return np.where(close, snapped, m)


@dataclass(frozen=True, slots=True)
class Mounting:
    """The compass's orientation in the vehicle: an ArduPilot rotation plus a trim.

    ``custom_*_deg`` are CUST_ROTn_ROLL/PITCH/YAW, used only when ``orientation``
    is a custom rotation. ``trim_*_deg`` is applied after the rotation (ZYX Euler,
    degrees). Raises ``ValueError`` on a non-rotation value or non-finite angles.
    """

    orientation: Rotation = Rotation.ROTATION_NONE
    custom_roll_deg: float = 0.0
    custom_pitch_deg: float = 0.0
    custom_yaw_deg: float = 0.0
    trim_roll_deg: float = 0.0
    trim_pitch_deg: float = 0.0
    trim_yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "orientation", parse_rotation(self.orientation))
        for name in (
            "custom_roll_deg",
            "custom_pitch_deg",
            "custom_yaw_deg",
            "trim_roll_deg",
            "trim_pitch_deg",
            "trim_yaw_deg",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")

    def matrix(self) -> FloatArray:
        """The full sensor-to-vehicle matrix ``T_trim @ M_orientation``."""
        m = rotation_matrix(
            self.orientation, (self.custom_roll_deg, self.custom_pitch_deg, self.custom_yaw_deg)
        )
        if self.trim_roll_deg == 0.0 and self.trim_pitch_deg == 0.0 and self.trim_yaw_deg == 0.0:
            return m
        t = euler_to_dcm(
            math.radians(self.trim_roll_deg),
            math.radians(self.trim_pitch_deg),
            math.radians(self.trim_yaw_deg),
        )
        return t @ m

    def to_vehicle(self, v_sensor: FloatArray) -> FloatArray:
        """Rotate a (3,) or (N, 3) sensor-frame vector into vehicle axes."""
        return np.asarray(v_sensor, dtype=np.float64) @ self.matrix().T
