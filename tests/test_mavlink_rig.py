"""The MAVLink test rig: a real daemon on the simulated compass, a real pymavlink ground station.

Imported by the other ``test_mavlink_*`` modules (``from test_mavlink_rig import ...``);
its own tests check the rig's ground rules: the bytes on the wire are MAVLink 2
and both UDP and TCP carry a conversation.

* :class:`Gcs` wraps a ``pymavlink.mavutil`` connection (ardupilotmega, MAVLink 2)
  with an inbox, so a test can wait for one message without losing the others,
  and every wait has a deadline.
* :func:`start_rig` builds a :class:`Rig`: configuration from a mapping, the
  simulated compass in process (``fast``: on a :class:`FastClock`, ``SPEED`` times
  real time but never far ahead of the compass's reader, with the calibration
  controller and the pipeline's frame clock on it, as the calibrator's own tests
  do), the daemon with a :class:`MavlinkOutput`, started.
"""

from __future__ import annotations

import itertools
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")  # before mavutil picks its dialect module
import waiting
from pymavlink import mavutil

from benchmarks import procstat
from benchmarks.fuzz_hostile import heartbeat
from bridge.calibration.sessions import CalibratorSettings
from bridge.config import Config, config_from_mapping
from bridge.daemon import Daemon, build_daemon
from bridge.link.serial_link import LinkState
from bridge.link.transport import SimTransport
from bridge.mavlink import MavlinkOutput, MavlinkSettings
from bridge.mavlink.endpoints import Link
from bridge.protocol.gmr import AttitudeFrame
from bridge.sim.firmware import Firmware, make_firmware
from bridge.sim.motion import Motion, YawTurns
from bridge.sim.physics import DEFAULT_LOCATION
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration  # real sockets, processes or threads

mavutil.set_dialect("ardupilotmega")
M: Any = mavutil.mavlink

DEADLINE_S = 20.0  #: real seconds any single wait may take before the test fails
SPEED = 20.0  #: fast rigs: simulated seconds per real second
#: fast rigs: the most simulated time the compass runs ahead of its reader (a host's stall)
LEAD_S = 0.5
LAT, LON, ALT = DEFAULT_LOCATION
GCS_SYSID, GCS_COMPID = 255, 190


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port nobody listens on right now (127.0.0.1; UDP unless ``kind`` says otherwise)."""
    return procstat.free_port(kind)


def recv_udp(sock: socket.socket, n: int, timeout: float = DEADLINE_S) -> list[bytes]:
    """The first ``n`` datagrams arriving on ``sock`` within ``timeout`` s (fewer if not)."""
    sock.settimeout(0.2)
    return list(itertools.islice(procstat.datagrams(sock, within_s=timeout), n))


class FastClock:
    """Monotonic time running ``speed`` times faster than real time (and its sleep), that
    never runs more than ``lead_s`` ahead of the compass's reader.

    A host that stalls delays the frames it reads, not the compass's sampling. Sped up,
    a stall of the test machine is ``speed`` times longer to the simulated world: at 20x
    a 100 ms stall is 2 s in which the reader reads nothing, the firmware drops every
    frame older than that (a suspended host, ``MAX_BACKLOG_S``), and a six-face dwell
    of 6 s can pass unread -- no real host stalls that long. So the world waits for
    its reader: the transport's :meth:`sleep` is where the reader has caught up, and
    from there the clock runs on at most ``lead_s``; a longer stall stops it. The
    frames sampled meanwhile come in one burst of at most ``lead_s``, as after a real
    stall of a host, and their ``seq`` tells the daemon when they were sampled.
    """

    def __init__(self, speed: float, lead_s: float = LEAD_S) -> None:
        self.speed = speed
        self.lead_s = lead_s
        self._t0 = time.monotonic()
        self._stopped = 0.0  #: simulated seconds the clock stood still, waiting for the reader
        self._caught_up = self._t0  #: when the reader last waited for the compass
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            t = self._t0 + (time.monotonic() - self._t0) * self.speed - self._stopped
            limit = self._caught_up + self.lead_s
            if t > limit:
                self._stopped += t - limit
                t = limit
            return t

    def sleep(self, seconds: float) -> None:
        """The reader waits for the compass's next event: it is up to date now."""
        now = self()
        with self._lock:
            self._caught_up = max(self._caught_up, now)
        time.sleep(max(0.0, seconds) / self.speed)


