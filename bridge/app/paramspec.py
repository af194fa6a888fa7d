"""The bridge's parameters: names, types, ranges, and the calibration they describe (pure).

Names follow ArduPilot where ArduPilot has one, so MAVProxy / QGroundControl /
Mission Planner users find what they know; the bridge's own live under
``BRG_``. Types are ArduPilot's storage types (INT8, INT32, REAL32); how they
travel on MAVLink depends on the ground station's flavour and is the MAVLink
adapter's business (:mod:`bridge.mavlink.paramproto`).

The calibration group (COMPASS_OFS_*, COMPASS_DIA_*, COMPASS_ODI_*,
COMPASS_SCALE, COMPASS_ORIENT, BRG_ALIGN_*) *is* the magnetometer
calibration, written the ArduPilot way (the calibration's parameter view,
:meth:`bridge.core.calibration.Calibration.ardupilot_parameters`)::

    corrected = COMPASS_SCALE * R(COMPASS_ORIENT) @ R(BRG_ALIGN) @ S @ (raw + COMPASS_OFS / 1000)
    S = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]

``R(BRG_ALIGN)`` is the rotation the symmetric ArduPilot form cannot hold (a
rotation vector in radians: the magnetometer-to-accelerometer alignment the
best fit finds). A fitted rotation of more than 45 deg is split into the
nearest ArduPilot rotation (COMPASS_ORIENT) and a residual, as ArduPilot's
own calibrator reports a new orientation.

A value is refused when the name is unknown or read-only, the value is
NaN/inf, out of range, or not a whole number for an integer type (judged by
the parameter's own type, as ArduPilot does), or when the calibration it
would give is singular.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.core.calibration import Calibration
from bridge.core.mounting import ROTATION_EULER_DEG, Mounting, Rotation
from bridge.core.quality import QualityLimits
from bridge.types import HEADING_REFERENCES, LEARN_MODES

# ArduPilot's storage types, numbered as MAVLink's MAV_PARAM_TYPE (which the MAVLink
# adapter puts on the wire, encoded as the ground station's flavour expects).
INT8 = 2
INT16 = 4
INT32 = 6
REAL32 = 9
_INT_TYPES = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-(2**31), 2**31 - 1)}
_TYPE_NAMES = {INT8: "INT8", INT16: "INT16", INT32: "INT32", REAL32: "REAL32"}

NAME_MAX = 16  #: param_id is char[16]

#: Device id reported as COMPASS_DEV_ID, built the ArduPilot way
#: (bus type 6 = SERIAL, bus 0, address 0, devtype 0x47 'G').
COMPASS_DEV_ID = (6 & 0x7) | (0 << 3) | (0 << 8) | (0x47 << 16)

#: ArduPilot rotations a parameter may name: the fixed ones (custom rotations need CUST_ROT*).
ROTATION_CHOICES: tuple[int, ...] = tuple(int(r) for r in ROTATION_EULER_DEG)


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One parameter: name, MAV_PARAM_TYPE, default, range and what it means."""

    name: str
    ptype: int
    default: float
    minimum: float
    maximum: float
    doc: str
    unit: str = ""
    group: str = "bridge"
    read_only: bool = False
    choices: tuple[int, ...] | None = None
    #: The configuration key giving the default ("section.key"; "" = a parameter only).
    config_key: str = ""
    #: A string configuration key's values, by parameter value (0, 1, ...).
    config_choices: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if not 0 < len(self.name) <= NAME_MAX or not self.name.isascii():
            raise ValueError(f"bad parameter name {self.name!r}")


def _f32(v: float) -> float:
    """``v`` as the float32 it becomes on the wire (so the echo equals the stored value)."""
    return float(struct.unpack("<f", struct.pack("<f", v))[0])


#: The autopilot heading feeds, by BRG_HDG_FEED value (``[mavlink] heading_feed``).
HEADING_FEEDS: tuple[str, ...] = ("off", "px4_odometry", "ardupilot_vision")


@dataclass(frozen=True, slots=True)
class StreamRate:
    """A MAVLink stream's rate parameter: its name, what it sends, the configuration key
    giving its default, and that default (Hz, 0 = off)."""

    param: str
    message: str
    config_key: str
    default_hz: float


