"""The Zenoh tests' rig: a bridge with its Zenoh output on 127.0.0.1, and test sessions.

:class:`Bridge` is a simulated compass on a real pty, the real daemon and a real
:class:`~bridge.zenoh.output.ZenohOutput`; :func:`peer` a second, real zenoh session
(scouting off, explicit endpoints); :class:`Received` what a test subscriber got;
:class:`~service_harness.GroundStation` is the UDP socket a bridge's MAVLink output sends
to. Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import io
import json
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from waiting import wait_for

from benchmarks.procstat import free_port as free_port  # the tests' one (TCP)
from bridge.config import load_config
from bridge.daemon import build_daemon
from bridge.mavlink import MavlinkOutput, MavlinkSettings
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import MOTIONS, PtyCompass
from bridge.zenoh import schema
from bridge.zenoh.output import ZenohOutput
from bridge.zenoh.services import fleet_services
from bridge.zenoh.session import ZenohSettings

DEADLINE_S = 10.0
#: Test sessions and bridges talk over explicit endpoints only: nothing leaves the host.
NO_SCOUTING = (
    ("scouting/multicast/enabled", "false"),
    ("scouting/gossip/enabled", "false"),
)


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


def contiguous(seqs: Sequence[int]) -> bool:
    return list(seqs) == list(range(seqs[0], seqs[0] + len(seqs)))


def _query(session: zenoh.Session, key: str, timeout: float = 3.0) -> list[zenoh.Reply]:
    return list(session.get(key, timeout=timeout))


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


def status_of_a_streaming_bridge(
    tmp: Path, name: str
) -> tuple[Bridge, int, int, dict[str, Any], str]:
    """``compass-bridge status`` asking a bridge ``name`` (20 Hz, listening on
    ``tcp/127.0.0.1:port``) once 40 frames went through it: the bridge (stopped since),
    the port, the exit code and ``--json`` document, then the text for people."""
    from bridge.tools.status import run_status
    from bridge.zenoh.monitor import MonitorOptions

    port = free_port()
    with Bridge(tmp, name, listen=[f"tcp/127.0.0.1:{port}"], rate_hz=20) as b:
        wait_until(lambda: b.daemon.bridge.pipeline.samples >= 40, 15.0, "frames flowing")
        opts = MonitorOptions(keyexpr="fleet/**/status", connect=(f"tcp/127.0.0.1:{port}",))
        out = io.StringIO()
        code = run_status(opts, out, as_json=True, timeout=5.0)
        human = io.StringIO()
        run_status(opts, human, timeout=5.0)
    return b, port, code, json.loads(out.getvalue()), human.getvalue()