class Gcs:
    """A pymavlink ground station with an inbox and bounded waits."""

    def __init__(self, conn: Any) -> None:
        self.conn = conn
        self.mav = conn.mav
        self.inbox: list[Any] = []
        self.raw: list[bytes] = []  # every packet's bytes, as they arrived

    def close(self) -> None:
        self.conn.close()

    def pump(self, timeout: float = 0.05) -> None:
        """Read whatever arrives within ``timeout`` into the inbox."""
        m = self.conn.recv_match(blocking=True, timeout=timeout)
        while m is not None:
            if m.get_type() != "BAD_DATA":
                self.inbox.append(m)
                self.raw.append(bytes(m.get_msgbuf()))
            m = self.conn.recv_match(blocking=False)

    def wait(
        self,
        mtype: str | tuple[str, ...],
        cond: Callable[[Any], bool] | None = None,
        timeout: float = DEADLINE_S,
        consume: bool = True,
    ) -> Any:
        """The oldest message of ``mtype`` (matching ``cond``) in the inbox or still to come.

        Only that message leaves the inbox (``consume``): every type is its own queue, so
        a STATUSTEXT sent just before a COMMAND_ACK is still there after waiting for the
        ACK. Use :meth:`flush` to wait for something *newer* than what came so far.
        Fails the test after ``timeout``.
        """
        types = (mtype,) if isinstance(mtype, str) else mtype
        deadline = time.monotonic() + timeout
        while True:
            for i, m in enumerate(self.inbox):
                if m.get_type() in types and (cond is None or cond(m)):
                    if consume:
                        del self.inbox[i]
                    return m
            if time.monotonic() > deadline:
                seen = sorted({m.get_type() for m in self.inbox})
                pytest.fail(f"no {types} within {timeout} s (inbox holds {seen})")
            self.pump(0.05)

    def nothing(self, mtype: str, cond: Callable[[Any], bool] | None, seconds: float) -> None:
        """Assert that no such message comes within ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump(0.05)
        bad = [m for m in self.inbox if m.get_type() == mtype and (cond is None or cond(m))]
        assert not bad, f"unexpected {mtype}: {bad[0]}"

    def collect(self, seconds: float) -> list[Any]:
        """Everything that arrives within ``seconds`` (the inbox is emptied)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump(0.05)
        out, self.inbox = self.inbox, []
        return out

    def flush(self) -> None:
        """Forget what arrived so far."""
        self.pump(0.05)
        self.inbox.clear()

    def command(
        self,
        command: int,
        *params: float,
        target: tuple[int, int] = (1, 1),
        use_int: bool = False,
        timeout: float = DEADLINE_S,
        final: bool = False,
    ) -> Any:
        """Send COMMAND_LONG (or COMMAND_INT) and return its first COMMAND_ACK (``final``: the
        one after IN_PROGRESS, as QGroundControl and MAVSDK wait for long work's)."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        if use_int:
            self.mav.command_int_send(
                target[0],
                target[1],
                0,
                command,
                0,
                0,
                p[0],
                p[1],
                p[2],
                p[3],
                int(p[4]),
                int(p[5]),
                p[6],
            )
        else:
            self.mav.command_long_send(target[0], target[1], command, 0, *p)
        ack = self.wait("COMMAND_ACK", lambda m: m.command == command, timeout)
        if final and ack.result == M.MAV_RESULT_IN_PROGRESS:
            ack = self.wait("COMMAND_ACK", lambda m: m.command == command, timeout)
        return ack

    def param(
        self, name: str, timeout: float = DEADLINE_S, target: tuple[int, int] = (1, 1)
    ) -> Any:
        """PARAM_REQUEST_READ by name -> its PARAM_VALUE."""
        self.mav.param_request_read_send(target[0], target[1], name.encode(), -1)
        return self.wait("PARAM_VALUE", lambda m: m.param_id == name, timeout)

    def set_param(
        self, name: str, value: float, ptype: int, target: tuple[int, int] = (1, 1)
    ) -> Any:
        """PARAM_SET -> the PARAM_VALUE echo."""
        self.mav.param_set_send(target[0], target[1], name.encode(), value, ptype)
        return self.wait("PARAM_VALUE", lambda m: m.param_id == name)


def connect_gcs(url: str, sysid: int = GCS_SYSID, compid: int = GCS_COMPID, **kw: Any) -> Gcs:
    """A pymavlink peer on ``url`` that announces itself with a HEARTBEAT."""
    conn = mavutil.mavlink_connection(
        url, source_system=sysid, source_component=compid, dialect="ardupilotmega", **kw
    )
    g = Gcs(conn)
    g.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return g


def make_config(tmp_path: Path, state: str = "state", **sections: dict[str, Any]) -> Config:
    raw: dict[str, Any] = {
        "device": {"port": "sim", "stale_after": 5.0},
        "storage": {"dir": str(tmp_path / state)},
        "location": {"latitude": LAT, "longitude": LON, "altitude_m": ALT},
        "zenoh": {"enabled": False},
    }
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    return config_from_mapping(raw, env={}, hostname="test")


class Sent(Link):
    """A link that keeps what it is sent: a peer without an endpoint (the handlers only
    send to it; nothing here frames, queues or writes)."""

    def __init__(self) -> None:
        self.name = "sent"
        self.messages: list[Any] = []

    def send(self, packet: Any) -> None:
        self.messages.append(packet)

    @property
    def results(self) -> list[int]:
        """The COMMAND_ACKs' results, in the order sent."""
        return [int(p.result) for p in self.messages]


