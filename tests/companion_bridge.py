"""A bridge beside a real autopilot, for the autopilot tests: :func:`start_bridge` runs a
companion bridge daemon in this process (a simulated compass lying still, in real time)
that feeds its heading to the autopilot; :class:`HeadingRecorder` keeps what it published,
and :func:`mean_heading` / :func:`overshoot_deg` compare the autopilot's yaw with it.

What a ground station asks of the bridge through the autopilot's router --
QGroundControl's parameter load (:func:`load_parameters`), a storm of
GET_MESSAGE_INTERVAL (:func:`message_interval_storm`) -- is asked the same way of both
autopilots. The autopilots themselves are started by tests/autopilots.py.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from autopilots import DEADLINE_S, M, Observer


class HeadingRecorder:
    """An output that keeps every sample's true heading with its wall-clock time: the
    bridge's heading to compare the autopilot's yaw with."""

    name = "recorder"
    due_at = -math.inf  # every sample as it comes (the compass link reads no bursts for it)

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.samples: list[tuple[float, float]] = []  #: (unix time, true heading deg)

    def start(self) -> None:
        """Nothing to start."""

    def publish(self, sample: Any) -> None:
        """Keep the sample's true heading (never blocks)."""
        h = sample.heading_true_deg
        if h is not None:
            with self._lock:
                self.samples.append((time.time(), float(h)))

    def close(self, timeout: float) -> None:
        """Nothing to stop."""

    def latest(self) -> float | None:
        """The newest heading."""
        with self._lock:
            return self.samples[-1][1] if self.samples else None


@dataclass
class Bridge:
    """A bridge daemon in this process (simulated compass in real time) beside an autopilot."""

    daemon: Any
    out: Any  #: its MavlinkOutput
    recorder: HeadingRecorder
    log: list[str]  #: the ``bridge`` loggers' lines (INFO and up) while it ran
    #: The time stamp (us) of every heading-feed message it sent (the MAVLink tap's view).
    sent_feed: list[int] = field(default_factory=list)
    #: The yaw sigma (rad) of every heading-feed message it sent, as the autopilot reads it
    #: back from the covariance (ArduPilot's angErr, PX4's yaw variance's root).
    sent_sigma: list[float] = field(default_factory=list)
    _restore: Callable[[], None] = lambda: None

    def stop(self) -> None:
        """Stop the daemon (and the log capture)."""
        try:
            self.daemon.stop(timeout=5.0)
        finally:
            self._restore()
            self._restore = lambda: None


def start_bridge(
    workdir: Path,
    endpoint: str,
    *,
    feed: str,
    location: tuple[float, float, float] | None,
    compass_at: tuple[float, float, float],
    yaw_deg: float,
    system_id: int = 1,
    mavlink: Mapping[str, Any] | None = None,
) -> Bridge:
    """A companion bridge (component 200) whose simulated compass lies still at
    ``yaw_deg`` (true) at ``compass_at``, feeding ``feed`` on ``endpoint``; ``location``
    None leaves ``[location]`` out (the position must come from the autopilot)."""
    import logging

    from bridge.config import config_from_mapping
    from bridge.daemon import build_daemon
    from bridge.link.serial_link import LinkState
    from bridge.link.transport import SimTransport
    from bridge.mavlink import MavlinkOutput, MavlinkSettings
    from bridge.sim.firmware import make_firmware
    from bridge.sim.motion import Still

    raw: dict[str, Any] = {
        "device": {"port": "sim", "stale_after": 5.0},
        "storage": {"dir": str(workdir)},
        "zenoh": {"enabled": False},
        "mavlink": {
            "endpoints": [endpoint],
            "role": "companion",
            "heading_feed": feed,
            "system_id": system_id,
            **dict(mavlink or {}),
        },
    }
    if location is not None:
        raw["location"] = dict(zip(("latitude", "longitude", "altitude_m"), location, strict=True))
    cfg = config_from_mapping(raw, env={}, hostname="test")
    # A real unit's errors and noise, calibrated with its true errors (what a good
    # calibration gives: `run --simulate`'s default).
    fw = make_firmware(3, motion=Still.from_deg(yaw_deg=yaw_deg), location=compass_at)
    daemon = build_daemon(cfg, transport=SimTransport(fw))
    daemon.bridge.settings.update_calibration(fw.sensor.errors.true_calibration(), "simulator")
    out = MavlinkOutput(MavlinkSettings.from_config(cfg), daemon.bridge.services)
    recorder = HeadingRecorder()
    lines: list[str] = []

    class _Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    handler = _Keep(logging.INFO)
    logger = logging.getLogger("bridge")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)

    def restore() -> None:
        logger.removeHandler(handler)
        logger.setLevel(level)

    sent: list[int] = []
    sigmas: list[float] = []

    def tap(m: Any) -> None:
        kind = m.message.get_type()
        if kind == "VISION_POSITION_ESTIMATE":
            sent.append(int(m.message.usec))
            c = m.message.covariance  # GCS_Common.cpp: angErr = cbrt(c15^2 + c18^2 + c20^2)
            sigmas.append((c[15] ** 2 + c[18] ** 2 + c[20] ** 2) ** (1.0 / 3.0))
        elif kind == "ODOMETRY":
            sent.append(int(m.message.time_usec))
            sigmas.append(math.sqrt(m.message.pose_covariance[20]))

    unsubscribe = daemon.bridge.services.mavlink_tap.subscribe(tap)

    def restore_all() -> None:
        unsubscribe()
        restore()

    daemon.bridge.pipeline.set_outputs([out, recorder])
    daemon.start()
    bridge = Bridge(daemon, out, recorder, lines, sent, sigmas, restore_all)
    deadline = time.monotonic() + DEADLINE_S
    while daemon.link.state is not LinkState.STREAMING or daemon.bridge.pipeline.samples < 3:
        if time.monotonic() > deadline:
            bridge.stop()
            pytest.fail("the simulated compass does not stream")
        time.sleep(0.02)
    return bridge