#: The configurable MAVLink streams' rates (the MAVLink adapter maps them to messages).
STREAM_RATES: tuple[StreamRate, ...] = (
    StreamRate("BRG_SR_ATT", "ATTITUDE", "rate_attitude_hz", 10.0),
    StreamRate("BRG_SR_QUAT", "ATTITUDE_QUATERNION", "rate_attitude_quaternion_hz", 10.0),
    StreamRate("BRG_SR_HUD", "VFR_HUD", "rate_vfr_hud_hz", 4.0),
    StreamRate("BRG_SR_SIMU", "SCALED_IMU", "rate_scaled_imu_hz", 2.0),
    StreamRate("BRG_SR_RIMU", "RAW_IMU", "rate_raw_imu_hz", 2.0),
    StreamRate("BRG_SR_HIMU", "HIGHRES_IMU", "rate_highres_imu_hz", 2.0),
    StreamRate("BRG_SR_SYS", "SYS_STATUS", "rate_sys_status_hz", 1.0),
    StreamRate("BRG_SR_FEED", "heading feed", "rate_heading_feed_hz", 10.0),
)


def _stream_specs() -> list[ParamSpec]:
    return [
        ParamSpec(
            r.param,
            REAL32,
            r.default_hz,
            0.0,
            50.0,
            f"{r.message} rate (0 = off)",
            "Hz",
            "rates",
            config_key=f"mavlink.{r.config_key}",
        )
        for r in STREAM_RATES
    ]


