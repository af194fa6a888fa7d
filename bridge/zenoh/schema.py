"""The JSON documents the bridge publishes on Zenoh: names, versions, builders, validation.

PURE: no I/O, no clocks -- every time value comes in as an argument.

Every document is a JSON object that names itself twice, so that a consumer
can tell what it holds with or without Zenoh's metadata:

* in the body: ``"schema": "compass-bridge/heading", "version": 1``;
* in the Zenoh encoding: ``application/json;compass-bridge/heading@1``.

A version changes only when a field is removed, renamed or changes meaning or
unit; adding a field is not a new version (consumers ignore fields they do not
know). :func:`validate` checks a received document against the field table of
its schema, so a consumer (``compass-bridge monitor``, the tests) never trusts
a payload it has not checked.

Units: angles in degrees (headings [0, 360) clockwise from north, roll
[-180, 180] right wing down positive, pitch [-90, 90] nose up positive);
magnetic field in gauss; acceleration in g with the datasheet's gravity-vector
sign (a level unit reads (0, 0, +1)); raw values in ADC counts (0..4095);
times in seconds. Axes: vehicle body x forward, y right, z down (FRD); world
NED. Non-finite numbers are published as ``null`` (strict JSON has no NaN).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:  # types only: a consumer (monitor) must not pull in the daemon and numpy
    from bridge.app.sample import CompassSample, DaemonStatus
    from bridge.events import Event
    from bridge.protocol.device import LinkCounters

#: The family every schema name starts with.
SCHEMA_FAMILY: Final = "compass-bridge"

HEADING: Final = f"{SCHEMA_FAMILY}/heading"
ATTITUDE: Final = f"{SCHEMA_FAMILY}/attitude"
IMU: Final = f"{SCHEMA_FAMILY}/imu"
STATUS: Final = f"{SCHEMA_FAMILY}/status"
EVENT: Final = f"{SCHEMA_FAMILY}/event"
CALIBRATION: Final = f"{SCHEMA_FAMILY}/calibration"
PARAMS: Final = f"{SCHEMA_FAMILY}/params"
COMMAND_RESULT: Final = f"{SCHEMA_FAMILY}/command-result"

#: Current version of each schema.
VERSIONS: Final[Mapping[str, int]] = {
    HEADING: 1,
    ATTITUDE: 1,
    IMU: 1,
    STATUS: 1,
    EVENT: 1,
    CALIBRATION: 1,
    PARAMS: 1,
    COMMAND_RESULT: 1,
}

JSON_MIME: Final = "application/json"


def encoding_text(schema: str) -> str:
    """The Zenoh encoding string of a schema: ``application/json;<schema>@<version>``."""
    return f"{JSON_MIME};{schema}@{VERSIONS[schema]}"


def schema_from_encoding(encoding: str) -> tuple[str, int] | None:
    """``(schema, version)`` from an encoding string, or None if it names no schema of ours."""
    mime, sep, suffix = encoding.partition(";")
    if mime != JSON_MIME or not sep:
        return None
    name, at, version = suffix.rpartition("@")
    if not at or not name.startswith(SCHEMA_FAMILY + "/") or not version.isdigit():
        return None
    return name, int(version)


# ---------------------------------------------------------------------------
# Serialisation
# ---------------------------------------------------------------------------


def _clean(v: Any) -> Any:
    """Non-finite floats -> None, tuples -> lists, recursively (strict JSON)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, Mapping):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    return v


def _make_encode() -> Callable[[Any], str]:
    """The compact, strict encoder, made once.

    json.dumps() with any option builds a JSONEncoder, and JSONEncoder.encode() a C
    encoder, per call: three times per published sample. CPython's C encoder made once
    (no circular-reference bookkeeping: the documents are trees) does the same work
    without those; the pure-Python encoder where there is no C one.
    """
    c_make_encoder = getattr(json.encoder, "c_make_encoder", None)
    if c_make_encoder is None:
        return json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode
    iterencode = c_make_encoder(
        None,  # markers: no circular check
        json.JSONEncoder().default,  # raises TypeError for what JSON cannot carry
        json.encoder.encode_basestring_ascii,
        None,  # indent
        ":",
        ",",
        False,  # sort_keys
        False,  # skipkeys
        False,  # allow_nan: NaN/inf raise ValueError
    )

    def encode(doc: Any) -> str:
        return "".join(iterencode(doc, 0))

    return encode