def offline_daemon(tmp: Path, hostname: str, **mavlink: Any) -> tuple[Config, Daemon]:
    """A configuration (a simulated compass, zenoh off, state in ``tmp``; ``mavlink`` its
    section, no endpoints unless given) and its daemon, never started: the services a
    :class:`MavlinkOutput` under test uses, without the daemon's threads."""
    cfg = config_from_mapping(
        {
            "device": {"port": "sim"},
            "storage": {"dir": str(tmp)},
            "zenoh": {"enabled": False},
            "mavlink": {"endpoints": [], **mavlink},
        },
        env={},
        hostname=hostname,
    )
    return cfg, build_daemon(cfg)


@dataclass
class Rig:
    """A running daemon with a MAVLink output on a simulated compass."""

    daemon: Daemon
    out: MavlinkOutput
    fw: Firmware
    cfg: Config
    udp_port: int  #: our udpin port (a GCS connects with udpout:127.0.0.1:<port>)
    tcp_port: int  #: our tcpin port
    gcss: list[Gcs]
    pty: PtyCompass | None = None  #: the simulated compass on a real pty (``pty=True``)
    clock: Callable[[], float] = time.monotonic  #: the simulator's clock

    def motion_time(self) -> float:
        """Seconds into the simulator's motion script (its clock, not real time)."""
        epoch = self.fw.motion_epoch
        return 0.0 if epoch is None else self.clock() - epoch

    def wait_motion_time(self, t: float) -> None:
        """Wait (bounded) until the motion script reaches ``t`` simulated seconds."""
        assert self.motion_time() <= t, f"too late: the motion is at {self.motion_time():.1f} s"
        assert wait_until(lambda: self.motion_time() >= t), "motion clock stuck"

    def gcs(self, kind: str = "udp", **kw: Any) -> Gcs:
        url = (
            f"udpout:127.0.0.1:{self.udp_port}"
            if kind == "udp"
            else f"tcp:127.0.0.1:{self.tcp_port}"
        )
        g = connect_gcs(url, **kw)
        self.gcss.append(g)
        # the first HEARTBEAT back means the endpoint knows us
        g.wait("HEARTBEAT", lambda m: m.get_srcSystem() == self.out.identity.system_id)
        return g

    def stop(self) -> None:
        for g in self.gcss:
            g.close()
        self.gcss.clear()
        self.daemon.stop(timeout=5.0)
        if self.pty is not None:
            self.pty.stop()