def angle_diff(a: float, b: float) -> float:
    """``a - b`` in degrees, wrapped to [-180, 180)."""
    return (a - b + 180.0) % 360.0 - 180.0


def heading_at(record: Sequence[tuple[float, float]], t: float) -> float | None:
    """The bridge's heading in force at ``t`` (a record of (time, heading)), None before it;
    any (time, value) record alike (the fed yaw ArduPilot logged)."""
    last = None
    for tb, h in record:
        if tb > t:
            break
        last = h
    return last


def mean_heading(
    record: Sequence[tuple[float, float]], t0: float, t1: float, min_samples: int = 3
) -> float:
    """The bridge's mean heading over [t0, t1) of a record of (time, heading): a step is
    measured between two means, not two single samples, which differ by the sensor's noise
    (0.1-0.2 deg each) on their own."""
    hs = [h for t, h in record if t0 <= t < t1]
    assert len(hs) >= min_samples, (t0, t1, len(hs))
    return hs[0] + statistics.fmean(angle_diff(h, hs[0]) for h in hs)


def overshoot_deg(
    yaw: Iterable[tuple[float, float]],
    record: Sequence[tuple[float, float]],
    settled_at: float,
    step: float,
) -> float:
    """How far the autopilot's yaw went past the bridge's new heading, in the step's direction.

    ``yaw`` is the autopilot's (time, yaw) after a change, ``record`` the bridge's
    headings; from ``settled_at`` on the record holds the new heading. Each yaw is
    compared with the heading at ``max(t, settled_at)``: a yaw that already shows the
    change is never compared with the old heading, so a few milliseconds of error in
    mapping the autopilot's clock onto ours cannot pass for an overshoot of the whole step.
    """
    sign = math.copysign(1.0, step)
    worst = -math.inf
    for t, y in yaw:
        b = heading_at(record, max(t, settled_at))
        if b is not None:
            worst = max(worst, angle_diff(y, b) * sign)
    return worst


def learned_calibration(bridge: Bridge, step_deg: float) -> Any:
    """The calibration whose offsets turn the (level, still) unit's heading by ``step_deg``:
    what the drift monitor would apply for a hard-iron change of that size."""
    from bridge.calibration.drift.estimator import with_offset_change

    a = bridge.out.latest.attitude
    h = np.asarray(a.mag_G, dtype=float)
    # Heading ψ = atan2(-h_y, h_x) for a level unit: turning ψ by +step turns the field
    # seen in body axes by -step about z; the offset change is what takes h there.
    c, s_ = math.cos(math.radians(-step_deg)), math.sin(math.radians(-step_deg))
    turned = np.array([c * h[0] - s_ * h[1], s_ * h[0] + c * h[1], h[2]])
    settings = bridge.daemon.bridge.settings
    return with_offset_change(settings.calibration, settings.mounting.matrix(), tuple(h - turned))


#: Longer than one STATUSTEXT (50 characters): the bridge sends it in chunks.
LONG_TEXT = "Compass bridge test: " + "a long status text in several chunks; " * 4


def from_bridge(m: Any) -> bool:
    """Sent by the bridge (component 200)."""
    return bool(m.get_srcComponent() == 200)


#: QGroundControl's ParameterManager (src/FactSystem/ParameterManager.cc) restarts a 3 s
#: timer on every PARAM_VALUE (``_waitingParamTimeoutTimer``); when it fires,
#: ``_waitingParamTimeout`` asks again for the indices still missing, by index, at most
#: ten at a time (``_fillIndexBatchQueue``), each up to five times
#: (``_maxInitialLoadRetrySingleParam``).
QGC_PARAM_TIMEOUT_S = 3.0
QGC_BATCH = 10
QGC_RETRIES = 5