_encode = _make_encode()


def dumps(doc: Mapping[str, Any]) -> bytes:
    """Strict, compact UTF-8 JSON (NaN/inf become null)."""
    try:
        # The builders below already write None for non-finite numbers: the common case
        # needs no second walk over the document (this runs for every published sample).
        text = _encode(doc)
    except ValueError:
        text = _encode(_clean(doc))
    return text.encode("utf-8")


_isfinite = math.isfinite  # a module global: one lookup, per number of every document


def _r(v: float | None, digits: int) -> float | None:
    """Round for the wire (the sensor is not better than this), keeping None/non-finite as None.

    round() is most of a sensor document's cost (a decimal conversion each way): the
    builders below call it once per number, and a value that appears twice is rounded
    once.
    """
    return round(v, digits) if v is not None and _isfinite(v) else None


def _vec(v: Sequence[float] | None, digits: int) -> list[float | None] | None:
    if v is None:
        return None
    x, y, z = v  # a Vec3; float() keeps a numpy scalar's rounding a plain float
    return [_r(float(x), digits), _r(float(y), digits), _r(float(z), digits)]


def _head(schema: str) -> dict[str, Any]:
    return {"schema": schema, "version": VERSIONS[schema]}


# ---------------------------------------------------------------------------
# Sensor streams
# ---------------------------------------------------------------------------

_ANGLE_DIGITS = 3  # 0.001 deg: far below the compass's noise, keeps payloads short
_FIELD_DIGITS = 6  # 1 microgauss = 0.1 nT
_ACCEL_DIGITS = 5  # 10 micro-g
_QUAT_DIGITS = 7


class SampleTimes:
    """When a sample happened, in the clocks a consumer can use.

    ``t_monotonic`` is the host's CLOCK_MONOTONIC at the frame's arrival (the
    sample's own time); ``t_unix`` the same instant on the wall clock;
    ``zenoh_time`` the publication's Zenoh HLC timestamp as RFC 3339 text
    (also carried as the Zenoh sample's timestamp), or None.

    A plain class, not a frozen dataclass: one is made for every published
    sample, and a frozen dataclass's ``__init__`` sets each field through
    ``object.__setattr__`` (measured: the dearest step of a sample's
    documents after the JSON itself). Treat it as read-only.
    """

    __slots__ = ("t_monotonic", "t_unix", "wire", "zenoh_time")

    def __init__(self, t_monotonic: float, t_unix: float, zenoh_time: str | None = None) -> None:
        self.t_monotonic = t_monotonic
        self.t_unix = t_unix
        self.zenoh_time = zenoh_time
        #: ``(t_monotonic, t_unix)`` rounded for the wire: once per sample, not per document.
        self.wire = (round(t_monotonic, 6), round(t_unix, 6))

    def __repr__(self) -> str:
        return (
            f"SampleTimes(t_monotonic={self.t_monotonic!r}, t_unix={self.t_unix!r}, "
            f"zenoh_time={self.zenoh_time!r})"
        )


def _sample_head(schema: str, sample: CompassSample, times: SampleTimes) -> dict[str, Any]:
    """The head every sensor document starts with, in this order (the caller's dict display
    unpacks it first, so the published key order holds)."""
    t_monotonic, t_unix = times.wire
    return {
        "schema": schema,
        "version": VERSIONS[schema],
        "seq": sample.seq,
        "t_monotonic": t_monotonic,
        "t_unix": t_unix,
        "zenoh_time": times.zenoh_time,
    }


def quality_flags(sample: CompassSample) -> dict[str, bool]:
    """The per-sample quality flags (all false where the source cannot tell)."""
    a = sample.attitude
    return {
        "saturated": sample.saturated,
        "degraded": bool(a is not None and a.degraded),
        "disturbed": bool(a is not None and a.disturbed),
        "accelerating": bool(a is not None and a.accelerating),
    }


