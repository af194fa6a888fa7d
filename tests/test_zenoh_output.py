"""The Zenoh output on a real bridge: a simulated compass on a real pty, the real daemon,
and a second, real zenoh session on 127.0.0.1 (scouting off, explicit endpoints).

Every wait is bounded. Rates and counts come from the simulated device's
configured rate and its own sequence numbers, not from the output's counters.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from waiting import wait_for

from bridge.app.calibration.store import CALIBRATION_DOCUMENT
from bridge.app.sample import DaemonStatus
from bridge.calibration.model import AffineCalibration, Calibration
from bridge.config import load_config
from bridge.daemon import Daemon, build_daemon, build_outputs
from bridge.device import LinkCounters, LinkState
from bridge.mavlink import MavlinkOutput, MavlinkSettings
from bridge.mavlink.dialect import mavlink
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import MOTIONS, PtyCompass
from bridge.storage import StateStore
from bridge.zenoh import schema
from bridge.zenoh.contract import FleetServices
from bridge.zenoh.output import ZenohOutput
from bridge.zenoh.services import fleet_services
from bridge.zenoh.session import ZenohSettings

pytestmark = pytest.mark.integration  # real sockets, processes or threads

DEADLINE_S = 10.0
#: Test sessions and bridges talk over explicit endpoints only: nothing leaves the host.
NO_SCOUTING = (
    ("scouting/multicast/enabled", "false"),
    ("scouting/gossip/enabled", "false"),
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred: Callable[[], bool], timeout: float = DEADLINE_S, what: str = "") -> float:
    """Poll ``pred`` until true; returns the seconds it took; fails after ``timeout``
    (:func:`waiting.wait_for` with this module's deadline by default)."""
    return wait_for(pred, what or repr(pred), timeout)


def peer_config(
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zid: str | None = None,
    mode: str = "peer",
) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    for key, value in NO_SCOUTING:
        cfg.insert_json5(key, value)
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if zid is not None:
        cfg.insert_json5("id", json.dumps(zid))
    return cfg


@contextlib.contextmanager
def peer(**kw: Any) -> Iterator[zenoh.Session]:
    """A second zenoh session (the test's), closed on exit."""
    session = zenoh.open(peer_config(**kw))
    try:
        yield session
    finally:
        session.close()


@dataclass
class Received:
    """Everything a test subscriber got, by key."""

    samples: dict[str, list[zenoh.Sample]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    block: threading.Event | None = None  #: set -> the callback stalls until it is set

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.setdefault(str(sample.key_expr), []).append(sample)
        if self.block is not None:
            self.block.wait(30.0)

    def count(self, key: str) -> int:
        with self.lock:
            return len(self.samples.get(key, []))

    def get(self, key: str) -> list[zenoh.Sample]:
        with self.lock:
            return list(self.samples.get(key, []))

    def docs(self, key: str) -> list[dict[str, Any]]:
        return [json.loads(s.payload.to_bytes()) for s in self.get(key)]


class Bridge:
    """A running bridge: simulated compass on a pty -> daemon -> ZenohOutput (+ other outputs)."""

    def __init__(
        self,
        tmp_path: Path,
        name: str,
        *,
        connect: Sequence[str] = (),
        listen: Sequence[str] = ("tcp/127.0.0.1:0",),
        rate_hz: int = 20,
        motion: str = "turns",
        seed: int = 1,
        overrides: Sequence[tuple[str, str]] = NO_SCOUTING,
        mavlink_port: int | None = None,
        config: Sequence[str] = (),
        **settings: Any,
    ) -> None:
        self.name = name
        self.link_path = tmp_path / f"{name}.tty"
        self.state_dir = tmp_path / f"{name}-state"
        self.sim = PtyCompass(
            make_firmware(seed, motion=MOTIONS[motion](seed)), str(self.link_path)
        )
        self.cfg = load_config(
            None,
            [
                f"device.port={self.link_path}",
                f"device.rate_hz={rate_hz}",
                f"storage.dir={self.state_dir}",
                # Every frame on the sensor streams (the product default caps them at 10 Hz).
                "zenoh.heading_rate_hz=0",
                "zenoh.attitude_rate_hz=0",
                "zenoh.imu_rate_hz=0",
                # MAVLink to a test socket when asked, else nowhere.
                f"mavlink.endpoints=['udpout:127.0.0.1:{mavlink_port}']"
                if mavlink_port
                else "mavlink.endpoints=[]",
                *config,
            ],
            env={},
            hostname=name,
        )
        self.settings = ZenohSettings.from_config(
            self.cfg.zenoh,
            connect=tuple(connect),
            listen=tuple(listen),
            overrides=tuple(overrides),
            **settings,
        )
        self.prefix = self.settings.key_prefix
        self.daemon = build_daemon(self.cfg)
        self.output = ZenohOutput(self.settings, fleet_services(self.daemon.bridge.services))
        outputs: list[Any] = [self.output]
        self.mavlink: MavlinkOutput | None = None
        if mavlink_port:
            self.mavlink = MavlinkOutput(
                MavlinkSettings.from_config(self.cfg), self.daemon.bridge.services
            )
            outputs.insert(0, self.mavlink)
        self.daemon.bridge.pipeline.set_outputs(outputs)

    def key(self, *parts: str) -> str:
        return "/".join((self.prefix, *parts))

    def start(self) -> Bridge:
        self.sim.start()
        self.daemon.start()
        return self

    def stop(self) -> None:
        self.daemon.stop(timeout=5.0)
        self.sim.stop()

    def __enter__(self) -> Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class MavlinkSink:
    """A UDP socket the bridge's MAVLink output sends to; counts what it decodes, by type."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = int(self.sock.getsockname()[1])
        self.parser = mavlink.MAVLink(None)
        self.counts: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            for msg in self.parser.parse_buffer(data) or []:
                t = msg.get_type()
                self.counts[t] = self.counts.get(t, 0) + 1

    def count(self, mtype: str) -> int:
        return self.counts.get(mtype, 0)

    def __enter__(self) -> MavlinkSink:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


def contiguous(seqs: Sequence[int]) -> bool:
    return list(seqs) == list(range(seqs[0], seqs[0] + len(seqs)))


# ---------------------------------------------------------------------------
# Publications
# ---------------------------------------------------------------------------


def test_every_publication_arrives_with_a_valid_schema(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with peer(listen=[f"tcp/127.0.0.1:{port}"]) as sub:
        _s = sub.declare_subscriber("fleet/**", rx)
        with Bridge(tmp_path, "b1", connect=[f"tcp/127.0.0.1:{port}"]) as b:
            streams = {
                "heading": schema.HEADING,
                "attitude": schema.ATTITUDE,
                "imu": schema.IMU,
                "status": schema.STATUS,
            }
            wait_until(
                lambda: all(rx.count(b.key(k)) >= (2 if k == "status" else 20) for k in streams),
                what="20 samples of each stream and 2 statuses",
            )

            # frame_rate_hz is over the last 2 s: a status from the first seconds also
            # spans the time before the compass streamed, so wait for one past that.
            def settled() -> bool:
                live = [d for d in rx.docs(b.key("status")) if d["link"]["state"] == "streaming"]
                return bool(live) and live[-1]["uptime_s"] >= live[0]["uptime_s"] + 2.5

            wait_until(settled, what="a status 2.5 s into streaming")
        for stream, name in streams.items():
            for sample in rx.get(b.key(stream)):
                assert str(sample.encoding) == f"application/json;{name}@1"
                doc = schema.parse(sample.payload.to_bytes(), name)
                assert doc["schema"] == name and doc["version"] == 1
        # The sensor streams carry the device's frame counter: no frame skipped.
        seqs = [d["seq"] for d in rx.docs(b.key("heading"))]
        assert contiguous(seqs)
        assert [d["seq"] for d in rx.docs(b.key("attitude"))] == seqs
        # The zenoh timestamp travels on the sample and, as text, in the document.
        h = rx.get(b.key("heading"))[-1]
        assert h.timestamp is not None
        assert (
            json.loads(h.payload.to_bytes())["zenoh_time"] == h.timestamp.to_string_rfc3339_lossy()
        )
        # The IMU stream carries the frame's raw counts beside the calibrated vectors.
        imu = rx.docs(b.key("imu"))[-1]
        assert imu["raw"]["mag"] is not None and imu["raw"]["accel"] is not None
        # The status reports the live link and the device's frame rate (frames over the
        # host's clock, so a busy machine moves it: its arithmetic is checked on set times
        # in test_zenoh_schema.py; here, that it is the frames' rate, not the documents').
        last = rx.docs(b.key("status"))[-1]
        assert last["link"]["state"] == "streaming"
        assert 10.0 < last["link"]["frame_rate_hz"] < 40.0  # 20 Hz asked; not 60 (3 streams)


def test_the_pipeline_puts_each_sample_before_publish_returns(tmp_path: Path) -> None:
    """No hand-over to another thread (a wake-up per sample): the reader thread puts them."""
    with Bridge(tmp_path, "b0") as b:
        wait_until(b.output.connected.is_set, what="the bridge's session")
        calls: list[tuple[int, str]] = []
        publish = b.output.publish

        def watched(sample: Any) -> None:
            before = b.output.counters.published.get("heading", 0)
            publish(sample)
            after = b.output.counters.published.get("heading", 0)
            calls.append((after - before, threading.current_thread().name))

        b.output.publish = watched  # type: ignore[method-assign]  # instrumented on purpose
        wait_until(lambda: len(calls) >= 10, what="ten samples")
        # Heading goes out for every frame here (cap 0): each call put exactly one.
        assert [n for n, _ in calls[:10]] == [1] * 10
        assert {name for _, name in calls} == {"compass-link-reader"}


def test_a_document_that_fails_to_build_holds_back_no_other_stream(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A builder's bug (injected here: the attitude document raises) is counted and said
    once; the heading and imu documents of the same sample still go out."""

    def broken(sample: Any, times: Any) -> dict[str, Any]:
        raise RuntimeError("attitude builder bug")

    docs = tuple((k, broken if k == "attitude" else b) for k, b in schema.SENSOR_DOCS)
    monkeypatch.setattr(schema, "SENSOR_DOCS", docs)
    with Bridge(tmp_path, "b0") as b:
        wait_until(lambda: b.output.counters.published.get("imu", 0) >= 5, what="imu documents")
        published = b.output.counters.published
        assert published.get("heading", 0) >= 5 and "attitude" not in published
        assert b.output.counters.put_errors >= 5


def test_status_is_published_at_once_when_the_link_changes(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with (
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as sub,
        Bridge(tmp_path, "b2", connect=[f"tcp/127.0.0.1:{port}"], status_period_s=30.0) as b,
    ):
        _s = sub.declare_subscriber(b.key("status"), rx)
        _e = sub.declare_subscriber(b.key("events"), rx)

        def states() -> list[str]:
            return [d["link"]["state"] for d in rx.docs(b.key("status"))]

        wait_until(lambda: "streaming" in states(), what="a streaming status")
        n = len(states())
        b.sim.unplug(2.0)  # pull the cable for 2 s
        # With a 30 s period only a change can explain a new status this soon.
        took = wait_until(lambda: len(states()) > n and states()[-1] != "streaming", 8.0)
        assert took < 5.0
        wait_until(lambda: states()[-1] == "streaming", 10.0, "the link back")
        # The daemon's link event reaches <prefix>/events with its schema.
        wait_until(lambda: rx.count(b.key("events")) >= 1, what="a link event")
        events = [schema.parse(e.payload.to_bytes(), schema.EVENT) for e in rx.get(b.key("events"))]
        lost = [e for e in events if e["kind"] == "link.lost"]
        assert lost and lost[0]["severity"] == "error"


def test_a_link_state_change_without_an_event_is_published_at_once() -> None:
    """The publisher no longer reads the status twice a second to find a change: the
    link's state changes are told to it (``subscribe_link_state``; opening a port again
    comes with no event), and the status goes out at once. A 30 s period: only the notice
    can explain a new status this soon."""
    port = free_port()
    state = [LinkState.OPENING]
    follow: list[Callable[[Any], None]] = []

    def status() -> DaemonStatus:
        return DaemonStatus("/dev/ttyX", state[0], LinkCounters(), 0, 0, "stored")

    def subscribe(fn: Callable[[Any], None]) -> Callable[[], None]:
        follow.append(fn)
        return lambda: follow.remove(fn)

    services = FleetServices(status=status, subscribe_link_state=subscribe)
    settings = ZenohSettings(
        connect=(f"tcp/127.0.0.1:{port}",), key_prefix="test/notice", status_period_s=30.0,
        overrides=NO_SCOUTING,
    )  # fmt: skip
    out = ZenohOutput(settings, services)
    rx = Received()
    with peer(listen=[f"tcp/127.0.0.1:{port}"]) as sub:
        _s = sub.declare_subscriber("test/notice/status", rx)
        out.start()
        try:

            def states() -> list[str]:
                return [d["link"]["state"] for d in rx.docs("test/notice/status")]

            # Routed both ways once a query is answered (the first status may have gone
            # out before the subscriber was known: it is not waited for).
            wait_until(lambda: bool(_query(sub, "test/notice/status", 0.5)), what="a route")
            assert len(follow) == 1
            n = len(states())
            for new in (LinkState.STREAMING, LinkState.ABSENT, LinkState.OPENING):
                state[0] = new
                follow[0](new)

                def told_last(v: str = new.value) -> bool:
                    return states()[-1:] == [v]

                wait_until(told_last, what=f"a {new.value} status")
            # (The first status, "opening", may still have been on its way when n was read.)
            told = ["streaming", "absent", "opening"]
            assert states()[n:] in (told, ["opening", *told])
        finally:
            out.close(5.0)
    assert not follow  # unsubscribed on close


# ---------------------------------------------------------------------------
# Queries and liveliness
# ---------------------------------------------------------------------------


def _query(session: zenoh.Session, key: str, timeout: float = 3.0) -> list[zenoh.Reply]:
    return list(session.get(key, timeout=timeout))


def test_queryables_answer_status_and_calibration(tmp_path: Path) -> None:
    # A calibration on disk, as the calibrator stores it (with its report).
    stored = Calibration(mag=AffineCalibration(offset=(0.01, -0.02, 0.03)))
    state_dir = tmp_path / "b3-state"
    StateStore(str(state_dir)).save(
        CALIBRATION_DOCUMENT,
        {"calibration": stored.to_dict(), "report": {"method": "ellipsoid", "fitness_mG": 3.5}},
    )
    port = free_port()
    with (
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        MavlinkSink() as gcs,
        Bridge(tmp_path, "b3", connect=[f"tcp/127.0.0.1:{port}"], mavlink_port=gcs.port) as b,
    ):
        wait_until(b.output.connected.is_set, what="the bridge's session")

        def status_ok() -> bool:
            replies = _query(s, b.key("status"), 1.0)
            return bool(replies) and replies[0].ok is not None

        wait_until(status_ok, what="a status reply")
        (reply,) = _query(s, b.key("status"))
        assert reply.ok is not None
        assert str(reply.ok.encoding) == schema.encoding_text(schema.STATUS)
        doc = schema.parse(reply.ok.payload.to_bytes(), schema.STATUS)
        assert doc["link"]["port"] == str(b.link_path)
        assert doc["calibration"]["source"] == "stored"

        (reply,) = _query(s, b.key("calibration"))
        assert reply.ok is not None
        cal = schema.parse(reply.ok.payload.to_bytes(), schema.CALIBRATION)
        assert Calibration.from_dict(cal["calibration"]) == stored
        assert cal["report"]["fitness_mG"] == 3.5

        # A wildcard query reaches every queryable of the bridge (and never a command).
        # The parameter table is the MAVLink output's: the same names and values.
        (reply,) = _query(s, b.key("params"))
        assert reply.ok is not None
        params = schema.parse(reply.ok.payload.to_bytes(), schema.PARAMS)["params"]
        assert b.mavlink is not None
        assert params == pytest.approx(b.daemon.bridge.params.values())
        # ArduPilot adds COMPASS_OFS to the raw field (ours subtracts the offset): 0.01 G -> -10 mG.
        assert params["COMPASS_OFS_X"] == pytest.approx(-10.0, abs=0.01)

        keys = sorted(str(r.ok.key_expr) for r in _query(s, "fleet/**") if r.ok is not None)
        assert keys == [b.key("calibration"), b.key("params"), b.key("status")]


def test_liveliness_token_appears_and_vanishes(tmp_path: Path) -> None:
    port = free_port()
    seen: list[tuple[str, bool]] = []
    with peer(listen=[f"tcp/127.0.0.1:{port}"]) as s:

        def on_token(sample: zenoh.Sample) -> None:
            seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        _l = s.liveliness().declare_subscriber("fleet/**", on_token, history=True)
        b = Bridge(tmp_path, "b4", connect=[f"tcp/127.0.0.1:{port}"]).start()
        try:
            wait_until(lambda: (b.prefix, True) in seen, what="the token")
            alive = [
                str(r.ok.key_expr) for r in s.liveliness().get("fleet/**", timeout=2.0) if r.ok
            ]
            assert alive == [b.prefix]
        finally:
            b.stop()
        wait_until(lambda: (b.prefix, False) in seen, 5.0, "the token to vanish")
        assert not [r for r in s.liveliness().get("fleet/**", timeout=1.0) if r.ok]


# ---------------------------------------------------------------------------
# Failures: the peer goes away, a subscriber stalls, endpoints are bad
# ---------------------------------------------------------------------------


def test_publishing_resumes_within_2s_of_the_peer_returning(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with (
        MavlinkSink() as gcs,
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
        MavlinkSink() as gcs,
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


# ---------------------------------------------------------------------------
# Remote calibration and access control
# ---------------------------------------------------------------------------

TRUSTED_ZID = "a11ce"
UNTRUSTED_ZID = "b0b"


def _command(session: zenoh.Session, key: str, args: dict[str, Any] | None = None) -> list[Any]:
    """Send a command; returns the decoded result documents (empty: no answer)."""
    payload = json.dumps(args).encode() if args is not None else None
    out = []
    for r in session.get(key, payload=payload, timeout=3.0):
        assert r.ok is not None, r.err.payload.to_string() if r.err else "no reply"
        assert str(r.ok.encoding) == schema.encoding_text(schema.COMMAND_RESULT)
        out.append(schema.parse(r.ok.payload.to_bytes(), schema.COMMAND_RESULT))
    return out


def test_remote_calibration_is_off_by_default(tmp_path: Path) -> None:
    port = free_port()
    with (
        Bridge(tmp_path, "c1", listen=[f"tcp/127.0.0.1:{port}"]) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        assert _query(s, b.key("cmd/calibration/start"), 1.0) == []
        assert not b.daemon.bridge.calibrator.snapshot().running


def test_remote_calibration_drives_the_calibrator(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with (
        Bridge(
            tmp_path,
            "c2",
            listen=[f"tcp/127.0.0.1:{port}"],
            motion="tumble",
            remote_calibration=True,
        ) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        _e = s.declare_subscriber(b.key("events"), rx)
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        # A fleet-wide wildcard query reaches the command queryables but starts nothing.
        _query(s, "fleet/**", 1.0)
        assert b.daemon.bridge.calibrator.snapshot().mode is None

        (bad,) = _command(s, b.key("cmd/calibration/start"), {"what": "everything"})
        assert bad["ok"] is False and "what must be one of" in bad["message"]

        (started,) = _command(s, b.key("cmd/calibration/start"), {"what": "mag"})
        assert started["ok"] is True
        assert started["detail"]["result"] == "in_progress"
        assert b.daemon.bridge.calibrator.snapshot().running
        (again,) = _command(s, b.key("cmd/calibration/start"))
        assert again["ok"] is False and again["detail"]["result"] == "denied"

        (cancelled,) = _command(s, b.key("cmd/calibration/cancel"))
        assert cancelled["ok"] is True
        assert not b.daemon.bridge.calibrator.snapshot().running
        # The calibrator's own events reached the bus, in order.
        wait_until(
            lambda: "calibration.cancelled" in [d["kind"] for d in rx.docs(b.key("events"))],
            what="the cancel event",
        )
        kinds = [d["kind"] for d in rx.docs(b.key("events"))]
        assert kinds.index("calibration.started") < kinds.index("calibration.cancelled")


def test_access_control_denies_cmd_to_an_untrusted_peer(tmp_path: Path) -> None:
    # docs/zenoh.md's recipe, with peers told apart by zenoh id (on a real network:
    # usernames or certificate common names).
    acl = tmp_path / "zenoh-acl.json5"
    acl.write_text(
        json.dumps(
            {
                "access_control": {
                    "enabled": True,
                    "default_permission": "allow",
                    "rules": [
                        {
                            "id": "no-remote-calibration",
                            "permission": "deny",
                            "flows": ["ingress"],
                            "messages": ["query"],
                            "key_exprs": ["fleet/*/compass/cmd/**"],
                        }
                    ],
                    "subjects": [{"id": "viewers", "zids": [UNTRUSTED_ZID]}],
                    "policies": [{"rules": ["no-remote-calibration"], "subjects": ["viewers"]}],
                }
            }
        )
    )
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with (
        Bridge(
            tmp_path,
            "c3",
            listen=[endpoint],
            motion="tumble",
            remote_calibration=True,
            config_file=str(acl),
        ) as b,
        peer(connect=[endpoint], zid=UNTRUSTED_ZID) as viewer,
        peer(connect=[endpoint], zid=TRUSTED_ZID) as operator,
    ):
        for s in (viewer, operator):

            def reachable(s: zenoh.Session = s) -> bool:
                return bool(_query(s, b.key("status"), 0.5))

            wait_until(reachable, what="the bridge")
        # The viewer still sees the bridge, but its command never reaches the calibrator.
        assert _command(viewer, b.key("cmd/calibration/start")) == []
        assert b.daemon.bridge.calibrator.snapshot().mode is None
        (reply,) = _command(operator, b.key("cmd/calibration/start"))
        assert reply["ok"] is True and b.daemon.bridge.calibrator.snapshot().running
        assert _command(viewer, b.key("cmd/calibration/cancel")) == []
        assert b.daemon.bridge.calibrator.snapshot().running  # the viewer's cancel did nothing
        (reply,) = _command(operator, b.key("cmd/calibration/cancel"))
        assert reply["ok"] is True and not b.daemon.bridge.calibrator.snapshot().running


# ---------------------------------------------------------------------------
# Wiring: the daemon builds the output from [zenoh]
# ---------------------------------------------------------------------------


def test_the_daemon_builds_the_zenoh_output_from_the_configuration(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "w.tty"
    base = [f"device.port={link}", "device.rate_hz=20", f"storage.dir={tmp_path / 'state'}"]
    off = load_config(
        None, [*base, "zenoh.enabled=false", "mavlink.endpoints=[]"], env={}, hostname="w1"
    )
    assert build_outputs(off, build_daemon(off), console=False) == []
    rx = Received()
    with (
        PtyCompass(make_firmware(3), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        MavlinkSink() as gcs,
    ):
        cfg = load_config(
            None,
            [
                *base,
                f"zenoh.connect=['tcp/127.0.0.1:{port}']",
                f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
                "zenoh.key_prefix=wired/<hostname>/compass",
                "zenoh.heading_rate_hz=5",
                "zenoh.attitude_rate_hz=0",  # every frame (the default caps it at 10 Hz)
                "zenoh.mavlink_mirror=true",
                f"mavlink.endpoints=['udpout:127.0.0.1:{gcs.port}']",
            ],
            env={},
            hostname="w1",
        )
        _s = s.declare_subscriber("wired/**", rx)
        _m = s.declare_subscriber("mavlink/**", rx)
        daemon = build_daemon(cfg, ())
        daemon.bridge.pipeline.set_outputs(build_outputs(cfg, daemon, console=False))
        assert sorted(o.name for o in daemon.bridge.pipeline.outputs) == ["mavlink", "zenoh"]
        daemon.start()
        try:
            key = "wired/w1/compass"
            wait_until(lambda: rx.count(f"{key}/attitude") >= 20, what="attitudes")
            # The mirror found the MAVLink output the configuration built.
            wait_until(lambda: rx.count("mavlink/1/1/HEARTBEAT") >= 1, what="a mirrored HEARTBEAT")
            # 3 s of the device's frames, counted by its own sequence numbers (not timed: a
            # busy machine delays them, it does not change how many there are)
            a0 = rx.count(f"{key}/attitude")
            wait_until(lambda: rx.count(f"{key}/attitude") >= a0 + 60, what="60 more attitudes")
        finally:
            daemon.stop()
    seqs = [d["seq"] for d in rx.docs(f"{key}/attitude")][a0:]
    assert contiguous(seqs)  # every frame of the 20 Hz device
    first, last = seqs[0], seqs[-1]
    span = last - first + 1
    headings = [d for d in rx.docs(f"{key}/heading") if first <= d["seq"] <= last]
    # capped by zenoh.heading_rate_hz: 5 of the device's 20 frames a second (within 1 Hz)
    assert len(headings) == pytest.approx(span * 5.0 / 20.0, abs=span / 20.0)


# ---------------------------------------------------------------------------
# MAVLink mirror
# ---------------------------------------------------------------------------


def test_mavlink_mirror_republishes_what_the_bridge_sends(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with (
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        MavlinkSink() as gcs,
    ):
        _s = s.declare_subscriber("mavlink/**", rx)
        with Bridge(
            tmp_path,
            "mm",
            connect=[f"tcp/127.0.0.1:{port}"],
            mavlink_port=gcs.port,
            mavlink_mirror=True,
        ) as b:
            assert b.mavlink is not None
            sysid, compid = b.mavlink.identity.system_id, b.mavlink.identity.component_id
            base = f"mavlink/{sysid}/{compid}"
            wait_until(
                lambda: rx.count(f"{base}/HEARTBEAT") >= 2 and rx.count(f"{base}/ATTITUDE") >= 10,
                what="mirrored HEARTBEAT and ATTITUDE",
            )
        # Every message type the ground station got over UDP was mirrored too.
        mirrored = {k.rsplit("/", 1)[1] for k in rx.samples}
        assert set(gcs.counts) <= mirrored, set(gcs.counts) - mirrored
        hb = rx.docs(f"{base}/HEARTBEAT")[-1]
        assert str(rx.get(f"{base}/HEARTBEAT")[-1].encoding) == "application/json"
        assert hb["header"]["system_id"] == sysid and hb["header"]["component_id"] == compid
        assert hb["header"]["message_id"] == 0
        assert hb["message"]["type"] == "HEARTBEAT"
        assert hb["message"]["mavtype"] == {"type": "MAV_TYPE_GENERIC"}  # standalone role
        assert hb["message"]["autopilot"] == {"type": "MAV_AUTOPILOT_GENERIC"}
        att = rx.docs(f"{base}/ATTITUDE")[-1]["message"]
        assert att["type"] == "ATTITUDE"
        assert all(isinstance(att[f], float) for f in ("roll", "pitch", "yaw"))
        assert -3.1416 <= att["yaw"] <= 3.1416


# ---------------------------------------------------------------------------
# Reload (SIGHUP): the service swaps outputs; zenoh follows
# ---------------------------------------------------------------------------


def _service(cfg: Any, reload_to: Any) -> Any:
    from bridge.daemon import Service

    def make_outputs(c: Any, d: Daemon) -> list[Any]:
        return build_outputs(c, d, console=False)

    return Service(cfg, make_outputs, reload_config=lambda: reload_to, env={})


def _wired_config(tmp_path: Path, link: Path, *extra: str) -> Any:
    return load_config(
        None,
        [
            f"device.port={link}",
            "device.rate_hz=20",
            f"storage.dir={tmp_path / 'state'}",
            *extra,
        ],
        env={},
        hostname="r1",
    )


def test_after_a_mavlink_reload_the_mirror_follows_the_new_output(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "r.tty"
    rx = Received()
    with (
        PtyCompass(make_firmware(5), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        MavlinkSink() as gcs,
    ):
        common = (
            f"zenoh.connect=['tcp/127.0.0.1:{port}']",
            f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
            "zenoh.mavlink_mirror=true",
            f"mavlink.endpoints=['udpout:127.0.0.1:{gcs.port}']",
        )
        cfg1 = _wired_config(tmp_path, link, *common)
        cfg2 = _wired_config(tmp_path, link, *common, "mavlink.system_id=7")
        svc = _service(cfg1, cfg2)
        _m = s.declare_subscriber("mavlink/**", rx)
        svc.daemon.start()
        try:
            zenoh_out = next(o for o in svc.daemon.bridge.pipeline.outputs if o.name == "zenoh")
            wait_until(lambda: rx.count("mavlink/1/1/HEARTBEAT") >= 1, what="system 1")
            assert svc.reload()
            # Only the MAVLink output restarted; the zenoh output re-attached its mirror.
            assert (
                next(o for o in svc.daemon.bridge.pipeline.outputs if o.name == "zenoh")
                is zenoh_out
            )
            wait_until(lambda: rx.count("mavlink/7/1/HEARTBEAT") >= 2, 6.0, "system 7")
        finally:
            svc.daemon.stop()


def test_a_zenoh_reload_moves_the_bridge_to_its_new_prefix(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "r.tty"
    seen: list[tuple[str, bool]] = []
    rx = Received()
    with (
        PtyCompass(make_firmware(6), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        common = (
            f"zenoh.connect=['tcp/127.0.0.1:{port}']",
            f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
            "mavlink.endpoints=[]",
        )
        cfg1 = _wired_config(tmp_path, link, *common, "zenoh.key_prefix=old/<hostname>")
        cfg2 = _wired_config(tmp_path, link, *common, "zenoh.key_prefix=new/<hostname>")
        svc = _service(cfg1, cfg2)

        def on_token(sample: zenoh.Sample) -> None:
            seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        _l = s.liveliness().declare_subscriber("**", on_token, history=True)
        _s = s.declare_subscriber("*/r1/heading", rx)
        svc.daemon.start()
        try:
            wait_until(lambda: rx.count("old/r1/heading") >= 3, what="the old prefix")
            assert svc.reload()
            wait_until(lambda: rx.count("new/r1/heading") >= 3, 6.0, "the new prefix")
            wait_until(lambda: ("old/r1", False) in seen, 5.0, "the old token to vanish")
            assert ("new/r1", True) in seen
        finally:
            svc.daemon.stop()