def start_rig(
    tmp_path: Path,
    *,
    motion: Motion | None = None,
    fast: bool = False,
    speed: float = SPEED,
    seed: int = 3,
    state: str = "state",
    mavlink: dict[str, Any] | None = None,
    calibration: dict[str, Any] | None = None,
    settings: CalibratorSettings | None = None,
    extra_endpoints: tuple[str, ...] = (),
    device: dict[str, Any] | None = None,
    ideal: bool = False,
    pty: bool = False,
) -> Rig:
    """A started :class:`Rig` with a udpin and a tcpin endpoint on free ports.

    ``speed``: a fast rig's simulated seconds per real second (a slower one loses less
    simulated time when the machine stalls it); ``ideal``: a perfect simulated unit (no
    calibration needed, never "disturbed");
    ``pty``: the compass served on a real pseudo-terminal (it can be unplugged).
    """
    assert not (pty and fast), "a pty compass runs in real time"
    udp, tcp = free_port(), free_port(socket.SOCK_STREAM)
    mav: dict[str, Any] = {
        "endpoints": [f"udpin:127.0.0.1:{udp}", f"tcpin:127.0.0.1:{tcp}", *extra_endpoints]
    }
    mav.update(mavlink or {})
    dev = dict(device or {})
    if fast:
        # The compass runs ``speed`` times faster than the link's clock: frames held for a
        # burst would be seconds of the compass's time. Reading in bursts is for real time.
        dev.setdefault("read_bursts", False)
    link_path = tmp_path / f"compass-{udp}.tty"
    if pty:
        dev["port"] = str(link_path)
    cfg = make_config(
        tmp_path,
        state,
        mavlink=mav,
        calibration=calibration or {},
        device=dev,
    )
    fw = make_firmware(
        seed, motion=motion or YawTurns(10.0), location=DEFAULT_LOCATION, ideal=ideal
    )
    server: PtyCompass | None = None
    transport: SimTransport | None = None
    fc = FastClock(speed)
    if pty:
        server = PtyCompass(fw, link_path).start()
    elif fast:
        transport = SimTransport(fw, clock=fc, sleep=fc.sleep)
    else:
        transport = SimTransport(fw)
    if fast:
        # The calibration controller and the frames' instants on the simulator's clock (as
        # test_calibrator): the link's clock is real time, the compass's frames are not.
        daemon = build_daemon(
            cfg,
            transport=transport,
            calibrator_settings=settings or CalibratorSettings(no_data_timeout_s=40.0),
            clock=fc,
        )
    else:
        daemon = build_daemon(cfg, transport=transport)
    out = MavlinkOutput(MavlinkSettings.from_config(cfg), daemon.bridge.services)
    daemon.bridge.pipeline.set_outputs([out])
    daemon.start()
    rig = Rig(daemon, out, fw, cfg, udp, tcp, [], server, fc if fast else time.monotonic)
    try:
        assert daemon.link.wait_state(LinkState.STREAMING, DEADLINE_S), "compass not streaming"
        assert wait_until(lambda: daemon.link.params is not None), "no PAR,GET in the handshake"
        assert wait_until(lambda: daemon.bridge.pipeline.samples >= 3), (
            "no samples through the pipeline"
        )
    except BaseException:
        rig.stop()
        raise
    return rig


def wait_until(cond: Callable[[], bool], timeout: float = DEADLINE_S) -> bool:
    """:func:`waiting.wait_until` with the rig's deadline by default."""
    return waiting.wait_until(cond, timeout, step=0.02)


def rig_factory() -> Iterator[Callable[..., Rig]]:
    """Factory of started rigs; every one is stopped at the end.

    The suite's ``rigs`` fixture (tests/conftest.py) is this, for every test module.
    """
    made: list[Rig] = []

    def make(tmp_path: Path, **kw: Any) -> Rig:
        r = start_rig(tmp_path, **kw)
        made.append(r)
        return r

    yield make
    for r in made:
        r.stop()


# ------------------------------------------------------------------------------ the rig's own tests