#: Every parameter, in index order (PARAM_VALUE.param_index).
SPECS: tuple[ParamSpec, ...] = (
    # -- the magnetometer calibration (ArduPilot's names and units)
    ParamSpec(
        "COMPASS_OFS_X", REAL32, 0.0, -10000, 10000, "offset added to raw x", "mGauss", "cal"
    ),
    ParamSpec(
        "COMPASS_OFS_Y", REAL32, 0.0, -10000, 10000, "offset added to raw y", "mGauss", "cal"
    ),
    ParamSpec(
        "COMPASS_OFS_Z", REAL32, 0.0, -10000, 10000, "offset added to raw z", "mGauss", "cal"
    ),
    ParamSpec("COMPASS_DIA_X", REAL32, 1.0, 0.05, 20.0, "soft-iron diagonal x", "", "cal"),
    ParamSpec("COMPASS_DIA_Y", REAL32, 1.0, 0.05, 20.0, "soft-iron diagonal y", "", "cal"),
    ParamSpec("COMPASS_DIA_Z", REAL32, 1.0, 0.05, 20.0, "soft-iron diagonal z", "", "cal"),
    ParamSpec("COMPASS_ODI_X", REAL32, 0.0, -5.0, 5.0, "soft-iron off-diagonal xy", "", "cal"),
    ParamSpec("COMPASS_ODI_Y", REAL32, 0.0, -5.0, 5.0, "soft-iron off-diagonal xz", "", "cal"),
    ParamSpec("COMPASS_ODI_Z", REAL32, 0.0, -5.0, 5.0, "soft-iron off-diagonal yz", "", "cal"),
    ParamSpec("COMPASS_SCALE", REAL32, 1.0, 0.01, 100.0, "field scale factor", "", "cal"),
    ParamSpec(
        "COMPASS_ORIENT",
        INT8,
        0,
        0,
        max(ROTATION_CHOICES),
        "magnetometer rotation relative to the accelerometer (ArduPilot Rotation)",
        "",
        "cal",
        choices=ROTATION_CHOICES,
    ),
    ParamSpec(
        "BRG_ALIGN_X",
        REAL32,
        0.0,
        -math.pi,
        math.pi,
        "mag-to-accel alignment, rotation vector x",
        "rad",
        "cal",
    ),
    ParamSpec(
        "BRG_ALIGN_Y",
        REAL32,
        0.0,
        -math.pi,
        math.pi,
        "mag-to-accel alignment, rotation vector y",
        "rad",
        "cal",
    ),
    ParamSpec(
        "BRG_ALIGN_Z",
        REAL32,
        0.0,
        -math.pi,
        math.pi,
        "mag-to-accel alignment, rotation vector z",
        "rad",
        "cal",
    ),
    # -- compass use, identity, fit threshold
    ParamSpec(
        "COMPASS_USE",
        INT8,
        1,
        0,
        1,
        "use the compass for heading (SYS_STATUS enabled, heading feed)",
        "",
        "use",
    ),
    ParamSpec(
        "COMPASS_DEV_ID",
        INT32,
        COMPASS_DEV_ID,
        COMPASS_DEV_ID,
        COMPASS_DEV_ID,
        "device id (read-only)",
        "",
        "info",
        read_only=True,
    ),
    ParamSpec(
        "COMPASS_CAL_FIT",
        REAL32,
        16.0,
        1.0,
        100.0,
        "largest fitness (RMS residual) a calibration may have",
        "mGauss",
        "cal_fit",
    ),
    # -- declination
    ParamSpec(
        "COMPASS_AUTODEC",
        INT8,
        1,
        0,
        1,
        "declination from the World Magnetic Model at the position",
        "",
        "dec",
    ),
    ParamSpec(
        "COMPASS_DEC",
        REAL32,
        0.0,
        -math.pi,
        math.pi,
        "declination, east positive (set by the WMM when COMPASS_AUTODEC = 1)",
        "rad",
        "dec",
    ),
    # -- the published heading
    ParamSpec(
        "BRG_HDG_REF",
        INT8,
        0,
        0,
        1,
        "published heading: 0 magnetic north, 1 true north (needs a declination)",
        "",
        "heading",
        config_key="heading.reference",
        config_choices=HEADING_REFERENCES,
    ),
    # -- mounting
    ParamSpec(
        "AHRS_ORIENTATION",
        INT8,
        0,
        0,
        max(ROTATION_CHOICES),
        "the unit's orientation in the vehicle (ArduPilot Rotation)",
        "",
        "mount",
        choices=ROTATION_CHOICES,
    ),
    # -- quality limits (bridge.core.quality.QualityLimits)
    ParamSpec(
        "BRG_FIELD_TOL",
        REAL32,
        0.15,
        0.01,
        1.0,
        "field strength tolerance before 'disturbed'",
        "",
        "limits",
    ),
    ParamSpec(
        "BRG_DIP_TOL",
        REAL32,
        5.0,
        0.5,
        45.0,
        "dip angle tolerance before 'disturbed'",
        "deg",
        "limits",
    ),
    ParamSpec(
        "BRG_ACC_TOL",
        REAL32,
        0.1,
        0.01,
        1.0,
        "|accel| - 1 g tolerance before 'accelerating'",
        "g",
        "limits",
    ),
    ParamSpec(
        "BRG_DEGR_PITCH",
        REAL32,
        85.0,
        10.0,
        90.0,
        "|pitch| beyond which the attitude is 'degraded'",
        "deg",
        "limits",
    ),
    # -- calibration routing
    ParamSpec(
        "BRG_CAL_ONBOARD",
        INT8,
        0,
        0,
        1,
        "magnetometer/level calibration by the compass itself (1) or the host (0)",
        "",
        "routing",
        config_key="calibration.onboard",
    ),
    # -- calibration drift (bridge.app.calibration.drift)
    ParamSpec(
        "BRG_CAL_LEARN",
        INT8,
        1,
        0,
        2,
        "hard-iron drift: 0 off, 1 detect and warn, 2 also learn the offsets",
        "",
        "learn",
        config_key="calibration.learn",
        config_choices=LEARN_MODES,
    ),
    ParamSpec(
        "BRG_CAL_UNDO",
        INT8,
        0,
        0,
        1,
        "set 1: back to the calibration before learning (reads 1 until set to 0 again)",
        "",
        "learn",
    ),
    # -- autopilot heading feed
    ParamSpec(
        "BRG_HDG_FEED",
        INT8,
        0,
        0,
        len(HEADING_FEEDS) - 1,
        "heading feed: 0 off, 1 PX4 ODOMETRY, 2 ArduPilot VISION_POSITION_ESTIMATE",
        "",
        "feed",
        config_key="mavlink.heading_feed",
        config_choices=HEADING_FEEDS,
    ),
    ParamSpec(
        "BRG_YAW_SIGMA",
        REAL32,
        2.0,
        0.1,
        90.0,
        "heading feed yaw standard deviation",
        "deg",
        "feed",
        config_key="mavlink.heading_feed_sigma_deg",
    ),
    # -- stream rates
    *_stream_specs(),
)

