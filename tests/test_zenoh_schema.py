"""The pure parts of the Zenoh adapter: documents, validation, pacing, session config, MAVLink mirror.

Expected values come from the inputs (an ideal simulated unit at a known
attitude, hand-built samples), never from the code's own output.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.app.sample import CompassSample, DaemonStatus
from bridge.config import ConfigError, load_config
from bridge.core.attitude import AttitudeEngine, FieldReference
from bridge.core.calibration import Calibration
from bridge.core.geometry import euler_to_dcm, quaternion_to_dcm
from bridge.events import Event, Severity
from bridge.link.serial_link import LinkCounters, LinkState
from bridge.sim.physics import SensorModel, UnitErrors
from bridge.zenoh import schema
from bridge.zenoh.mirror import MirrorMessage, mirror_key
from bridge.zenoh.pacing import Decimator, RateMeter
from bridge.zenoh.session import (
    CONNECT_RETRY,
    DEFAULT_LISTEN,
    ZenohSettings,
    build_config,
    config_items,
    uses_default_listener,
)

FIELD_NED_G = (0.21, 0.02, 0.43)
TIMES = schema.SampleTimes(t_monotonic=12.5, t_unix=1_700_000_000.25, zenoh_time="t/zid")


def host_sample(roll_deg: float, pitch_deg: float, yaw_deg: float) -> CompassSample:
    """A GMR sample of an ideal unit at a known attitude, through the real engine."""
    model = SensorModel(UnitErrors.ideal(), FIELD_NED_G)
    R = euler_to_dcm(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    s = model.sample(R, np.random.default_rng(0))
    (mx, my, mz), (ax, ay, az) = s.mag_counts[0], s.acc_counts[0]
    ref = FieldReference(declination_deg=5.0)
    a = AttitudeEngine(Calibration(), reference=ref).solve_counts(mx, my, mz, ax, ay, az)
    return CompassSample.from_solution(a, 12.5, seq=7, device_heading_deg=101.5)


def test_heading_document_carries_both_norths_and_declination() -> None:
    s = host_sample(0.0, 0.0, 100.0)
    doc = schema.parse(schema.dumps(schema.heading_doc(s, TIMES)), schema.HEADING)
    # The field points 5.4 deg east of north (atan2(0.02, 0.21)) on an ideal unit.
    expected_mag = (100.0 - math.degrees(math.atan2(0.02, 0.21))) % 360
    assert doc["heading_magnetic_deg"] == pytest.approx(expected_mag, abs=0.3)
    assert doc["heading_true_deg"] == pytest.approx((expected_mag + 5.0) % 360, abs=0.3)
    assert doc["declination_deg"] == 5.0
    assert doc["heading_reference"] == "magnetic"
    assert doc["heading_deg"] == doc["heading_magnetic_deg"]
    assert doc["seq"] == 7 and doc["device_heading_deg"] == 101.5
    assert doc["t_monotonic"] == 12.5 and doc["t_unix"] == 1_700_000_000.25
    assert doc["zenoh_time"] == "t/zid"
    assert doc["flags"] == {
        "saturated": False,
        "degraded": False,
        "disturbed": False,
        "accelerating": False,
    }


def test_attitude_quaternion_matches_the_euler_angles() -> None:
    s = host_sample(10.0, -20.0, 250.0)
    doc = schema.parse(schema.dumps(schema.attitude_doc(s, TIMES) or {}), schema.ATTITUDE)
    assert doc["roll_deg"] == pytest.approx(10.0, abs=0.5)
    assert doc["pitch_deg"] == pytest.approx(-20.0, abs=0.5)
    q = doc["quaternion"]
    R = quaternion_to_dcm([q["w"], q["x"], q["y"], q["z"]])
    # The quaternion's rotation is the published attitude (yaw = published heading).
    want = euler_to_dcm(
        math.radians(doc["roll_deg"]), math.radians(doc["pitch_deg"]), math.radians(doc["yaw_deg"])
    )
    assert np.allclose(R, want, atol=1e-4)


def test_heading_only_sentence_gets_attitude_from_its_angles_and_no_imu() -> None:
    s = CompassSample(
        t=3.0,
        source="device",
        heading_deg=45.0,
        heading_reference="true",
        heading_magnetic_deg=None,
        heading_true_deg=45.0,
        declination_deg=None,
        pitch_deg=2.0,
        roll_deg=-3.0,
    )
    a = schema.parse(schema.dumps(schema.attitude_doc(s, TIMES) or {}), schema.ATTITUDE)
    q = a["quaternion"]
    R = quaternion_to_dcm([q["w"], q["x"], q["y"], q["z"]])
    assert np.allclose(
        R, euler_to_dcm(math.radians(-3), math.radians(2), math.radians(45)), atol=1e-5
    )
    assert schema.imu_doc(s, TIMES) is None
    h = schema.parse(schema.dumps(schema.heading_doc(s, TIMES)), schema.HEADING)
    assert h["heading_magnetic_deg"] is None and h["seq"] is None
    # Without pitch/roll (HDT) there is no attitude at all.
    bare = CompassSample(3.0, "device", 45.0, "true", None, 45.0, None, None, None)
    assert schema.attitude_doc(bare, TIMES) is None


def test_imu_document_units() -> None:
    s = host_sample(0.0, 0.0, 0.0)
    doc = schema.parse(schema.dumps(schema.imu_doc(s, TIMES) or {}), schema.IMU)
    # Level ideal unit: gravity vector (0, 0, +1) g; the field in gauss as given.
    assert doc["accel_g"] == pytest.approx([0.0, 0.0, 1.0], abs=0.01)
    assert doc["mag_G"] == pytest.approx(list(FIELD_NED_G), abs=0.002)
    assert doc["field_strength_G"] == pytest.approx(math.dist((0, 0, 0), FIELD_NED_G), abs=0.002)


def test_non_finite_numbers_become_null() -> None:
    raw = schema.dumps({"a": math.nan, "b": [1.0, math.inf], "c": {"d": -math.inf}})
    assert json.loads(raw) == {"a": None, "b": [1.0, None], "c": {"d": None}}


def test_status_and_event_documents() -> None:
    counters = LinkCounters(frames=10, attitude_frames=9, bad_lines={"checksum": 2, "range": 1})
    st = DaemonStatus("sim", LinkState.STALE, counters, 9, 0, "stored")
    doc = schema.status_doc(
        st,
        frame_rate_hz=None,
        calibration={"state": "idle"},
        publisher={"published": {}},
        t_unix=5.0,
        uptime_s=1.0,
    )
    doc = schema.parse(schema.dumps(doc), schema.STATUS)
    assert doc["link"]["state"] == "stale"
    assert doc["parameters"] == {"save_error": None}  # params.json took them
    refused = DaemonStatus("sim", LinkState.STALE, counters, 9, 0, "stored", "disk full")
    doc2 = schema.status_doc(
        refused, frame_rate_hz=None, calibration={}, publisher={}, t_unix=5.0, uptime_s=1.0
    )
    assert schema.parse(schema.dumps(doc2), schema.STATUS)["parameters"] == {
        "save_error": "disk full"
    }
    assert schema.storage_refused(doc) == [] and schema.storage_refused(doc2) == ["parameters"]
    doc2["calibration"] = {"save_error": "disk full"}
    assert schema.storage_refused(doc2) == ["calibration", "parameters"]
    assert doc["link"]["counters"]["bad_lines_total"] == 3
    assert doc["link"]["counters"]["bad_lines"] == {"checksum": 2, "range": 1}
    ev = Event("link.lost", "Compass link lost", Severity.WARNING, {"x": math.nan}, 1.0, 2.0)
    e = schema.parse(schema.dumps(schema.event_doc(ev)), schema.EVENT)
    assert (e["kind"], e["severity"], e["severity_level"], e["data"]) == (
        "link.lost",
        "warning",
        4,
        {"x": None},
    )


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("heading_deg"), "missing field"),
        (lambda d: d.update(heading_deg="12"), "has type str"),
        (lambda d: d.update(heading_deg=True), "has type bool"),
        (lambda d: d.update(heading_deg=360.5), "outside"),
        (lambda d: d.update(version=2), "unsupported version"),
        (lambda d: d.update(schema="compass-bridge/nope"), "unknown schema"),
        (lambda d: d["flags"].pop("disturbed"), "flags.disturbed"),
    ],
)
def test_validation_refuses_bad_heading_documents(
    mutate: Callable[[dict[str, Any]], object], message: str
) -> None:
    doc = schema.heading_doc(host_sample(0, 0, 10), TIMES)
    mutate(doc)
    with pytest.raises(schema.SchemaError, match=message):
        schema.validate(json.loads(schema.dumps(doc)))


def test_validation_refuses_a_non_unit_quaternion_and_bad_raw_counts() -> None:
    doc = schema.attitude_doc(host_sample(0, 0, 10), TIMES)
    assert doc is not None
    doc["quaternion"]["w"] = 2.0
    with pytest.raises(schema.SchemaError, match="norm"):
        schema.validate(doc)
    imu = schema.imu_doc(host_sample(0, 0, 10), TIMES)
    assert imu is not None
    imu["raw"]["mag"] = [1, 2, 5000]
    with pytest.raises(schema.SchemaError, match=r"0\.\.4095"):
        schema.validate(imu)
    with pytest.raises(schema.SchemaError, match="not JSON"):
        schema.parse(b"{nope")
    with pytest.raises(schema.SchemaError, match="expected schema"):
        schema.parse(schema.dumps(schema.heading_doc(host_sample(0, 0, 1), TIMES)), schema.IMU)


def test_encoding_names_schema_and_version() -> None:
    text = schema.encoding_text(schema.HEADING)
    assert text == "application/json;compass-bridge/heading@1"
    assert schema.schema_from_encoding(text) == (schema.HEADING, 1)
    assert schema.schema_from_encoding("application/json") is None
    assert schema.schema_from_encoding("text/plain;compass-bridge/heading@1") is None
    assert schema.schema_from_encoding("application/json;other/thing@1") is None


# ---------------------------------------------------------------------------
# Pacing
# ---------------------------------------------------------------------------


def test_decimator_keeps_the_asked_rate_despite_jitter() -> None:
    rng = np.random.default_rng(3)
    d = Decimator(10.0)
    # 20 Hz frames with +-4 ms arrival jitter over 10 s.
    times = np.arange(200) * 0.05 + rng.uniform(-0.004, 0.004, 200)
    accepted = [t for t in times if d.accept(float(t))]
    assert len(accepted) == pytest.approx(100, abs=2)
    assert min(np.diff(accepted)) > 0.07  # never two in one period


def test_decimator_zero_passes_everything_and_restarts_after_a_gap() -> None:
    assert all(Decimator(0.0).accept(t) for t in (0.0, 0.0, 0.001))
    d = Decimator(1.0)
    assert d.accept(0.0) and not d.accept(0.5) and d.accept(1.0)
    assert d.accept(10.0)  # after a long gap the next sample goes out at once...
    assert not d.accept(10.5)  # ...and the schedule restarts from it (no burst)
    with pytest.raises(ValueError):
        Decimator(-1.0)


_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(), inner, max_size=4),
    max_leaves=20,
)


@examples(100)  # Hypothesis's default count, a third of it everyday
@given(_JSON)
def test_dumps_writes_what_json_dumps_writes(doc: object) -> None:
    """The encoder made once (CPython's C encoder, see schema._make_encode) is json.dumps
    (non-finite numbers aside: test_non_finite_numbers_become_null)."""
    expected = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    assert schema.dumps(doc) == expected  # type: ignore[arg-type]  # any JSON value, not only documents


def test_dumps_refuses_what_json_cannot_carry() -> None:
    with pytest.raises(TypeError):
        schema.dumps({"a": object()})


def test_rate_meter_follows_the_counter() -> None:
    m = RateMeter(window=2.0)
    assert m.rate() is None
    for i in range(50):
        m.add(i * 0.1, i * 2)  # 20 per second
    assert m.rate() == pytest.approx(20.0)
    m.add(5.1, 0)  # the counter restarted (a new link): no negative rate
    assert m.rate() is None
    m.add(6.1, 10)
    assert m.rate() == pytest.approx(10.0)


# ---------------------------------------------------------------------------
# Session configuration
# ---------------------------------------------------------------------------


def _items(settings: ZenohSettings, **kw: Any) -> dict[str, Any]:
    return {k: json.loads(v) for k, v in config_items(settings, **kw)}


def test_defaults_listen_on_loopback_without_multicast_and_rejoin_fast() -> None:
    items = _items(ZenohSettings())
    assert items["mode"] == "peer"
    assert items["scouting/multicast/enabled"] is False
    assert items["listen/endpoints"] == list(DEFAULT_LISTEN)
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in items["listen/endpoints"])
    assert items["connect/retry"] == dict(CONNECT_RETRY)
    assert items["connect/retry"]["period_max_ms"] <= 1000
    assert items["connect/exit_on_failure"] is False


def test_client_never_listens_and_explicit_endpoints_win() -> None:
    assert "listen/endpoints" not in _items(ZenohSettings(mode="client"))
    items = _items(ZenohSettings(connect=("tcp/10.0.0.1:7447",), listen=("tcp/10.0.0.2:7448",)))
    assert items["connect/endpoints"] == ["tcp/10.0.0.1:7447"]
    assert items["listen/endpoints"] == ["tcp/10.0.0.2:7448"]
    assert _items(ZenohSettings(), with_default_listener=False)["listen/endpoints"] == []
    assert _items(ZenohSettings(multicast_scouting=True))["scouting/multicast/enabled"] is True


def test_shared_memory_is_off_unless_a_config_file_turns_it_on(tmp_path: Path) -> None:
    # Off: zenoh's SHM handoff task would wake its net thread 20 times a second.
    assert _items(ZenohSettings())["transport/shared_memory/enabled"] is False
    assert _items(ZenohSettings(mode="client"))["transport/shared_memory/enabled"] is False
    cfg = build_config(ZenohSettings())
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    f = tmp_path / "zenoh.json5"
    f.write_text("{ transport: { shared_memory: { enabled: true } } }")
    cfg = build_config(ZenohSettings(config_file=str(f)))
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is True


def test_a_config_file_passes_through_and_keeps_what_it_sets(tmp_path: Path) -> None:
    f = tmp_path / "zenoh.json5"
    f.write_text(
        """{
          // a user's file: its own retry and listener, plus access control
          connect: { retry: { period_init_ms: 5000 } },
          listen: { endpoints: ["tcp/127.0.0.1:17447"] },
          access_control: { enabled: true, default_permission: "allow",
                            rules: [], subjects: [], policies: [] },
        }"""
    )
    cfg = build_config(ZenohSettings(config_file=str(f)))

    def get(key: str) -> Any:  # a JSON value
        return json.loads(cfg.get_json(key))

    assert get("listen/endpoints") == ["tcp/127.0.0.1:17447"]
    assert get("connect/retry")["period_init_ms"] == 5000
    assert get("access_control")["enabled"] is True
    assert get("scouting/multicast/enabled") is False  # our key still applies
    assert get("transport/shared_memory/enabled") is False  # the file names no SHM
    assert not uses_default_listener(ZenohSettings(config_file=str(f)), cfg)
    plain = ZenohSettings()
    assert uses_default_listener(plain, build_config(plain))


def test_import_zenoh_inside_the_adapter_is_the_library() -> None:
    """The adapter's package is named bridge.zenoh; imports are absolute, so ``import zenoh``
    inside it is Eclipse Zenoh: the configuration it builds is the library's."""
    import zenoh

    import bridge.zenoh

    assert zenoh is not bridge.zenoh and zenoh.__name__ == "zenoh"
    assert isinstance(build_config(ZenohSettings()), zenoh.Config)


def test_settings_from_config_substitute_the_host_name() -> None:
    cfg = load_config(None, ["zenoh.connect=['tcp/127.0.0.1:7447']"], env={}, hostname="boat7")
    st = ZenohSettings.from_config(cfg.zenoh)
    assert st.key_prefix == "fleet/boat7/compass"
    assert st.key("heading") == "fleet/boat7/compass/heading"
    assert st.connect == ("tcp/127.0.0.1:7447",)
    with pytest.raises(ValueError, match="mode"):
        ZenohSettings(mode="router")


def test_new_zenoh_keys_are_validated_at_load(tmp_path: Path) -> None:
    cfg = load_config(
        None,
        [
            "zenoh.heading_rate_hz=5",
            "zenoh.remote_calibration=true",
            "zenoh.mavlink_mirror=true",
            "zenoh.multicast_scouting=true",
        ],
        env={},
        hostname="h",
    )
    st = ZenohSettings.from_config(cfg.zenoh)
    # The streams not set keep the default cap (10 Hz, MAVLink's default ATTITUDE rate).
    assert (st.heading_rate_hz, st.attitude_rate_hz, st.imu_rate_hz) == (5.0, 10.0, 10.0)
    assert st.remote_calibration and st.mavlink_mirror and st.multicast_scouting
    with pytest.raises(ConfigError, match="does not exist") as e:
        load_config(None, [f"zenoh.config_file={tmp_path / 'nope.json5'}"], env={})
    assert e.value.key == "zenoh.config_file"
    with pytest.raises(ConfigError, match=r"\[0, 100\]"):
        load_config(None, ["zenoh.imu_rate_hz=500"], env={})


# ---------------------------------------------------------------------------
# MAVLink mirror (bluerobotics/mavlink-server layout)
# ---------------------------------------------------------------------------


def test_mirror_uses_the_mavlink_server_layout() -> None:
    hb = MirrorMessage.from_fields(
        0,
        {
            "type": 18,  # MAV_TYPE_ONBOARD_CONTROLLER
            "autopilot": 8,  # MAV_AUTOPILOT_INVALID
            "base_mode": 0b1000_0001,
            "custom_mode": 0,
            "system_status": 4,  # MAV_STATE_ACTIVE
            "mavlink_version": 3,
        },
        system_id=1,
        component_id=200,
        sequence=9,
    )
    assert mirror_key(hb) == "mavlink/1/200/HEARTBEAT"
    doc = json.loads(hb.to_json())
    assert doc["header"] == {"system_id": 1, "component_id": 200, "sequence": 9, "message_id": 0}
    m = doc["message"]
    assert m["type"] == "HEARTBEAT"
    assert m["mavtype"] == {"type": "MAV_TYPE_ONBOARD_CONTROLLER"}  # rust-mavlink's rename
    assert m["autopilot"] == {"type": "MAV_AUTOPILOT_INVALID"}
    assert m["base_mode"] == {"bits": 129}
    assert m["system_status"] == {"type": "MAV_STATE_ACTIVE"}

    att = MirrorMessage.from_fields(
        30,
        dict.fromkeys(("roll", "pitch", "yaw", "rollspeed", "pitchspeed"), 0.5)
        | {"yawspeed": math.nan, "time_boot_ms": 10},
        system_id=1,
        component_id=1,
    )
    a = json.loads(att.to_json())["message"]
    assert a["type"] == "ATTITUDE" and a["roll"] == 0.5 and a["yawspeed"] is None
    st = MirrorMessage.from_fields(
        253,
        {"severity": 4, "text": b"Compass link lost\0\0", "id": 0, "chunk_seq": 0},
        system_id=1,
        component_id=1,
    )
    s = json.loads(st.to_json())["message"]
    assert s["text"] == "Compass link lost"
    assert s["severity"] == {"type": "MAV_SEVERITY_WARNING"}


def test_mirror_decodes_the_bridges_own_encoded_packets() -> None:
    from bridge.mavlink.dialect import Message, mavlink, message

    def payload(msg: Message) -> bytes:
        msg.pack(mavlink.MAVLink(None, 1, 1))
        return bytes(msg.get_payload())

    q = [0.5, 0.5, -0.5, 0.5]
    p = message(
        61,  # ATTITUDE_QUATERNION_COV: an array of 4 and one of 9
        time_usec=123456789,
        q=q,
        rollspeed=0.0,
        pitchspeed=0.25,
        yawspeed=0.0,
        covariance=[1.5, 2.5] + [0.0] * 7,  # ends in zeros: MAVLink 2 trims them
    )
    data = payload(p)
    assert len(data) < 72  # trailing zeros were trimmed (MAVLink 2)
    m = MirrorMessage.from_packet(61, data, system_id=3, component_id=200, sequence=5)
    doc = json.loads(m.to_json())
    assert mirror_key(m) == "mavlink/3/200/ATTITUDE_QUATERNION_COV"
    assert doc["message"]["q"] == q and doc["message"]["time_usec"] == 123456789
    assert doc["message"]["covariance"] == [1.5, 2.5] + [0.0] * 7
    t = message(253, severity=6, text=b"Calibration started: mag", id=0, chunk_seq=0)
    s = json.loads(
        MirrorMessage.from_packet(253, payload(t), system_id=1, component_id=1).to_json()
    )
    assert s["message"]["text"] == "Calibration started: mag"
    assert s["message"]["severity"] == {"type": "MAV_SEVERITY_INFO"}
    with pytest.raises(ValueError):
        MirrorMessage.from_packet(253, bytes(100), system_id=1, component_id=1)


@examples(100)  # Hypothesis's default count, a third of it everyday
@given(
    rate=st.sampled_from([0.0, 1.0, 10.0, 20.0, 100.0]),
    gaps=st.lists(st.floats(0.0, 0.5), min_size=1, max_size=60),
)
def test_decimator_opens_at_is_exactly_when_accept_says_yes(rate: float, gaps: list[float]) -> None:
    """The zenoh output skips a frame on ``t < opens_at`` without asking the decimator:
    that must be the same answer accept() gives, at every step of any schedule."""
    d, probe = Decimator(rate), Decimator(rate)
    t = 100.0
    for gap in gaps:
        t += gap
        probe._due = d._due  # the same state, asked without side effects on d
        assert probe.accept(t) == (t >= d.opens_at)
        d.accept(t)