def heading_doc(sample: CompassSample, times: SampleTimes) -> dict[str, Any]:
    """``<prefix>/heading``: magnetic and true heading, declination, quality flags, times."""
    heading, mag, true = sample.heading_deg, sample.heading_magnetic_deg, sample.heading_true_deg
    # The published heading is the magnetic or the true one, the same float object (the
    # engine and the heading-only path publish one of the two): rounded once. Identity, not
    # equality: -0.0 == 0.0, and they would not print alike.
    r = _r
    r_heading = r(heading, _ANGLE_DIGITS)
    # One dict display per document, in the published key order: a document is built for
    # every published sample, and growing a dict key by key resizes it on the way.
    return {
        **_sample_head(HEADING, sample, times),
        "source": sample.source,
        "heading_deg": r_heading,
        "heading_reference": sample.heading_reference,
        "heading_magnetic_deg": r_heading if mag is heading else r(mag, _ANGLE_DIGITS),
        "heading_true_deg": r_heading if true is heading else r(true, _ANGLE_DIGITS),
        "declination_deg": r(sample.declination_deg, _ANGLE_DIGITS),
        "device_heading_deg": r(sample.device_heading_deg, _ANGLE_DIGITS),
        "flags": quality_flags(sample),
        # where roll and pitch came from, and the heading error that tilt leaves
        "tilt": {
            "source": sample.tilt_source,
            "heading_error_deg": r(sample.heading_sigma_deg, _ANGLE_DIGITS),
        },
    }


def attitude_doc(sample: CompassSample, times: SampleTimes) -> dict[str, Any] | None:
    """``<prefix>/attitude``: roll, pitch, yaw and the body->NED quaternion.

    None when the sample has no pitch/roll (a heading-only sentence such as HDT).
    """
    a = sample.attitude
    if a is not None:
        roll, pitch = math.degrees(a.roll), math.degrees(a.pitch)
        q = a.quaternion
        degraded = a.degraded
    elif sample.pitch_deg is not None and sample.roll_deg is not None:
        from bridge.core.geometry import euler_to_quaternion  # numpy: only on this path

        roll, pitch = sample.roll_deg, sample.pitch_deg
        q = euler_to_quaternion(
            math.radians(roll), math.radians(pitch), math.radians(sample.heading_deg)
        )
        degraded = False
    else:
        return None
    w, x, y, z = q
    r = _r
    return {
        **_sample_head(ATTITUDE, sample, times),
        "source": sample.source,
        "roll_deg": r(roll, _ANGLE_DIGITS),
        "pitch_deg": r(pitch, _ANGLE_DIGITS),
        "yaw_deg": r(sample.heading_deg, _ANGLE_DIGITS),
        "yaw_reference": sample.heading_reference,
        "quaternion": {
            "w": r(w, _QUAT_DIGITS),
            "x": r(x, _QUAT_DIGITS),
            "y": r(y, _QUAT_DIGITS),
            "z": r(z, _QUAT_DIGITS),
        },
        "degraded": degraded,
    }


def raw_counts(sample: CompassSample) -> tuple[list[int] | None, list[int] | None]:
    """``(mag, accel)`` raw ADC counts of a GMR frame, or ``(None, None)`` without them."""
    rc = sample.raw_counts
    if rc is None:
        return None, None
    return [int(v) for v in rc[:3]], [int(v) for v in rc[3:]]


def imu_doc(sample: CompassSample, times: SampleTimes) -> dict[str, Any] | None:
    """``<prefix>/imu``: raw counts, calibrated field (gauss), acceleration (g).

    None for heading-only compasses (they send no vectors).
    """
    a = sample.attitude
    if a is None:
        return None
    raw_mag, raw_acc = raw_counts(sample)
    r = _r
    return {
        **_sample_head(IMU, sample, times),
        "raw": {"mag": raw_mag, "accel": raw_acc},
        "mag_G": _vec(a.mag_G, _FIELD_DIGITS),
        "accel_g": _vec(a.accel_g, _ACCEL_DIGITS),
        "field_strength_G": r(a.field_strength_G, _FIELD_DIGITS),
        "dip_deg": r(a.dip_deg, _ANGLE_DIGITS),
        "accel_norm_g": r(a.accel_norm_g, _ACCEL_DIGITS),
        "saturated": sample.saturated,
    }


