"""Frames per second of CPU through the bridge's per-frame path (``python -m benchmarks pipeline``).

Two figures, both frames per second of *process* CPU time (every thread of this
process, zenoh's native ones included), best of ``repeat`` runs, the same
``$PGMRA`` lines (:func:`benchmarks.mavlink.frame_lines`: a drawn, uncalibrated
unit at random attitudes):

* :func:`shipped` -- **throughput**, target 10 000: the daemon's own path at the
  shipped configuration. Each frame's bytes go into the link's state machine
  (:meth:`bridge.protocol.link.LinkMachine.receive`: decode, sequence tracking)
  at the compass's top rate (100 Hz on the frames' clock), and every frame it
  returns into :meth:`bridge.app.pipeline.Pipeline.on_frame`, which hands the
  sample to the running outputs the configuration builds
  (:func:`bridge.daemon.build_outputs`): MAVLink on a real ``udpout`` endpoint,
  Zenoh on a session listening on 127.0.0.1 with a subscriber in a child
  process (the fleet software's side, whose CPU is not the bridge's), both at
  the shipped stream rates
  (config/compass-bridge.toml: ATTITUDE 10 Hz ..., Zenoh 10 Hz). What the
  daemon spends for each frame of a 100 Hz compass, its threads included, but
  with the caches warm: frames come back to back (the cold figure is
  :mod:`benchmarks.cold`'s).
* :func:`every_stream` -- **throughput_every_stream**, no target: every MAVLink
  sample stream encoded and framed and the three Zenoh documents put for
  *every* frame, which no configuration can ask of the daemon (MAVLink stream
  rates stop at 50 Hz). Most of it is pymavlink's packing, the documents' float
  formatting and zenoh's transport (docs/performance.md).
"""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.figures import Figure, Step, no_step, process_cpu
from benchmarks.procstat import free_port, stop_child

TARGET_FPS = 10000.0
#: The frames' clock: the compass's top rate, as at ``[device] rate_hz = 100``.
FRAME_RATE_HZ = 100.0


def _zenoh_config(*, listen: str | None = None, connect: str | None = None) -> Any:
    import json

    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    cfg.insert_json5("connect/endpoints", json.dumps([connect] if connect else []))
    return cfg


def _figure(
    name: str,
    target: float | None,
    frames: int,
    cpu_s: float,
    wall_s: float,
    detail: dict[str, Any],
) -> Figure:
    """Frames per second of CPU (the best run's ``cpu_s``), and per second of wall clock."""
    return Figure(
        name,
        frames / cpu_s if cpu_s > 0 else math.inf,
        "frames/s (process CPU)",
        target,
        lower_is_better=False,
        detail={
            "frames": frames,
            "wall_fps": round(frames / wall_s, 1) if wall_s > 0 else None,
            **detail,
        },
    )


def _lines(data: bytes) -> list[bytes]:
    """``data`` cut after every line end: one read a frame, as the reader gets them at 100 Hz
    when each frame is read as it comes (the daemon reads several at once between outputs)."""
    return [line + b"\n" for line in data.split(b"\n") if line]


def _subscribe(endpoint: str, keys: str) -> None:
    """The fleet software's side (``python -m benchmarks.throughput ENDPOINT KEYS``, a child
    process so its CPU is not counted as the bridge's): counts the documents by the key's
    last chunk and answers every line on stdin with the counts as JSON."""
    import zenoh

    counts: dict[str, int] = {}

    def on(s: Any) -> None:
        k = str(s.key_expr).rsplit("/", 1)[-1]
        counts[k] = counts.get(k, 0) + 1

    with zenoh.open(_zenoh_config(connect=endpoint)) as session:
        _sub = session.declare_subscriber(keys, on)
        for _ in sys.stdin:
            print(json.dumps(counts), flush=True)


class Subscriber:
    """:func:`_subscribe` running: ``counts()`` asks it what it has received so far."""

    def __init__(self, endpoint: str, keys: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.throughput", endpoint, keys],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            cwd=Path(__file__).resolve().parents[1],  # the checkout: benchmarks is importable
        )

    def counts(self) -> dict[str, int]:
        """Documents received so far, by the key's last chunk."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(b"?\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"throughput: the subscriber exited ({self.proc.poll()})")
        return {str(k): int(v) for k, v in json.loads(line).items()}

    def close(self) -> None:
        """Stop it and reap it."""
        stop_child(self.proc)


def _queued(links: list[Any]) -> bool:
    """Whether packets wait on any of ``links`` for the endpoint's thread."""
    return any(lk.queue or lk.pending for lk in links)


