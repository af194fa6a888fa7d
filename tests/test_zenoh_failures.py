"""The Zenoh output when things go wrong: the peer goes away and returns, a subscriber
stalls, endpoints or the configuration are bad, the default port is taken. A real bridge
and real zenoh sessions on 127.0.0.1 (tests/zenoh_rig.py); every wait is bounded.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from service_harness import GroundStation
from zenoh_rig import Bridge, Received, contiguous, free_port, peer, wait_until

pytestmark = pytest.mark.integration  # real sockets, processes or threads


# ---------------------------------------------------------------------------
# Failures: the peer goes away, a subscriber stalls, endpoints are bad
# ---------------------------------------------------------------------------


def test_publishing_resumes_within_2s_of_the_peer_returning(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with (
        GroundStation() as gcs,
        Bridge(tmp_path, "b5", connect=[endpoint], rate_hz=20, mavlink_port=gcs.port) as b,
    ):
        rx = Received()
        with peer(listen=[endpoint]) as s:
            _s = s.declare_subscriber(b.key("heading"), rx)
            wait_until(lambda: rx.count(b.key("heading")) >= 5, what="headings")
            wait_until(lambda: gcs.count("ATTITUDE") >= 5, what="MAVLink ATTITUDE")
        # The peer is gone. Neither the pipeline nor MAVLink may notice: over 2 s of the
        # device's own frames (its count, not the wall clock, which a busy machine stretches)
        # the pipeline takes every frame and MAVLink sends its ATTITUDE at BRG_SR_ATT
        # (default 10 Hz, 1 in 2 frames) whatever zenoh does.
        fw = b.sim.firmware
        f0, before, mav_before = (
            fw.frames_sent,
            b.daemon.bridge.pipeline.samples,
            gcs.count("ATTITUDE"),
        )
        wait_until(lambda: fw.frames_sent >= f0 + 40, what="2 s of the device's frames")
        sent = fw.frames_sent - f0
        wait_until(
            lambda: b.daemon.bridge.pipeline.samples - before >= sent,
            1.0,
            "the pipeline to take every frame",
        )
        assert b.mavlink is not None
        att_hz = b.daemon.bridge.params.get("BRG_SR_ATT")
        wanted = 0.8 * att_hz * sent / 20.0  # (0.5 s for the last datagrams to be read)
        wait_until(lambda: gcs.count("ATTITUDE") - mav_before >= wanted, 0.5, "ATTITUDE")
        rx2 = Received()
        with peer(listen=[endpoint]) as s:
            t0 = time.monotonic()
            _s = s.declare_subscriber(b.key("heading"), rx2)
            took = wait_until(lambda: rx2.count(b.key("heading")) >= 1, 5.0, "headings again")
            assert took <= 2.0, f"publishing resumed only after {took:.2f} s"
            assert time.monotonic() - t0 <= 2.5


def test_a_stalled_subscriber_does_not_slow_the_daemon(tmp_path: Path) -> None:
    """One subscriber stops reading; the serial side and a healthy subscriber carry on at 100 Hz."""
    stalled_port, healthy_port = free_port(), free_port()
    # Small socket buffers make the stall bite at once instead of after megabytes.
    small = "#so_rcvbuf=4096;so_sndbuf=4096"
    block = threading.Event()
    stalled = Received(block=block)
    healthy = Received()
    with (
        peer(listen=[f"tcp/127.0.0.1:{stalled_port}{small}"]) as s1,
        peer(listen=[f"tcp/127.0.0.1:{healthy_port}"]) as s2,
        GroundStation() as gcs,
    ):
        _a = s1.declare_subscriber("fleet/**", stalled)
        _b = s2.declare_subscriber("fleet/**", healthy)
        try:
            with Bridge(
                tmp_path,
                "b6",
                connect=[f"tcp/127.0.0.1:{stalled_port}{small}", f"tcp/127.0.0.1:{healthy_port}"],
                rate_hz=100,
                mavlink_port=gcs.port,
            ) as b:
                key = b.key("heading")
                wait_until(lambda: healthy.count(key) >= 50, what="the healthy subscriber")
                wait_until(lambda: b.daemon.bridge.status().counters.attitude_frames > 0)
                # Measure over a window well after the stall began: 3 s of the device's own
                # frames (its count, not the wall clock, which a busy machine stretches).
                fw = b.sim.firmware
                f0 = fw.frames_sent
                wait_until(lambda: fw.frames_sent >= f0 + 50, what="0.5 s of frames")
                f0, n0, h0 = fw.frames_sent, b.daemon.bridge.pipeline.samples, healthy.count(key)
                m0 = gcs.count("ATTITUDE")
                wait_until(lambda: fw.frames_sent >= f0 + 300, what="3 s of the device's frames")
                sent = fw.frames_sent - f0
                # the pipeline takes every frame of the 100 Hz device (1 s for the
                # last ones in flight), MAVLink sends its ATTITUDE at BRG_SR_ATT
                wait_until(
                    lambda: b.daemon.bridge.pipeline.samples - n0 >= sent, 1.0, "every frame"
                )
                assert b.mavlink is not None
                att_hz = b.daemon.bridge.params.get("BRG_SR_ATT")
                wanted = 0.9 * att_hz * sent / 100.0
                wait_until(lambda: gcs.count("ATTITUDE") - m0 >= wanted, 0.5, "ATTITUDE")
                n1, h1 = b.daemon.bridge.pipeline.samples, healthy.count(key)
                assert h1 - h0 >= 0.95 * (n1 - n0), "the healthy subscriber lost headings"
                seqs = [d["seq"] for d in healthy.docs(key)]
                assert contiguous(seqs[len(seqs) // 2 :])
                # The stall was real: the blocked subscriber got almost nothing.
                assert stalled.count(key) < 0.1 * healthy.count(key)
                # zenoh dropped the stalled peer's copies; for the bridge nothing failed.
                assert b.output.counters.put_errors == 0
        finally:
            block.set()


def test_bad_endpoints_and_config_never_stop_the_bridge(tmp_path: Path) -> None:
    refused = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there
    with Bridge(
        tmp_path,
        "b7",
        mode="client",
        connect=[refused],
        config_file=str(tmp_path / "missing.json5"),
    ) as b:
        wait_until(lambda: b.output.counters.open_failures >= 2, what="retried opens")
        # 20 Hz carries on: 1 s of the device's frames all taken (counted, not timed)
        fw = b.sim.firmware
        f0, before = fw.frames_sent, b.daemon.bridge.pipeline.samples
        wait_until(lambda: fw.frames_sent >= f0 + 20, what="1 s of the device's frames")
        sent = fw.frames_sent - f0
        wait_until(
            lambda: b.daemon.bridge.pipeline.samples - before >= sent, 1.0, "every frame taken"
        )
        assert not b.output.connected.is_set()
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 3.0  # and it still stops promptly


def test_a_client_joins_its_router_when_it_appears(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with Bridge(tmp_path, "b8", mode="client", connect=[endpoint]) as b:
        wait_until(lambda: b.output.counters.open_failures >= 1, what="a failed open")
        rx = Received()
        with peer(listen=[endpoint], mode="router") as router:
            _s = router.declare_subscriber(b.key("heading"), rx)
            took = wait_until(lambda: rx.count(b.key("heading")) >= 1, 5.0, "headings")
            assert took <= 2.5  # a failed open is retried after 0.5 s, each try waits <= 1 s


def test_a_taken_default_port_falls_back_to_no_listener(tmp_path: Path) -> None:
    taken = free_port()
    port = free_port()
    rx = Received()
    with (
        peer(listen=[f"tcp/127.0.0.1:{taken}"]),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        _s = s.declare_subscriber("fleet/**", rx)
        with Bridge(
            tmp_path,
            "b9",
            connect=[f"tcp/127.0.0.1:{port}"],
            listen=(),
            default_listen=(f"tcp/127.0.0.1:{taken}",),
        ) as b:
            wait_until(lambda: rx.count(b.key("heading")) >= 3, what="headings")
            assert b.output.counters.open_failures == 0