#: The sensor streams' document builders, by key under the prefix, in the order they go out.
SENSOR_DOCS: Final = (("heading", heading_doc), ("attitude", attitude_doc), ("imu", imu_doc))


# ---------------------------------------------------------------------------
# Status, events, query answers
# ---------------------------------------------------------------------------


def counters_dict(c: LinkCounters) -> dict[str, Any]:
    """Link counters as JSON (bad lines by reason and their total)."""
    out: dict[str, Any] = {}
    for name in c.__dataclass_fields__:
        v = getattr(c, name)
        out[name] = dict(v) if isinstance(v, Mapping) else v
    out["bad_lines_total"] = c.bad_lines_total
    return out


def status_doc(
    status: DaemonStatus,
    *,
    frame_rate_hz: float | None,
    calibration: Mapping[str, Any],
    publisher: Mapping[str, Any],
    t_unix: float,
    uptime_s: float,
    tilt: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """``<prefix>/status``: link state, frame rate, counters, calibration state, and the
    tilt source's state (``tilt``: :meth:`bridge.app.tilt.TiltSources.status`, or None).

    ``calibration`` may carry ``drift`` (:func:`drift_detected` reads it): the drift
    monitor's ``mode``, ``state`` ("off", "uncalibrated", "collecting", "ok", "drift",
    "learning"),
    ``detected``, ``change_mG`` and ``offset_change_mG`` (body axes), ``heading_error_deg``,
    ``sigma_mG``, ``learned_mG`` and ``steps``.
    """
    doc = _head(STATUS)
    doc.update(
        {
            "t_unix": round(t_unix, 6),
            "uptime_s": round(uptime_s, 3),
            "link": {
                "port": status.port,
                "state": status.state.value,
                "frame_rate_hz": _r(frame_rate_hz, 2),
                "counters": counters_dict(status.counters),
            },
            "samples": status.samples,
            "pipeline_errors": status.pipeline_errors,
            "calibration": dict(calibration),
            # why params.json was last refused (retried; null: it was not)
            "parameters": {"save_error": status.parameters_error or None},
            "tilt": dict(tilt) if tilt else None,
            "zenoh": dict(publisher),
        }
    )
    return doc


def change_key(doc: Mapping[str, Any]) -> tuple[Any, ...]:
    """What makes a status *change* worth an immediate publication (not the counters):
    the link's state, the calibration's state and source."""
    cal = doc.get("calibration") or {}
    return (doc.get("link", {}).get("state"), cal.get("state"), cal.get("source"))


def drift_detected(doc: Mapping[str, Any]) -> bool:
    """A status document says the calibration has drifted (and it is not learned away yet)."""
    cal = doc.get("calibration")
    drift = cal.get("drift") if isinstance(cal, Mapping) else None
    return isinstance(drift, Mapping) and drift.get("detected") is True


def storage_refused(doc: Mapping[str, Any]) -> list[str]:
    """What a status document says storage refused: ``calibration`` (the one in use) and
    ``parameters`` (those set), each lost at a restart until it is saved."""
    return [
        part
        for part in ("calibration", "parameters")
        if isinstance(sub := doc.get(part), Mapping) and sub.get("save_error")
    ]


def event_doc(event: Event) -> dict[str, Any]:
    """``<prefix>/events``: one operator event (calibration, link, disturbance)."""
    doc = _head(EVENT)
    doc.update(
        {
            "kind": event.kind,
            "text": event.text,
            "severity": event.severity.name.lower(),
            "severity_level": int(event.severity),
            "data": _clean(dict(event.data)),
            "t_unix": round(event.t_unix, 6),
        }
    )
    return doc


def calibration_doc(
    calibration: Mapping[str, Any] | None,
    *,
    source: str,
    report: Mapping[str, Any] | None,
    state: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Answer of ``<prefix>/calibration``: the active parameters and their quality report."""
    doc = _head(CALIBRATION)
    doc.update(
        {
            "source": source,
            "calibration": _clean(dict(calibration)) if calibration is not None else None,
            "report": _clean(dict(report)) if report is not None else None,
            "state": _clean(dict(state)) if state is not None else None,
        }
    )
    return doc


def params_doc(params: Mapping[str, float | int]) -> dict[str, Any]:
    """Answer of ``<prefix>/params``: the bridge's parameter table, name -> value."""
    doc = _head(PARAMS)
    doc["params"] = {str(k): _clean(v) for k, v in params.items()}
    return doc


def command_result_doc(
    command: str, ok: bool, message: str, detail: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Reply of ``<prefix>/cmd/calibration/<command>``: the outcome."""
    doc = _head(COMMAND_RESULT)
    doc.update(
        {
            "command": command,
            "ok": ok,
            "message": message,
            "detail": _clean(dict(detail)) if detail is not None else None,
        }
    )
    return doc


# ---------------------------------------------------------------------------
# Validation (consumers: monitor, tests)
# ---------------------------------------------------------------------------


class SchemaError(ValueError):
    """A document that does not match its schema."""


_NUM = (int, float)
_OPT_NUM = (int, float, type(None))
_OPT_INT = (int, type(None))
_OPT_STR = (str, type(None))
_OPT_DICT = (dict, type(None))

#: schema -> required field -> accepted JSON types (bool is excluded from numbers below).
FIELDS: Final[Mapping[str, Mapping[str, tuple[type, ...]]]] = {
    HEADING: {
        "seq": _OPT_INT,
        "t_monotonic": _NUM,
        "t_unix": _NUM,
        "zenoh_time": _OPT_STR,
        "source": (str,),
        "heading_deg": _NUM,
        "heading_reference": (str,),
        "heading_magnetic_deg": _OPT_NUM,
        "heading_true_deg": _OPT_NUM,
        "declination_deg": _OPT_NUM,
        "device_heading_deg": _OPT_NUM,
        "flags": (dict,),
    },
    ATTITUDE: {
        "seq": _OPT_INT,
        "t_monotonic": _NUM,
        "t_unix": _NUM,
        "zenoh_time": _OPT_STR,
        "source": (str,),
        "roll_deg": _NUM,
        "pitch_deg": _NUM,
        "yaw_deg": _NUM,
        "yaw_reference": (str,),
        "quaternion": (dict,),
        "degraded": (bool,),
    },
    IMU: {
        "seq": _OPT_INT,
        "t_monotonic": _NUM,
        "t_unix": _NUM,
        "zenoh_time": _OPT_STR,
        "raw": (dict,),
        "mag_G": (list,),
        "accel_g": (list,),
        "field_strength_G": _OPT_NUM,
        "dip_deg": _OPT_NUM,
        "accel_norm_g": _OPT_NUM,
        "saturated": (bool,),
    },
    STATUS: {
        "t_unix": _NUM,
        "uptime_s": _NUM,
        "link": (dict,),
        "samples": (int,),
        "pipeline_errors": (int,),
        "calibration": (dict,),
        "zenoh": (dict,),
    },
    EVENT: {
        "kind": (str,),
        "text": (str,),
        "severity": (str,),
        "severity_level": (int,),
        "data": (dict,),
        "t_unix": _NUM,
    },
    CALIBRATION: {
        "source": (str,),
        "calibration": _OPT_DICT,
        "report": _OPT_DICT,
        "state": _OPT_DICT,
    },
    PARAMS: {"params": (dict,)},
    COMMAND_RESULT: {
        "command": (str,),
        "ok": (bool,),
        "message": (str,),
        "detail": _OPT_DICT,
    },
}

_ANGLE_RANGES: Final[Mapping[str, Mapping[str, tuple[float, float]]]] = {
    HEADING: {
        "heading_deg": (0.0, 360.0),
        "heading_magnetic_deg": (0.0, 360.0),
        "heading_true_deg": (0.0, 360.0),
        "declination_deg": (-180.0, 180.0),
    },
    ATTITUDE: {
        "roll_deg": (-180.0, 180.0),
        "pitch_deg": (-90.0, 90.0),
        "yaw_deg": (0.0, 360.0),
    },
}

_FLAG_NAMES: Final = ("saturated", "degraded", "disturbed", "accelerating")


def _type_ok(v: Any, types: tuple[type, ...]) -> bool:
    # JSON booleans are Python bools, which are ints: a number field must not accept them.
    if isinstance(v, bool):
        return bool in types
    return isinstance(v, types)


def validate(doc: Any, expect: str | None = None) -> tuple[str, int]:
    """Check a decoded document; returns ``(schema, version)`` or raises :class:`SchemaError`.

    ``expect`` names the schema the key promises (e.g. ``<prefix>/heading``).
    A newer version than this code knows is refused: its fields may mean
    something else.
    """
    if not isinstance(doc, dict):
        raise SchemaError(f"not a JSON object: {type(doc).__name__}")
    schema, version = doc.get("schema"), doc.get("version")
    if not isinstance(schema, str) or schema not in FIELDS:
        raise SchemaError(f"unknown schema {schema!r}")
    if expect is not None and schema != expect:
        raise SchemaError(f"expected schema {expect}, got {schema}")
    if not isinstance(version, int) or isinstance(version, bool) or version != VERSIONS[schema]:
        raise SchemaError(f"{schema}: unsupported version {version!r} (know {VERSIONS[schema]})")
    for name, types in FIELDS[schema].items():
        if name not in doc:
            raise SchemaError(f"{schema}: missing field {name!r}")
        if not _type_ok(doc[name], types):
            raise SchemaError(
                f"{schema}: field {name!r} has type {type(doc[name]).__name__}, "
                f"want {'/'.join(t.__name__ for t in types)}"
            )
    for name, (lo, hi) in _ANGLE_RANGES.get(schema, {}).items():
        v = doc[name]
        if v is not None and not lo <= v <= hi:
            raise SchemaError(f"{schema}: {name} = {v} outside [{lo:g}, {hi:g}]")
    if schema == HEADING:
        flags = doc["flags"]
        for f in _FLAG_NAMES:
            if not isinstance(flags.get(f), bool):
                raise SchemaError(f"{schema}: flags.{f} missing or not a boolean")
    if schema == ATTITUDE:
        q = doc["quaternion"]
        parts = [q.get(k) for k in "wxyz"]
        if not all(_type_ok(p, _NUM) for p in parts):
            raise SchemaError(f"{schema}: quaternion needs numeric w, x, y, z")
        norm = math.sqrt(sum(float(p) ** 2 for p in parts))
        if abs(norm - 1.0) > 1e-3:
            raise SchemaError(f"{schema}: quaternion norm {norm:.6f} is not 1")
    if schema == IMU:
        for name in ("mag_G", "accel_g"):
            vec = doc[name]
            if len(vec) != 3 or not all(_type_ok(x, _OPT_NUM) for x in vec):
                raise SchemaError(f"{schema}: {name} must be 3 numbers")
        for name in ("mag", "accel"):
            raw = doc["raw"].get(name)
            if raw is not None and (
                len(raw) != 3 or not all(_type_ok(x, (int,)) and 0 <= x <= 4095 for x in raw)
            ):
                raise SchemaError(f"{schema}: raw.{name} must be 3 counts in 0..4095")
    if schema == STATUS:
        link = doc["link"]
        if not isinstance(link.get("state"), str) or not isinstance(link.get("counters"), dict):
            raise SchemaError(f"{schema}: link.state / link.counters missing")
    return schema, version


def parse(payload: bytes, expect: str | None = None) -> dict[str, Any]:
    """Decode and validate a payload; raises :class:`SchemaError` (bad JSON included)."""
    try:
        doc = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SchemaError(f"not JSON: {e}") from None
    validate(doc, expect)
    assert isinstance(doc, dict)  # validate() checked it
    return doc