def _drain(links: list[Any], timeout_s: float = 1.0) -> None:
    """Wait until the endpoint's thread has sent what waits on ``links`` (``timeout_s`` at most).

    A frame's packets go out from the pipeline's thread unless another thread holds the
    endpoint's send lock at that instant (the telemetry's HEARTBEAT, the endpoint's own
    flush): then they queue, and every later frame's too until the endpoint's thread has
    flushed. At 100 Hz it has 10 ms between frames for that; fed back to back, the
    frames would fill the queue faster than a thread waiting for the GIL empties it,
    and drop packets the daemon never drops. Its flushing is the process's CPU too;
    the wait is not.
    """
    end = time.monotonic() + timeout_s
    while _queued(links) and time.monotonic() < end:
        time.sleep(0.0002)


def shipped(n: int = 20000, *, repeat: int = 3, step: Step = no_step) -> Figure:
    """Frames per process-CPU second through the daemon's path at the shipped configuration."""
    from benchmarks.mavlink import frame_lines
    from bridge.config import config_from_mapping
    from bridge.daemon import build_daemon, build_outputs
    from bridge.mavlink.endpoints import base as ep_base
    from bridge.protocol.link import LinkMachine
    from bridge.sim.physics import DEFAULT_LOCATION

    lines = _lines(frame_lines(n))
    period = 1.0 / FRAME_RATE_HZ
    zport = free_port(socket.SOCK_STREAM)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # MAVLink's peer; never read
    sink.bind(("127.0.0.1", 0))
    lat, lon, alt = DEFAULT_LOCATION
    best_cpu = best_wall = math.inf
    frames = sent = lost = 0
    got: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        cfg = config_from_mapping(
            {
                "device": {"port": "sim", "rate_hz": int(FRAME_RATE_HZ)},
                "storage": {"dir": tmp},
                "location": {"latitude": lat, "longitude": lon, "altitude_m": alt},
                "mavlink": {"endpoints": [f"udpout:127.0.0.1:{sink.getsockname()[1]}"]},
                "zenoh": {
                    "enabled": True,
                    "listen": [f"tcp/127.0.0.1:{zport}"],
                    "key_prefix": "bench/compass",
                },
            },
            env={},
            hostname="bench",
        )
        daemon = build_daemon(cfg)  # its link never starts: the frames are fed below
        outputs = build_outputs(cfg, daemon, console=False)
        pipeline = daemon.bridge.pipeline
        pipeline.set_outputs(outputs)
        subscriber = None
        # The UDP endpoint sends up to 16 packets per 10 ms from the caller's thread and queues
        # the rest for its own: a limit on wall-clock time, which the frames, fed back to back,
        # would exceed a hundredfold. Its clock follows the frames', so the packets leave as
        # they do at 100 Hz (every one from this thread, none queued).
        frame_time = [time.monotonic()]
        window_clock, ep_base._monotonic = ep_base._monotonic, lambda: frame_time[0]
        try:
            for out in outputs:
                out.start()
            subscriber = Subscriber(f"tcp/127.0.0.1:{zport}", "bench/compass/*")
            t = frame_time[0]
            machine = LinkMachine(name="bench", rate_hz=None)
            machine.start(t)
            machine.opened(t, interactive=False)
            # Until the subscriber has the documents (the sessions have met), 20 s at most.
            deadline = time.monotonic() + 20.0
            i = 0
            docs: dict[str, int] = {}
            while not docs and time.monotonic() < deadline:
                frame_time[0] = t
                for item in machine.receive(lines[i % len(lines)], t):
                    pipeline.on_frame(item)
                i, t = i + 1, t + period
                time.sleep(0.002)
                if i % 10 == 0:
                    docs = subscriber.counts()
            if not docs:
                raise RuntimeError("throughput: the Zenoh subscriber got no document in 20 s")
            eps = outputs[0].endpoints  # type: ignore[attr-defined]  # MAVLink comes first
            links = [lk for ep in eps for lk in ep.links]
            for r in range(repeat):
                # A new connection for each run (the frames' sequence numbers start again).
                machine = LinkMachine(name="bench", rate_hz=None)
                machine.start(t)
                machine.opened(t, interactive=False)
                before = subscriber.counts()
                sent0 = sum(ep.counters().packets_sent for ep in eps)
                samples0 = pipeline.samples
                w0, c0 = time.perf_counter(), process_cpu()
                receive, on_frame = machine.receive, pipeline.on_frame
                for line in lines:
                    frame_time[0] = t
                    for item in receive(line, t):
                        on_frame(item)
                    t += period
                    if _queued(links):
                        _drain(links)
                cpu, wall = process_cpu() - c0, time.perf_counter() - w0
                frames = pipeline.samples - samples0
                sent = sum(ep.counters().packets_sent for ep in eps) - sent0
                lost = sum(ep.counters().packets_dropped + ep.counters().errors for ep in eps)
                time.sleep(0.3)  # the last documents reach the subscriber
                docs = subscriber.counts()
                got = {k: docs.get(k, 0) - before.get(k, 0) for k in docs}
                best_cpu, best_wall = min(best_cpu, cpu), min(best_wall, wall)
                step((r + 1) / repeat, f"throughput run {r + 1}/{repeat}")
        finally:
            ep_base._monotonic = window_clock
            for out in outputs:
                out.close(2.0)
            if subscriber is not None:
                subscriber.close()
            sink.close()
    return _figure(
        "throughput",
        TARGET_FPS,
        frames,
        best_cpu,
        best_wall,
        {
            "frame_rate_hz": FRAME_RATE_HZ,
            "mavlink_packets_per_frame": round(sent / max(1, frames), 3),
            "mavlink_lost": lost,  # dropped from a full queue or by a failed sendto, all runs
            "zenoh_docs_per_frame": round(sum(got.values()) / max(1, frames), 3),
            "zenoh_received": got,
        },
    )