def test_bytes_on_the_wire_are_mavlink2(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    """A raw UDP socket (no pymavlink in between) sees 0xFD packets from our ids."""
    rig = rigs(tmp_path)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # Any datagram makes the udpin endpoint treat us as a peer: send a real HEARTBEAT.
        gcs_mav = M.MAVLink(None, GCS_SYSID, GCS_COMPID)
        sock.sendto(heartbeat(gcs_mav), ("127.0.0.1", rig.udp_port))
        got = recv_udp(sock, 20)
    finally:
        sock.close()
    assert len(got) >= 20
    # A datagram may carry several packets back to back (a frame's streams leave together):
    # cut each into its packets by the header's length byte (unsigned: 12 + payload bytes),
    # the cuts must fall exactly on the datagram's end; the checks below hold per packet.
    packets: list[bytes] = []
    for datagram in got:
        at = 0
        while at < len(datagram):
            assert datagram[at] == 0xFD, datagram[at : at + 1].hex()
            end = at + 12 + datagram[at + 1]
            assert end <= len(datagram)
            packets.append(datagram[at:end])
            at = end
    got = packets
    assert all(d[0] == 0xFD for d in got), [d[:1].hex() for d in got]
    # header: len, incompat, compat, seq, sysid, compid: our ids, unsigned, consecutive seq
    assert {(d[5], d[6]) for d in got} == {(1, 1)}
    assert all(d[2] == 0 for d in got)
    seqs = [d[4] for d in got]
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(seqs))


def test_udp_and_tcp_peers_both_get_a_conversation(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path)
    udp, tcp = rig.gcs("udp"), rig.gcs("tcp")
    for g in (udp, tcp):
        att = g.wait("ATTITUDE")
        assert att.get_srcSystem() == 1 and att.get_srcComponent() == 1
        assert g.conn.WIRE_PROTOCOL_VERSION == "2.0"
        ack = g.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert ack.result == M.MAV_RESULT_ACCEPTED
        assert (ack.target_system, ack.target_component) == (GCS_SYSID, GCS_COMPID)
        g.wait("AUTOPILOT_VERSION")
    # an ACK goes to the link that asked, not to the other one
    udp.flush()
    tcp.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE)
    udp.nothing("COMMAND_ACK", None, 0.5)


def test_a_stalled_reader_delays_the_fast_rigs_frames_but_loses_none_nor_their_instants(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    """A host that stalls delays the frames, not the compass's sampling. The reader held
    off the port for 0.3 s, 6 simulated seconds at 20x (the firmware drops frames over 2 s
    behind): the rig's clock waits for it, no frame is lost, and every frame reaches the
    calibrator at the instant the firmware sampled it, on the compass's own 10 Hz. (On
    wall time x 20 the stall lost 40 frames and the rest came stamped as they arrived.)"""
    rig = rigs(tmp_path, fast=True)
    pipeline = rig.daemon.bridge.pipeline
    fed: list[tuple[int, float]] = []
    feed = pipeline._feed

    def record(frame: object, t: float) -> None:
        if isinstance(frame, AttitudeFrame):
            fed.append((frame.seq, t))
        feed(frame, t)

    pipeline._feed = record
    assert wait_until(lambda: len(fed) >= 60)  # 6 simulated seconds: the rate is learnt
    first = len(fed) - 10
    transport = rig.daemon.transport.inner
    assert isinstance(transport, SimTransport)
    with transport._cond:  # the reader cannot read meanwhile
        time.sleep(0.3)
    assert wait_until(lambda: len(fed) >= first + 60)
    pipeline._feed = feed
    seqs = [seq for seq, _t in fed[first:]]
    assert all((b - a) % 65536 == 1 for a, b in itertools.pairwise(seqs)), seqs
    sampled = {e.frame.seq: e.t for e in list(rig.fw.truth)}
    late = [t - sampled[seq] for seq, t in fed[first:]]
    assert max(map(abs, late)) < 0.05, late  # half a frame's period
    assert pipeline.frame_clock.rate_hz == 10.0


def test_threads_of_a_stopped_rig_are_gone(tmp_path: Path) -> None:
    before = {t.name for t in threading.enumerate()}
    rig = start_rig(tmp_path)
    assert any(t.name.startswith("mavlink-") for t in threading.enumerate())
    rig.stop()
    assert wait_until(
        lambda: (
            not ({t.name for t in threading.enumerate() if t.name.startswith("mavlink-")} - before)
        ),
        5.0,
    )