CAL_PARAMS: tuple[str, ...] = tuple(s.name for s in SPECS if s.group == "cal")
#: Parameters whose default a configuration key gives (a value set over MAVLink wins).
CONFIG_PARAMS: tuple[ParamSpec, ...] = tuple(s for s in SPECS if s.config_key)


def param_from_config(spec: ParamSpec, value: Any) -> float:
    """The parameter value of configuration value ``value`` (``spec.config_key``'s)."""
    if spec.config_choices is not None:
        return float(spec.config_choices.index(value))
    return float(value)


def config_from_param(spec: ParamSpec, value: float, like: Any) -> Any:
    """The configuration value of parameter value ``value``, typed as ``like`` (the
    configuration's own value of ``spec.config_key``)."""
    if spec.config_choices is not None:
        i = int(value)
        return spec.config_choices[i] if 0 <= i < len(spec.config_choices) else value
    if isinstance(like, bool):
        return value != 0
    if isinstance(like, int):
        return int(value)
    return decimal7(value) if spec.ptype == REAL32 else float(value)


@dataclass(frozen=True, slots=True)
class SetOutcome:
    """Result of :meth:`ParamTable.set`: ``accepted``, the value now in force, and why not."""

    accepted: bool
    spec: ParamSpec | None
    index: int
    value: float
    reason: str = ""


class ParamTable:
    """The parameter values (pure, not thread-safe: one owner).

    ``overrides`` replaces defaults (e.g. from the configuration file);
    :meth:`set` validates; :meth:`put` stores without validation (values the
    bridge computes itself, e.g. a new calibration's view).
    """

    def __init__(
        self, specs: Iterable[ParamSpec] = SPECS, overrides: Mapping[str, float] | None = None
    ) -> None:
        self.specs: tuple[ParamSpec, ...] = tuple(specs)
        self._index = {s.name: i for i, s in enumerate(self.specs)}
        if len(self._index) != len(self.specs):
            raise ValueError("duplicate parameter names")
        self.defaults: dict[str, float] = {s.name: self._normal(s, s.default) for s in self.specs}
        for name, v in (overrides or {}).items():
            spec = self.spec(name)
            if spec is None:
                raise KeyError(f"unknown parameter {name!r}")
            reason = self.check(spec, v)
            if reason:
                raise ValueError(f"{name}: {reason}")
            self.defaults[name] = self._normal(spec, v)
        self._values: dict[str, float] = dict(self.defaults)

    def __len__(self) -> int:
        return len(self.specs)

    def spec(self, name: str) -> ParamSpec | None:
        """The spec of ``name`` (None if unknown)."""
        i = self._index.get(name)
        return None if i is None else self.specs[i]

    def index(self, name: str) -> int:
        """The index of ``name`` (``KeyError`` if unknown)."""
        return self._index[name]

    def get(self, name: str) -> float:
        """The value of ``name`` (``KeyError`` if unknown)."""
        return self._values[name]

    def values(self) -> dict[str, float]:
        """All values by name (a copy)."""
        return dict(self._values)

    def by_index(self, index: int) -> tuple[ParamSpec, float]:
        """(spec, value) at ``index`` (``IndexError`` if out of range)."""
        if not 0 <= index < len(self.specs):
            raise IndexError(index)
        s = self.specs[index]
        return s, self._values[s.name]

    @staticmethod
    def _normal(spec: ParamSpec, v: float) -> float:
        return float(int(v)) if spec.ptype in _INT_TYPES else _f32(float(v))

    @staticmethod
    def check(spec: ParamSpec, value: Any) -> str:
        """Why ``value`` may not be set; "" if it may.

        The value is judged by the parameter's own type, as ArduPilot does (it ignores
        the type a PARAM_SET names): a whole number in range for an integer parameter.
        """
        if spec.read_only:
            return "read-only"
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"not a number: {value!r}"
        v = float(value)
        if not math.isfinite(v):
            return f"not finite: {v}"
        if spec.ptype in _INT_TYPES:
            if v != math.floor(v):
                return f"{v} is not a whole number"
            tlo, thi = _INT_TYPES[spec.ptype]
            if not tlo <= v <= thi:
                return f"{v:g} does not fit {_TYPE_NAMES[spec.ptype]}"
        # float32 rounding of the limits themselves (pi as REAL32) must not refuse them
        lo, hi = spec.minimum, spec.maximum
        if spec.ptype == REAL32:
            lo, hi = min(lo, _f32(lo)), max(hi, _f32(hi))
        if not lo <= v <= hi:
            return f"{v:g} outside [{spec.minimum:g}, {spec.maximum:g}]"
        if spec.choices is not None and int(v) not in spec.choices:
            return f"{int(v)} is not one of the allowed values"
        return ""

    def set(self, name: str, value: Any) -> SetOutcome:
        """Validate and store; on refusal nothing changes and the outcome carries the reason."""
        spec = self.spec(name)
        if spec is None:
            return SetOutcome(False, None, -1, math.nan, "unknown parameter")
        i = self._index[name]
        reason = self.check(spec, value)
        if reason:
            return SetOutcome(False, spec, i, self._values[name], reason)
        self._values[name] = self._normal(spec, float(value))
        return SetOutcome(True, spec, i, self._values[name])

    def put(self, name: str, value: float) -> None:
        """Store a value the bridge computed (no range check; still normalised to the wire type)."""
        spec = self.spec(name)
        if spec is None:
            raise KeyError(name)
        self._values[name] = self._normal(spec, value)

    def restore(self, name: str, value: float) -> None:
        """Put back a previous value (undo of a refused side effect)."""
        self._values[name] = value