def load_parameters(obs: Observer, system_id: int, since: float) -> tuple[float, set[int], int]:
    """QGroundControl's initial load: PARAM_REQUEST_LIST to every component of
    ``system_id``; the bridge's answers until its last index, or until none has come for
    QGroundControl's :data:`QGC_PARAM_TIMEOUT_S`. Returns the seconds from ``since`` to the
    last of them, the indices that came in this first round and the param_count given."""
    obs.mav.param_request_list_send(system_id, 0)
    got = obs.until_quiet(
        "PARAM_VALUE",
        from_bridge,
        since,
        QGC_PARAM_TIMEOUT_S,
        lambda ms: any(m.param_index == m.param_count - 1 for m in ms),
    )
    if not got:
        # Nothing from the bridge: the request never reached it (QGroundControl would not
        # know it has parameters at all).
        pytest.fail(
            f"no PARAM_VALUE from the bridge within {QGC_PARAM_TIMEOUT_S} s of the "
            "PARAM_REQUEST_LIST: was the request forwarded?"
        )
    return max(t for t, _ in got) - since, {m.param_index for _, m in got}, got[0][1].param_count


def _has_all(indices: frozenset[int], messages: list[Any]) -> bool:
    return indices <= {m.param_index for m in messages}


def fetch_missing(obs: Observer, system_id: int, have: set[int], count: int) -> set[int]:
    """What QGroundControl does after a first round that missed some (see
    :data:`QGC_PARAM_TIMEOUT_S`): PARAM_REQUEST_READ by index to the bridge for the lowest
    ten missing, again after each answer or time-out, five rounds at most. Returns the
    indices it then has."""
    have = set(have)
    for _ in range(QGC_RETRIES):
        batch = frozenset(sorted(set(range(count)) - have)[:QGC_BATCH])
        if not batch:
            break
        since = time.monotonic()
        for i in sorted(batch):
            obs.mav.param_request_read_send(system_id, 200, b"", i)
        got = obs.until_quiet(
            "PARAM_VALUE",
            from_bridge,
            since,
            QGC_PARAM_TIMEOUT_S,
            partial(_has_all, batch),
        )
        have |= {m.param_index for _, m in got}
    return have


def set_bridge_parameter(obs: Observer, system_id: int, name: str, value: float) -> Any:
    """PARAM_SET of a REAL32 ``name`` to the bridge (component 200 of ``system_id``)
    through the autopilot; returns the bridge's PARAM_VALUE echo (the value it kept)."""
    since = time.monotonic()
    obs.mav.param_set_send(system_id, 200, name.encode(), value, M.MAV_PARAM_TYPE_REAL32)
    return obs.wait(
        "PARAM_VALUE",
        lambda m: m.param_id == name and m.get_srcComponent() == 200,
        since=since,
    )


def message_interval_storm(obs: Observer, system_id: int) -> tuple[int, int]:
    """30 GET_MESSAGE_INTERVAL (ATTITUDE, VFR_HUD, SYS_STATUS in turn) to the bridge at
    QGroundControl's pace, one per 20 ms; returns the bridge's COMMAND_ACKs and
    MESSAGE_INTERVALs for them, 2 s after the last."""
    since = time.monotonic()
    ids = [M.MAVLINK_MSG_ID_ATTITUDE, M.MAVLINK_MSG_ID_VFR_HUD, M.MAVLINK_MSG_ID_SYS_STATUS]
    for i in range(30):
        # PX4 forwards the ground station's commands through the same two-message
        # buffer: the storm comes at QGroundControl's pace, one command per 20 ms.
        obs.mav.command_long_send(
            system_id, 200, M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, ids[i % 3], 0, 0, 0, 0, 0, 0
        )
        time.sleep(0.02)
    time.sleep(2.0)
    acks = len(
        obs.history(
            "COMMAND_ACK",
            lambda m: from_bridge(m) and m.command == M.MAV_CMD_GET_MESSAGE_INTERVAL,
            since=since,
        )
    )
    return acks, len(obs.history("MESSAGE_INTERVAL", from_bridge, since=since))


def autopilot_parameters(obs: Observer, since: float) -> int:
    """How many of the autopilot's own parameters (component 1) arrived since ``since``."""
    return len(
        {
            m.param_index
            for _, m in obs.history("PARAM_VALUE", lambda m: m.get_srcComponent() == 1, since=since)
        }
    )


def send_long_status_text(bridge: Bridge, obs: Observer) -> list[Any]:
    """The bridge announces :data:`LONG_TEXT`; the STATUSTEXT chunks of it that reached
    ``obs`` within a second."""
    from bridge.events import Event, Severity

    since = time.monotonic()
    bridge.daemon.bridge.events.emit(Event("test.long", LONG_TEXT, Severity.NOTICE))
    time.sleep(1.0)
    return [m for _, m in obs.history("STATUSTEXT", from_bridge, since=since)]


def joined_text(chunks: Sequence[Any]) -> str:
    """The text STATUSTEXT chunks carry, joined (the last one's NUL padding stripped)."""
    text = b"".join((c.text.encode() if isinstance(c.text, str) else bytes(c.text)) for c in chunks)
    return text.rstrip(b"\0").decode()
