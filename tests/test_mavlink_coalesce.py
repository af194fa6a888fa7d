"""The sample streams due on one sample leave together: the attitude first, the rest in one.

``MavlinkOutput.publish`` hands the packets one frame produces to every
endpoint at once (``Endpoint.broadcast_many`` / ``Link.send_many``): a UDP
peer with nothing queued gets them framed back to back in one ``sendto``
(split on packet boundaries beyond ``MAX_DATAGRAM_BYTES``), as ArduPilot packs
its UDP link. When more than the attitude (ATTITUDE with its TILT_SRC note,
ATTITUDE_QUATERNION: ``schedule.ATTITUDE_FIRST``) is due, the attitude leaves in a
datagram of its own before the others are encoded, and the others follow in a
second: two datagrams, the same packets in the same order. Everything per packet
stays: the link's sequence numbers, the signature, the counters, the taps, the
direct-send burst window, and the fall-back to the endpoint's thread when the
socket would block. Real sockets
only: a UDP ground station on 127.0.0.1, a TCP client, and (for "would block",
which loopback UDP never reports on Linux: the loopback device frees the
sender's buffer at once) a Unix datagram socket whose receiver does not read.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from harness import ManualClock
from test_mavlink_endpoints import (
    KEY,
    Inbox,
    local_address,
    paced_udp_endpoint,
    parse_all,
    ping,
)
from test_mavlink_rig import DEADLINE_S, M, free_port, offline_daemon, recv_udp, wait_until
from test_mavlink_telemetry import make_sample

from benchmarks.procstat import datagrams, udp_socket
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import Message as Packet
from bridge.mavlink.dialect import message
from bridge.mavlink.endpoints import MAX_DATAGRAM_BYTES, open_endpoint
from bridge.mavlink.endpoints import base as E  # noqa: N812 - short
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings
from bridge.mavlink.signing import Signing

pytestmark = pytest.mark.integration  # real sockets, processes or threads

#: Every per-sample stream on: all of them fall due on the first sample, in this order.
ALL_STREAMS = ["ATTITUDE", "ATTITUDE_QUATERNION", "VFR_HUD", "SCALED_IMU", "RAW_IMU", "HIGHRES_IMU"]
#: The first frame's: ATTITUDE with its tilt source beside it (TILT_SRC, then once a second).
FIRST_FRAME = ["ATTITUDE", "NAMED_VALUE_INT", *ALL_STREAMS[1:]]
#: ... in two datagrams: the attitude first, then the rest.
ATTITUDE_DATAGRAM = FIRST_FRAME[:3]
REST_DATAGRAM = FIRST_FRAME[3:]
ALL_ON = {
    "rate_attitude_hz": 50.0,
    "rate_attitude_quaternion_hz": 10.0,
    "rate_vfr_hud_hz": 4.0,
    "rate_scaled_imu_hz": 10.0,
    "rate_raw_imu_hz": 10.0,
    "rate_highres_imu_hz": 10.0,
}
SAMPLE_IDS = {T.ATTITUDE, T.ATTITUDE_QUATERNION, T.VFR_HUD, T.SCALED_IMU, T.RAW_IMU, T.HIGHRES_IMU}
SAMPLE_IDS |= {int(M.MAVLINK_MSG_ID_NAMED_VALUE_INT)}


def consecutive(seqs: list[int]) -> bool:
    return all((b - a) % 256 == 1 for a, b in itertools.pairwise(seqs))


def payload_of(msg: Any) -> bytes:
    """The payload bytes a received message carried (after the 10-byte MAVLink 2 header)."""
    buf = bytes(msg.get_msgbuf())
    return buf[10 : 10 + buf[1]]


def big(i: int) -> Packet:
    """A large numbered packet (FILE_TRANSFER_PROTOCOL, 254-byte payload, nothing trimmed)."""
    return message(
        M.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL,
        target_network=i,
        target_system=1,
        target_component=1,
        payload=[0x55] * 251,
    )


class Gcs:
    """A ground station on a plain UDP socket: keeps raw datagrams."""

    def __init__(self) -> None:
        self.sock = udp_socket(0.1)
        self.port = int(self.sock.getsockname()[1])

    def datagram_with(self, mtype: str, key: bytes | None = None) -> bytes:
        """The next datagram holding a ``mtype`` message (others, e.g. HEARTBEAT, skipped)."""
        for data in datagrams(self.sock, within_s=DEADLINE_S):
            if any(m.get_type() == mtype for m in parse_all(data, key)):
                return data
        raise AssertionError(f"no datagram with {mtype} within {DEADLINE_S} s")


@pytest.fixture
def output(tmp_path: Path) -> Iterator[Callable[..., tuple[MavlinkOutput, Gcs, list[Packet]]]]:
    made: list[tuple[MavlinkOutput, Gcs]] = []

    def make(key: bytes | None = None, **rates: float) -> tuple[MavlinkOutput, Gcs, list[Packet]]:
        gcs = Gcs()
        cfg, daemon = offline_daemon(
            tmp_path, "coalesce", endpoints=[f"udpout:127.0.0.1:{gcs.port}"], **rates
        )
        settings = replace(MavlinkSettings.from_config(cfg), signing_key=key)
        out = MavlinkOutput(settings, daemon.bridge.services, clock=ManualClock(100.0))
        sent: list[Packet] = []
        daemon.bridge.mavlink_tap.subscribe(lambda m: sent.append(m.message))
        out.start()
        made.append((out, gcs))
        assert wait_until(lambda: bool(out.endpoints[0].links))
        # The clock stands still: the telemetry thread's one HEARTBEAT / SYS_STATUS round
        # is all it sends. Wait until the endpoint has accounted for it (sent, or offered
        # before the socket was open), so the counters below move for the sample only.
        ep = out.endpoints[0]

        def settled() -> bool:
            c = ep.counters()
            return bool(sent) and c.packets_sent + c.packets_unsent == len(sent)

        assert wait_until(settled)
        return out, gcs, sent

    yield make
    for out, gcs in made:
        out.close(2.0)
        gcs.sock.close()


def test_streams_due_on_one_sample_arrive_in_two_datagrams_the_attitude_first(
    output: Callable[..., tuple[MavlinkOutput, Gcs, list[Packet]]],
) -> None:
    out, gcs, sent = output(**ALL_ON)
    ep = out.endpoints[0]
    before, tapped = ep.counters(), len(sent)
    out.publish(make_sample(t=100.0))
    first = gcs.datagram_with("ATTITUDE")
    second = gcs.datagram_with("VFR_HUD")
    head, rest = parse_all(first), parse_all(second)
    assert [m.get_type() for m in head] == ATTITUDE_DATAGRAM  # the attitude, on its own
    assert [m.get_type() for m in rest] == REST_DATAGRAM  # then the other four, together
    msgs = head + rest
    assert consecutive([m.get_seq() for m in msgs])  # one sequence: in order, nothing between
    for data, part in ((first, head), (second, rest)):
        assert b"".join(bytes(m.get_msgbuf()) for m in part) == data  # nothing else in them
    # each packet handed to the tap once, in the same order, the same payloads
    frame = [p for p in sent[tapped:] if p.get_msgId() in SAMPLE_IDS]
    assert [(p.get_msgId(), bytes(p.get_payload())) for p in frame] == [
        (m.get_msgId(), payload_of(m)) for m in msgs
    ]
    after = ep.counters()
    assert after.packets_sent - before.packets_sent == 7  # packets, not datagrams
    assert after.bytes_sent - before.bytes_sent == len(first) + len(second)
    assert out.counters.publish_errors == 0
    # A frame with only ATTITUDE due (50 Hz: 20 ms later) still sends it alone.
    ManualClock.of(out.clock).t += 0.02
    out.publish(make_sample(t=100.02))
    (alone,) = parse_all(gcs.datagram_with("ATTITUDE"))
    assert alone.get_type() == "ATTITUDE" and alone.get_seq() == (msgs[-1].get_seq() + 1) % 256


def test_a_signed_link_signs_every_packet_of_both_datagrams(
    output: Callable[..., tuple[MavlinkOutput, Gcs, list[Packet]]],
) -> None:
    out, gcs, _sent = output(key=KEY, **ALL_ON)
    out.publish(make_sample(t=100.0))
    first, second = gcs.datagram_with("ATTITUDE", KEY), gcs.datagram_with("VFR_HUD", KEY)
    msgs = parse_all(first, KEY) + parse_all(second, KEY)  # pymavlink checks every signature
    assert [m.get_type() for m in msgs] == FIRST_FRAME
    assert all(m._signed and m._link_id == 0 for m in msgs)
    assert consecutive([m.get_seq() for m in msgs])
    for data in (first, second):
        with pytest.raises(M.MAVError):  # and they are really signed: another key fails
            parse_all(data, bytes(32))


def test_a_stream_that_fails_to_encode_does_not_hold_back_the_others(
    output: Callable[..., tuple[MavlinkOutput, Gcs, list[Packet]]],
) -> None:
    out, gcs, _sent = output(**ALL_ON)

    def broken(_s: Any) -> Packet:
        raise ValueError("encoder bug")

    out._sample_encoders[T.VFR_HUD] = broken  # the third of the six
    out.publish(make_sample(t=100.0))  # never raises
    msgs = parse_all(gcs.datagram_with("ATTITUDE"))
    assert [m.get_type() for m in msgs] == ["ATTITUDE", "NAMED_VALUE_INT", "ATTITUDE_QUATERNION"]
    assert out.counters.publish_errors == 1
    # Broken among the rest: those before it still leave, in the second datagram.
    out._sample_encoders[T.VFR_HUD] = out._stream_encoders[T.VFR_HUD]
    out._sample_encoders[T.RAW_IMU] = broken  # the fifth
    ManualClock.of(out.clock).t += 1.0  # every stream due again (TILT_SRC too)
    out.publish(make_sample(t=101.0))
    head = parse_all(gcs.datagram_with("ATTITUDE"))
    assert [m.get_type() for m in head] == ATTITUDE_DATAGRAM
    rest = parse_all(gcs.datagram_with("VFR_HUD"))
    assert [m.get_type() for m in rest] == ["VFR_HUD", "SCALED_IMU"]
    assert out.counters.publish_errors == 2


def test_a_group_larger_than_a_datagram_is_cut_on_packet_boundaries() -> None:
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    ep: Any = open_endpoint(
        f"udpout:127.0.0.1:{gcs.getsockname()[1]}", system_id=1, component_id=1,
        on_message=Inbox(),
    )  # fmt: skip
    try:
        ep._open()  # not started: nothing but this test sends
        ep.broadcast_many([big(i) for i in range(10)])  # 10 x 266 bytes
        got = recv_udp(gcs, 2)
        assert [len(d) for d in got] == [5 * 266, 5 * 266]  # 6 would not fit in 1400
        assert all(len(d) <= MAX_DATAGRAM_BYTES for d in got)
        msgs = [m for d in got for m in parse_all(d)]  # each datagram parses on its own
        assert [m.target_network for m in msgs] == list(range(10))
        assert [m.get_seq() for m in msgs] == list(range(10))
        assert recv_udp(gcs, 1, timeout=0.3) == []
        c = ep.counters()
        assert (c.packets_sent, c.bytes_sent) == (10, 10 * 266)
    finally:
        ep.close(1.0)
        gcs.close()


def test_when_the_socket_would_block_the_rest_waits_for_the_endpoint_thread(
    tmp_path: Path,
) -> None:
    path = str(tmp_path / "gcs")
    gcs = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    gcs.bind(path)
    gcs.setblocking(False)
    tx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    tx.setblocking(False)
    ep: Any = open_endpoint(
        f"udpout:127.0.0.1:{free_port()}", system_id=1, component_id=1,
        on_message=Inbox(), signing=Signing(KEY), link_id=2,
    )  # fmt: skip
    try:
        ep._open()  # not started: the test plays the endpoint thread's part (_flush)
        (link,) = ep.links
        ep._sock.close()
        ep._sock, link.address = tx, path  # the same sendto, onto a socket that fills up
        filler = 0
        with contextlib.suppress(BlockingIOError):
            for _ in range(10_000):
                tx.sendto(b"filler", path)
                filler += 1
        assert 0 < filler < 10_000  # the receiver's queue is full now
        group = [big(i) for i in range(10)]  # signed: 10 x 279 bytes, two datagrams' worth
        ep.broadcast_many(group)  # returns at once: nothing sent, nothing lost
        assert len(link.pending) == 10 * 279 and not link.queue
        assert ep.counters().packets_sent == 0
        link.send(big(10))  # later packets wait behind what is pending
        assert [p.target_network for p in link.queue] == [10]
        ep._flush()  # still full: everything stays as it was
        assert len(link.pending) == 10 * 279 and len(link.queue) == 1
        for _ in range(filler):  # the ground station reads again ...
            assert gcs.recv(65535) == b"filler"
        ep._flush()  # ... and the endpoint thread sends the rest, whole packets per datagram
        got = []
        with contextlib.suppress(BlockingIOError):
            for _ in range(10):
                got.append(gcs.recv(65535))
        assert [len(d) for d in got] == [5 * 279, 5 * 279, 279]
        msgs = [m for d in got for m in parse_all(d, KEY)]  # every signature verifies
        assert [m.target_network for m in msgs] == list(range(11))
        assert [m.get_seq() for m in msgs] == list(range(11))  # each framed once, in order
        assert all(m._signed and m._link_id == 2 for m in msgs)
        assert not link.pending and not link.queue
        c = ep.counters()
        assert (c.packets_sent, c.bytes_sent, c.packets_dropped) == (11, 11 * 279, 0)
    finally:
        ep.close(1.0)
        gcs.close()


def test_the_burst_window_counts_the_packets_of_a_group(monkeypatch: pytest.MonkeyPatch) -> None:
    burst = E._DIRECT_BURST
    # not started: the test plays the endpoint thread's part (_flush)
    with paced_udp_endpoint(monkeypatch) as (now, ep, gcs):
        (link,) = ep.links
        link.send(ping(0))  # one direct packet counts against the window ...
        link.send_many([ping(i) for i in range(1, burst + 4)])  # ... so 15 more go, 4 wait
        assert [p.time_boot_ms for p in link.queue] == list(range(burst, burst + 4))
        assert ep.counters().packets_sent == burst
        now[0] += E._DIRECT_WINDOW_S * 2  # a new window, but packets wait: behind them
        link.send_many([ping(burst + 4), ping(burst + 5)])
        assert len(link.queue) == 6
        ep._flush()
        n = burst + 6
        got = recv_udp(gcs, 2 + 6)  # the direct 1 + a datagram of 15, then 6 queued singly
        assert [len(parse_all(d)) for d in got] == [1, burst - 1, 1, 1, 1, 1, 1, 1]
        msgs = [m for d in got for m in parse_all(d)]
        assert [m.time_boot_ms for m in msgs] == list(range(n))
        assert [m.get_seq() for m in msgs] == list(range(n))
        assert ep.counters().packets_sent == n
        # The window over and nothing waiting: a group goes directly again, in one datagram.
        now[0] += E._DIRECT_WINDOW_S * 2
        link.send_many([ping(n), ping(n + 1), ping(n + 2)])
        assert not link.queue
        (d,) = recv_udp(gcs, 1)
        assert [m.get_seq() for m in parse_all(d)] == [n, n + 1, n + 2]


def test_a_stream_endpoint_gets_a_group_in_order() -> None:
    port = free_port(socket.SOCK_STREAM)
    ep = open_endpoint(
        f"tcpin:127.0.0.1:{port}", system_id=1, component_id=1, on_message=Inbox()
    ).start()
    client: socket.socket | None = None
    try:
        assert wait_until(lambda: local_address(ep) is not None)
        client = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
        assert wait_until(lambda: bool(ep.links))
        ep.broadcast_many([ping(i) for i in range(5)])  # queued, written by the thread
        data = b""
        deadline = time.monotonic() + DEADLINE_S
        while len(parse_all(data)) < 5 and time.monotonic() < deadline:
            data += client.recv(4096)
        msgs = parse_all(data)
        assert [m.time_boot_ms for m in msgs] == [0, 1, 2, 3, 4]
        assert [m.get_seq() for m in msgs] == [0, 1, 2, 3, 4]
        # (a stream endpoint counts packets as it frames them, bytes as the socket takes them)
        assert wait_until(lambda: ep.counters().bytes_sent == len(data))
        assert ep.counters().packets_sent == 5
    finally:
        if client is not None:
            client.close()
        ep.close(2.0)


def test_a_group_with_no_peer_is_counted_unsent() -> None:
    ep = open_endpoint(
        f"udpin:127.0.0.1:{free_port()}", system_id=1, component_id=1, on_message=Inbox()
    )
    ep.broadcast_many([ping(i) for i in range(3)])  # nobody heard from yet
    assert ep.counters().packets_unsent == 3 and ep.counters().packets_sent == 0
    ep.close(1.0)