# ---------------------------------------------------------------------------- the calibration


def same_calibration(a: Calibration, b: Calibration, tol: float = 1e-6) -> bool:
    """Equal up to ``tol`` (absolute, on offsets in gauss and matrix entries)."""
    pairs = ((a.mag, b.mag), (a.accel, b.accel))
    return all(
        np.allclose(x.offset_array, y.offset_array, atol=tol, rtol=0.0)
        and np.allclose(x.matrix_array, y.matrix_array, atol=tol, rtol=0.0)
        for x, y in pairs
    )


def decimal7(v: float) -> float:
    """A float32 parameter as the decimal a GCS shows (0.15000000596 -> 0.15)."""
    return float(f"{v:.7g}")


def limits_from_values(
    values: Mapping[str, float], base: QualityLimits | None = None
) -> QualityLimits:
    """QualityLimits from BRG_FIELD_TOL / BRG_DIP_TOL / BRG_ACC_TOL / BRG_DEGR_PITCH."""
    b = base if base is not None else QualityLimits()
    return QualityLimits(
        field_tolerance=decimal7(values["BRG_FIELD_TOL"]),
        dip_tolerance_deg=decimal7(values["BRG_DIP_TOL"]),
        accel_tolerance_g=decimal7(values["BRG_ACC_TOL"]),
        degraded_pitch_deg=decimal7(values["BRG_DEGR_PITCH"]),
        raise_after=b.raise_after,
        clear_after=b.clear_after,
    )


def limits_values(limits: QualityLimits) -> dict[str, float]:
    """Inverse of :func:`limits_from_values` (to show the engine's limits as parameters)."""
    return {
        "BRG_FIELD_TOL": limits.field_tolerance,
        "BRG_DIP_TOL": limits.dip_tolerance_deg,
        "BRG_ACC_TOL": limits.accel_tolerance_g,
        "BRG_DEGR_PITCH": limits.degraded_pitch_deg,
    }


def mounting_from_values(values: Mapping[str, float]) -> Mounting:
    """The engine's mounting: AHRS_ORIENTATION."""
    return Mounting(orientation=Rotation(int(values["AHRS_ORIENTATION"])))


def param_name(raw: bytes | str) -> str:
    """A received param_id as text (NUL-terminated unless 16 characters long)."""
    if isinstance(raw, bytes):
        raw = raw.split(b"\0", 1)[0].decode("ascii", "replace")
    return raw.split("\0", 1)[0]
