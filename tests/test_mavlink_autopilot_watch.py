"""The autopilot beside a companion bridge, as the MAVLink output sees it.

* the heading feed is withheld exactly when the autopilot has the bridge's own system
  *and* component id (ArduPilot drops those: ``MAVLink_routing::check_and_forward``),
  shown on a running bridge with stand-in autopilot HEARTBEATs;
* the generic requester of messages the companion needs (SET_MESSAGE_INTERVAL, and
  REQUEST_DATA_STREAM for ArduPilot), in memory;
* the heading guard: a heading step refused only while an armed ArduPilot is fed.

The real autopilots: test_autopilot_ardupilot.py, test_autopilot_px4.py.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from test_mavlink_rig import M, Rig

from bridge.app.settings import EngineSettings
from bridge.core.attitude import AttitudeEngine
from bridge.core.mounting import Mounting, Rotation
from bridge.core.wmm import earth_field
from bridge.events import ChangeRefusedError, EventBus
from bridge.mavlink import autopilot as AP  # noqa: N812 - short


def _heartbeat(mav: Any, armed: bool = False) -> Any:
    return mav.heartbeat_encode(
        M.MAV_TYPE_GROUND_ROVER,
        M.MAV_AUTOPILOT_ARDUPILOTMEGA,
        M.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0,
        0,
        M.MAV_STATE_STANDBY,
    )


def _feeds(g: Any, seconds: float) -> int:
    return sum(m.get_type() == "VISION_POSITION_ESTIMATE" for m in g.collect(seconds))


@pytest.mark.integration
@pytest.mark.parametrize(
    ("role", "system_id", "autopilot", "withheld"),
    [
        ("standalone", 1, (1, 1), True),  # the autopilot's own ids: it would drop them
        ("standalone", 2, (2, 1), True),
        ("standalone", 2, (1, 1), False),  # another system: ArduPilot takes it
        ("companion", 1, (1, 1), False),  # component 200
    ],
)
def test_the_feed_is_withheld_only_from_an_autopilot_with_our_ids(
    tmp_path: Path,
    rigs: Callable[..., Rig],
    role: str,
    system_id: int,
    autopilot: tuple[int, int],
    withheld: bool,
) -> None:
    rig = rigs(
        tmp_path,
        ideal=True,
        mavlink={"heading_feed": "ardupilot_vision", "role": role, "system_id": system_id},
    )
    g = rig.gcs("udp")
    assert _feeds(g, 1.0) >= 5  # before the autopilot is heard
    ap = M.MAVLink(None, srcSystem=autopilot[0], srcComponent=autopilot[1])
    g.conn.write(_heartbeat(ap).pack(ap))
    deadline = time.monotonic() + 5.0
    while rig.out.autopilot.target is None and time.monotonic() < deadline:
        time.sleep(0.02)
    heard = rig.out.autopilot.target
    if autopilot[0] != system_id:
        assert heard is None  # another system's autopilot is not ours to watch
    else:
        assert heard == autopilot
    g.flush()
    n = _feeds(g, 1.5)
    assert (n == 0) if withheld else (n >= 10), n


def test_missing_messages_are_asked_for_as_ground_stations_do() -> None:
    req = AP.StreamRequests()
    pos = AP.POSITION
    req.want(pos.msgid, pos.hz, pos.ardupilot_stream)
    # the one line another message takes (the autopilot's attitude)
    req.want(M.MAVLINK_MSG_ID_ATTITUDE, 10.0, M.MAV_DATA_STREAM_EXTRA1)
    assert set(req.wanted) == {pos.msgid, M.MAVLINK_MSG_ID_ATTITUDE}
    target = (1, 1)
    assert req.due(2.9, 0.0, target, ardupilot=True) == []  # not yet: a grace period
    req.heard(M.MAVLINK_MSG_ID_ATTITUDE, 2.0)
    first = req.due(3.1, 0.0, target, ardupilot=True)
    kinds = [
        (m.get_type(), getattr(m, "param1", None), getattr(m, "req_stream_id", None)) for m in first
    ]
    assert kinds == [
        ("COMMAND_LONG", float(pos.msgid), None),
        ("REQUEST_DATA_STREAM", None, M.MAV_DATA_STREAM_POSITION),
    ]
    assert first[0].command == M.MAV_CMD_SET_MESSAGE_INTERVAL and first[0].param2 == 1e6
    assert first[1].req_message_rate == 1 and first[1].start_stop == 1
    assert req.due(4.0, 0.0, target, ardupilot=True) == []  # asked again only every 5 s
    # ATTITUDE stopped coming too; PX4 gets SET_MESSAGE_INTERVAL only
    again = req.due(8.2, 0.0, target, ardupilot=False)
    assert [m.get_type() for m in again] == ["COMMAND_LONG", "COMMAND_LONG"]
    req.heard(pos.msgid, 8.5)
    req.heard(M.MAVLINK_MSG_ID_ATTITUDE, 8.5)
    assert req.due(9.0, 0.0, target, ardupilot=False) == []
    # bounded: at most REQUEST_TRIES rounds while it never comes
    quiet = AP.StreamRequests((pos,))
    sent = sum(len(quiet.due(float(t), 0.0, target, False)) for t in range(3, 200))
    assert sent == AP.REQUEST_TRIES
    with pytest.raises(ValueError):
        quiet.want(1, 0.0, 0)


def _watch(
    flavour: int, armed: bool, feed: int = AP.FEED_ARDUPILOT
) -> tuple[AP.AutopilotWatch, EventBus, list[Any]]:
    events = EventBus()
    seen: list[Any] = []
    events.subscribe(seen.append)
    now = [100.0]
    w = AP.AutopilotWatch((1, 200), lambda: feed, events, lambda: now[0])
    mav = M.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.heartbeat_encode(
        M.MAV_TYPE_GROUND_ROVER, flavour, M.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0, 0, 0
    )
    msg = M.MAVLink(None).parse_char(hb.pack(mav))
    sent: list[Any] = []
    w.heard(msg, sent.append)
    return w, events, seen


def test_heading_steps_are_refused_only_while_an_armed_ardupilot_is_fed() -> None:
    w, _, seen = _watch(M.MAV_AUTOPILOT_ARDUPILOTMEGA, armed=True)
    reason = w.guard("mounting", "parameters")
    assert "armed" in reason and "disarm" in reason
    assert [e.kind for e in seen] == ["mavlink.heading_change_refused"]
    assert w.guard("calibration", "learned")  # refused again, told once per 30 s
    assert len(seen) == 1
    for flavour, armed, feed in (
        (M.MAV_AUTOPILOT_ARDUPILOTMEGA, False, AP.FEED_ARDUPILOT),
        (M.MAV_AUTOPILOT_PX4, True, 1),
        (M.MAV_AUTOPILOT_ARDUPILOTMEGA, True, 0),
    ):
        other, _, _ = _watch(flavour, armed, feed)
        assert other.guard("mounting", "parameters") == ""


def test_a_refused_change_leaves_the_settings_as_they_were() -> None:
    settings = EngineSettings(AttitudeEngine(), field=earth_field(47.4, 8.5))
    before = (settings.mounting, settings.reference, settings.calibration)
    remove = settings.add_guard(lambda aspect, source: f"no {aspect} now")
    with pytest.raises(ChangeRefusedError, match="no mounting now"):
        settings.set_mounting(Mounting(orientation=Rotation.ROTATION_YAW_90), "test")
    with pytest.raises(ChangeRefusedError, match="no reference now"):
        settings.set_declination(30.0, "test")
    with pytest.raises(ChangeRefusedError, match="no reference now"):
        settings.set_position(-35.36, 149.16, 584.0, "autopilot position")
    assert (settings.mounting, settings.reference, settings.calibration) == before
    # a declination that moves less than REFERENCE_STEP_DEG is no heading step
    settings.set_position(47.6, 8.7, 0.0, "autopilot position")
    assert settings.reference != before[1]
    remove()
    settings.set_declination(30.0, "test")
    assert settings.reference is not None and settings.reference.declination_deg == 30.0