def every_stream(n: int = 20000, *, repeat: int = 3, step: Step = no_step) -> Figure:
    """Frames per process-CPU second with every stream encoded and put for every frame."""
    import zenoh

    from benchmarks.mavlink import STREAMS, bench_config, frame_lines, pack_every_stream
    from bridge.app.sample import CompassSample
    from bridge.daemon import build_daemon
    from bridge.mavlink.dialect import mavlink as mavlink_dialect
    from bridge.mavlink.output import MavlinkOutput, MavlinkSettings
    from bridge.protocol.gmr import GmrDecoder
    from bridge.zenoh import schema

    data = frame_lines(n)
    port = free_port(socket.SOCK_STREAM)
    pub_session = zenoh.open(_zenoh_config(listen=f"tcp/127.0.0.1:{port}"))
    sub_session = zenoh.open(_zenoh_config(connect=f"tcp/127.0.0.1:{port}"))
    received = [0]

    def on_sample(_s: Any) -> None:
        received[0] += 1

    best_cpu = best_wall = math.inf
    frames = 0
    put = 0
    try:
        _sub = sub_session.declare_subscriber("bench/**", on_sample)
        pubs = {
            s: pub_session.declare_publisher(
                f"bench/compass/{s}", congestion_control=zenoh.CongestionControl.DROP
            )
            for s in ("heading", "attitude", "imu")
        }
        time.sleep(0.5)  # let the two sessions meet before the clock starts
        with tempfile.TemporaryDirectory() as tmp:
            cfg = bench_config(tmp)
            daemon = build_daemon(cfg)  # never started: process() is the pipeline's per-frame work
            out = MavlinkOutput(MavlinkSettings(), daemon.bridge.services)
            framer = mavlink_dialect.MAVLink(None, 1, 1)
            for r in range(repeat):
                decoder = GmrDecoder(direction="host")
                frames = put = 0
                w0, c0 = time.perf_counter(), process_cpu()
                for frame in decoder.feed(data):
                    sample = daemon.bridge.pipeline.process(frame, w0)
                    if not isinstance(sample, CompassSample):
                        continue
                    frames += 1
                    pack_every_stream(out, framer, sample)
                    ts = pub_session.new_timestamp()
                    times = schema.SampleTimes(
                        t_monotonic=sample.t, t_unix=time.time(), zenoh_time=None
                    )
                    for name, doc in (
                        ("heading", schema.heading_doc(sample, times)),
                        ("attitude", schema.attitude_doc(sample, times)),
                        ("imu", schema.imu_doc(sample, times)),
                    ):
                        if doc is not None:
                            pubs[name].put(schema.dumps(doc), timestamp=ts)
                            put += 1
                best_cpu = min(best_cpu, process_cpu() - c0)
                best_wall = min(best_wall, time.perf_counter() - w0)
                step((r + 1) / repeat, f"every-stream run {r + 1}/{repeat}")
        time.sleep(0.3)  # the last puts reach the subscriber
    finally:
        sub_session.close()
        pub_session.close()
    return _figure(
        "throughput_every_stream",
        None,
        frames,
        best_cpu,
        best_wall,
        {
            "mavlink_streams": len(STREAMS),
            "zenoh_puts_per_frame": put / max(1, frames),
            "zenoh_received": received[0],
        },
    )


if __name__ == "__main__":
    _subscribe(sys.argv[1], sys.argv[2])
