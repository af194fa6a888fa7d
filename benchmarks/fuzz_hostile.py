"""Hostile angles, round two: what ``python -m benchmarks fuzz`` adds to its serial and MAVLink
fuzzing (:mod:`benchmarks.fuzz`). Each angle runs a real daemon (a child ``compass-bridge
run``) on the simulated compass, served on a pseudo-terminal by this process:

* **crowd** -- signing on, ``udpin`` and ``tcpin``. A signed ground station on ``udpin``
  sends one HEARTBEAT a second and counts its ATTITUDE by the bridge's own clock
  (``time_boot_ms``) while a child process sends ``--junk-rate`` datagrams a second, each
  from a port of its own (random bytes, unsigned and wrongly signed HEARTBEATs, replays of
  the ground station's packets), and ``--tcp-crowd`` TCP clients connect and never send
  nor read. Figures: the ground station's ATTITUDE as a percentage of its set rate (>= 95),
  how long a new TCP client waits to be served (<= 5 s).
* **zenoh** -- remote calibration on: ``--oversized`` queries, half with a 2 MB payload
  (over zenoh's 1 MiB bound: dropped by zenoh before it is assembled, unanswered -- the
  bridge's session has shared memory off, so a peer on the same host cannot pass the
  bound with a shared-memory reference, as it could before), half malformed (64 kB, deep
  nesting, integers beyond a float, a long text), all to be answered ``bad arguments``;
  then four of 100 MB (dropped likewise). Figures: malformed queries answered anything but
  ``bad arguments`` (0), the daemon's RSS growth (MB), tracebacks (0).
* **silent** -- the compass answers every command and streams no ``$PGMRA``. Figures:
  Zenoh status documents and HEARTBEATs that said it streams (0), link lost / restored
  events (0).
* **late** -- the compass answers 1.5 s late (its datasheet: 200 ms), then 0.6 s late with an
  on-board MAGCAL asked for. Figures: device resets read into it (0), commands sent again
  (0), left in calibration mode after the failed MAGCAL (0).
* **params** -- a storm of PARAM_SETs (``--set-rate`` a second) from a ground station.
  Figures: ``params.json`` writes a second (each a new inode: temp file, fsync, rename;
  <= 1.5), and a value set a moment before SIGTERM missing from the file after it (0).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from benchmarks.figures import Figure
from benchmarks.procstat import (
    DatagramReceiver,
    free_port,
    process_rss_mb,
    start_daemon,
    stop_child,
    wait_until,
)

log = logging.getLogger(__name__)

ANGLES = ("crowd", "zenoh", "silent", "late", "params")
_KEY = bytes.fromhex("c0" * 32)
_ATT_HZ = 10.0  #: BRG_SR_ATT's default
_SIGNING_EPOCH = 1420070400

#: The flood, in a process of its own (so it does not steal this process's time):
#: ``python -c FLOOD PORT RATE SECONDS SAMPLE_HEX ...`` sends RATE datagrams a second to
#: 127.0.0.1:PORT, each from a port of its own -- random junk, MAVLink 2 junk, and the
#: SAMPLES -- and prints the rate it kept (tests/test_mavlink_starvation.py floods with it).
FLOOD = textwrap.dedent(
    """
    import random, socket, sys, time
    port, rate, seconds = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
    samples = [bytes.fromhex(h) for h in sys.argv[4:]]
    rng = random.Random(7)
    sent, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        for _ in range(max(1, rate // 20)):
            k = rng.random()
            d = rng.randbytes(rng.randint(1, 200)) if k < 0.5 else (
                b"\\xfd" + rng.randbytes(rng.randint(10, 100)) if k < 0.6 else rng.choice(samples))
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(d, ("127.0.0.1", port))
            sent += 1
        time.sleep(max(0.0, t0 + sent / rate - time.monotonic()))
    print(sent / (time.monotonic() - t0))
    """
)


def signed(sysid: int, key: bytes, link_id: int = 0) -> Any:
    """A pymavlink ``MAVLink`` of ``sysid`` that signs what it packs with ``key``."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    mav = apm.MAVLink(None, sysid, 190)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = int((time.time() - _SIGNING_EPOCH) * 100_000)
    return mav


def heartbeat(mav: Any) -> bytes:
    """A ground station's HEARTBEAT (MAV_TYPE_GCS, no autopilot) as ``mav`` packs it: its
    system and component, its sequence, its signature if it signs (:func:`signed`)."""
    return bytes(mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav))


def start_flood(
    port: int, rate: int, seconds: float, captured: list[bytes]
) -> subprocess.Popen[str]:
    """:data:`FLOOD` at ``port`` in a child process (its stdout piped: the rate it kept).

    The samples are what an attacker has: a stranger's HEARTBEAT, one signed with
    another key, and ``captured`` -- a ground station's own packets, to replay."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    samples = [heartbeat(apm.MAVLink(None, 66, 1)), heartbeat(signed(77, bytes(32))), *captured]
    return subprocess.Popen(
        [sys.executable, "-c", FLOOD, str(port), str(rate), str(seconds),
         *(s.hex() for s in samples)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip


def idle_clients(port: int, n: int) -> list[socket.socket]:
    """``n`` TCP clients connecting to ``port`` that will never send nor read."""
    idle: list[socket.socket] = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            s.connect(("127.0.0.1", port))
        idle.append(s)
    return idle


def end_attack(flood: subprocess.Popen[str] | None, idle: list[socket.socket]) -> None:
    """Stop what :func:`start_flood` and :func:`idle_clients` started (either may be missing)."""
    if flood is not None and flood.poll() is None:
        flood.kill()
    for s in idle:
        s.close()


@contextlib.contextmanager
def _daemon(
    tmp: Path, name: str, config: str, *, fw_setup: Callable[[Any], None] | None = None
) -> Iterator[tuple[subprocess.Popen[bytes], Any, Path]]:
    """A daemon child on a simulated compass (its firmware handed to ``fw_setup``)."""
    from bridge.sim.firmware import make_firmware
    from bridge.sim.pty import PtyCompass

    fw = make_firmware(41)
    if fw_setup is not None:
        fw_setup(fw)
    sim = PtyCompass(fw, tmp / f"{name}.tty").start()
    cfg = tmp / f"{name}.toml"
    cfg.write_text(
        f'[device]\nport = "{sim.link_path}"\nrate_hz = 20\nstale_after = 1.0\n'
        f'[storage]\ndir = "{tmp / (name + "-state")}"\n{config}'
    )
    errlog = tmp / f"{name}.log"
    proc = start_daemon(cfg, errlog)
    try:
        yield proc, fw, errlog
    finally:
        stop_child(proc)
        sim.stop()


def _tracebacks(errlog: Path) -> int:
    return errlog.read_text(errors="replace").count("Traceback (most recent call last)")


class Gcs(DatagramReceiver):
    """A ground station on a UDP endpoint: HEARTBEATs at 1 Hz (signed with ``key``); keeps
    the ATTITUDE and HEARTBEAT it hears (the crowd test's ground station too)."""

    def __init__(self, port: int, key: bytes | None, *, listen: bool = False) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as apm

        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", port if listen else 0))
        sock.settimeout(0.1)
        super().__init__(sock)
        self.addr = ("127.0.0.1", port)
        self.listen = listen
        self.mav = signed(255, key) if key is not None else apm.MAVLink(None, 255, 190)
        self.parser = apm.MAVLink(None)
        self.lock = threading.Lock()
        self.seen: list[Any] = []
        self.sent: list[bytes] = []
        if not listen:
            self._threads.append(threading.Thread(target=self._beat, daemon=True))
        self.start()

    def _beat(self) -> None:
        while not self._stop.is_set():
            pkt = heartbeat(self.mav)
            self.sent.append(pkt)
            with contextlib.suppress(OSError):
                self.sock.sendto(pkt, self.addr)
            self._stop.wait(1.0)

    def handle(self, data: bytes) -> None:
        with contextlib.suppress(Exception):
            msgs = self.parser.parse_buffer(data) or []
            with self.lock:
                self.seen += [m for m in msgs if m.get_type() in ("ATTITUDE", "HEARTBEAT")]

    def of(self, kind: str) -> list[Any]:
        with self.lock:
            return [m for m in self.seen if m.get_type() == kind]

    def attitude_boot_ms(self) -> list[int]:
        """The bridge's time (``time_boot_ms``) of every ATTITUDE heard, in arrival order."""
        return [int(m.time_boot_ms) for m in self.of("ATTITUDE")]


def in_window(stamps_ms: list[int], start_ms: int, window_ms: int) -> int:
    """How many of ``stamps_ms`` fall in ``[start_ms, start_ms + window_ms)``: a rate by the
    sender's clock, so a busy receiver (late, bunched arrivals) does not move it."""
    return sum(1 for t in stamps_ms if start_ms <= t < start_ms + window_ms)


@contextlib.contextmanager
def _zenoh_session(port: int) -> Iterator[Any]:
    """A Zenoh peer connected to the daemon's endpoint on 127.0.0.1:``port``, closed after."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(c)
    try:
        yield session
    finally:
        session.close()


def _zenoh_config(port: int, prefix: str, remote: bool = False) -> str:
    return (
        f'[zenoh]\nenabled = true\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        f'key_prefix = "{prefix}"\nmulticast_scouting = false\n'
        f"remote_calibration = {'true' if remote else 'false'}\n"
    )


# ---------------------------------------------------------------------------- the angles


def crowd(tmp: Path, junk_rate: int, tcp_crowd: int, seconds: float) -> list[Figure]:
    """Junk from many ports and a TCP crowd against a signed ground station (module docstring)."""

    udp, tcp = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    key_file = tmp / "crowd.key"
    key_file.write_text(_KEY.hex() + "\n")
    mav = (
        f'[mavlink]\nendpoints = ["udpin:127.0.0.1:{udp}", "tcpin:127.0.0.1:{tcp}"]\n'
        f'signing_key_file = "{key_file}"\n[zenoh]\nenabled = false\n'
    )
    with _daemon(tmp, "crowd", mav) as (proc, _fw, errlog):
        gcs = Gcs(udp, _KEY)
        idle: list[socket.socket] = []
        flood: subprocess.Popen[str] | None = None
        try:
            if not wait_until(lambda: len(gcs.attitude_boot_ms()) >= 20, 30.0):
                raise RuntimeError(f"no ATTITUDE at the signed ground station (log: {errlog})")
            flood = start_flood(udp, junk_rate, seconds + 4, gcs.sent[:3])
            idle += idle_clients(tcp, tcp_crowd)
            time.sleep(2.0)
            start = max(gcs.attitude_boot_ms())
            t0 = time.monotonic()
            served = math.nan
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", tcp), timeout=15.0) as c,
            ):
                c.sendall(heartbeat(signed(250, _KEY, 3)))
                c.settimeout(15.0)
                if c.recv(4096):
                    served = time.monotonic() - t0
            window_ms = int(seconds * 1000)
            wait_until(lambda: max(gcs.attitude_boot_ms()) >= start + window_ms, seconds + 20.0)
            rate = in_window(gcs.attitude_boot_ms(), start, window_ms) / seconds
            out, _ = flood.communicate(timeout=seconds + 30.0)
            junk_sent = float(out.strip() or "nan")
        finally:
            end_attack(flood, idle)
            gcs.close()
        tracebacks = _tracebacks(errlog)
        alive = proc.poll() is None
    return [
        Figure("crowd_gcs_attitude", 100.0 * rate / _ATT_HZ, "% of set rate", 95.0, False, detail={
            "attitude_hz": round(rate, 2), "set_hz": _ATT_HZ, "window_s": seconds,
            "junk_datagrams_per_s": round(junk_sent, 1), "from_ports": "one each",
            "idle_tcp_clients": tcp_crowd, "signed": True}),
        Figure("crowd_tcp_newcomer_wait", served, "s", 5.0, detail={
            "idle_tcp_clients": tcp_crowd}),
        Figure("crowd_tracebacks", tracebacks + int(not alive), "", 0.0, detail={
            "alive": alive}),
    ]  # fmt: skip


#: How long an oversized query waits for a reply (zenoh drops it: none comes).
HUGE_QUERY_WAIT_S = 0.5


def oversized_zenoh(tmp: Path, queries: int) -> list[Figure]:
    """Oversized and malformed Zenoh command arguments (module docstring)."""
    zport = free_port(socket.SOCK_STREAM)
    prefix = f"bench/fuzz{zport}"
    config = "[mavlink]\nendpoints = []\n" + _zenoh_config(zport, prefix, remote=True)
    with _daemon(tmp, "zenoh", config) as (proc, _fw, errlog):
        with _zenoh_session(zport) as session:
            key = f"{prefix}/cmd/calibration/start"
            if not wait_until(
                lambda: bool(list(session.get(f"{prefix}/status", timeout=0.5))), 30.0
            ):
                raise RuntimeError(f"the daemon's Zenoh did not answer (log: {errlog})")
            time.sleep(1.0)
            rss0 = process_rss_mb(proc.pid)[0]
            malformed = [
                b"x" * 65536,
                b'{"what": ' + b"[" * 2000 + b"]" * 2000 + b"}",
                b'{"what": "fixed_yaw", "yaw_deg": 1' + b"0" * 400 + b"}",
                json.dumps({"what": "m" * 4000}).encode(),
            ]
            wrong = answered = dropped = 0
            huge = b"y" * (2 << 20)
            rss_warm = math.nan
            for i in range(queries):
                if i == min(20, queries // 5):  # past the allocator's warm-up
                    time.sleep(0.5)
                    rss_warm = process_rss_mb(proc.pid)[0]
                payload = huge if i % 2 else malformed[(i // 2) % len(malformed)]
                # A query zenoh drops gets no reply: its wait is the whole timeout, so the
                # oversized ones wait less (an answer on loopback takes milliseconds).
                wait = HUGE_QUERY_WAIT_S if payload is huge else 2.0
                replies = list(session.get(key, payload=payload, timeout=wait))
                ok = [r.ok for r in replies if r.ok is not None]
                if not ok:
                    dropped += 1
                    continue
                answered += 1
                doc = json.loads(ok[0].payload.to_bytes())
                if doc.get("ok") or not str(doc.get("message", "")).startswith("bad arguments"):
                    wrong += 1
            giant = b"z" * (100 << 20)  # 24 x 100 MB asked for, in short
            giants = sum(
                1
                for _ in range(4)
                for r in session.get(key, payload=giant, timeout=HUGE_QUERY_WAIT_S)
                if r.ok is not None
            )
            del giant
            time.sleep(1.0)
            rss1 = process_rss_mb(proc.pid)[0]
        tracebacks = _tracebacks(errlog)
    return [
        Figure("zenoh_not_bad_arguments", wrong, "answers", 0.0, detail={
            "queries": queries, "answered_bad_arguments": answered - wrong,
            "dropped_by_zenoh_over_1MiB": dropped}),
        Figure("zenoh_memory_growth", rss1 - rss_warm, "MB RSS", 16.0, detail={
            "rss_before_mb": round(rss0, 1), "rss_after_warmup_mb": round(rss_warm, 1),
            "rss_after_mb": round(rss1, 1), "payloads": "half 2 MB, half malformed <= 64 kB",
            "then_4x100MB_answered": giants,
            "measured": "from the 20th query to the last (the first ones fill the allocator)"}),
        Figure("zenoh_tracebacks", tracebacks, "", 0.0),
    ]  # fmt: skip


def _watch_zenoh(session: Any, prefix: str) -> tuple[list[str], list[str], Any]:
    states: list[str] = []
    events: list[str] = []

    def on_status(sample: Any) -> None:
        with contextlib.suppress(Exception):
            states.append(json.loads(sample.payload.to_bytes())["link"]["state"])

    def on_event(sample: Any) -> None:
        with contextlib.suppress(Exception):
            events.append(json.loads(sample.payload.to_bytes())["kind"])

    subs = [
        session.declare_subscriber(f"{prefix}/status", on_status),
        session.declare_subscriber(f"{prefix}/events", on_event),
    ]
    return states, events, subs


def silent_device(tmp: Path, seconds: float) -> list[Figure]:
    """A compass that answers and streams nothing (module docstring)."""
    zport, gport = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    prefix = f"bench/silent{zport}"
    config = f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{gport}"]\n' + _zenoh_config(zport, prefix)

    def mute(fw: Any) -> None:
        fw.streaming = False

    gcs = Gcs(gport, None, listen=True)
    with _daemon(tmp, "silent", config, fw_setup=mute) as (_proc, _fw, errlog):
        with _zenoh_session(zport) as session:
            states, events, _subs = _watch_zenoh(session, prefix)
            wait_until(lambda: len(states) >= 2, 30.0)
            time.sleep(seconds)
        tracebacks = _tracebacks(errlog)
    beats = gcs.of("HEARTBEAT")
    gcs.close()
    active = sum(1 for m in beats if int(m.system_status) == 4)  # MAV_STATE_ACTIVE
    said = states.count("streaming") + active
    flaps = sum(1 for k in events if k in ("link.lost", "link.restored"))
    return [
        Figure("silent_said_streaming", said, "reports", 0.0, detail={
            "zenoh_status_docs": len(states), "zenoh_states": sorted(set(states)),
            "heartbeats": len(beats), "heartbeats_active": active, "seconds": seconds}),
        Figure("silent_flaps", flaps, "lost/restored", 0.0),
        Figure("silent_tracebacks", tracebacks, "", 0.0),
    ]  # fmt: skip


def late_device(tmp: Path, seconds: float) -> list[Figure]:
    """A compass that answers late (module docstring)."""
    zport = free_port(socket.SOCK_STREAM)
    prefix = f"bench/late{zport}"
    config = "[mavlink]\nendpoints = []\n[calibration]\nonboard = true\n" + _zenoh_config(
        zport, prefix, remote=True
    )

    def slow(fw: Any) -> None:
        fw.answer_delay_s = 1.5

    counters: dict[str, Any] = {}
    with _daemon(tmp, "late", config, fw_setup=slow) as (_proc, fw, errlog):
        with _zenoh_session(zport) as session:
            states, _events, _subs = _watch_zenoh(session, prefix)
            wait_until(lambda: len(states) >= 2, 30.0)
            time.sleep(seconds)
            fw.answer_delay_s = 0.6
            key = f"{prefix}/cmd/calibration/start"
            list(session.get(key, payload=b'{"what": "mag"}', timeout=5.0))
            time.sleep(8.0)  # the MAGCAL fails (late answers) and is aborted
            for r in session.get(f"{prefix}/status", timeout=3.0):
                if r.ok is not None:
                    counters = json.loads(r.ok.payload.to_bytes())["link"]["counters"]
            left_calibrating = int(fw.calibrating)
        tracebacks = _tracebacks(errlog)
    return [
        Figure("late_device_resets", counters.get("device_resets", math.nan), "", 0.0, detail={
            "answer_delay_s": 1.5, "seconds": seconds,
            "late_answers": counters.get("late_answers"),
            "command_timeouts": counters.get("command_timeouts")}),
        Figure("late_commands_resent", counters.get("command_retries", math.nan), "", 0.0),
        Figure("late_left_calibrating", left_calibrating, "", 0.0, detail={
            "answer_delay_s": 0.6}),
        Figure("late_tracebacks", tracebacks, "", 0.0),
    ]  # fmt: skip


def add_arguments(ap: Any) -> None:
    """The angles' options on ``bench fuzz``'s command line."""
    ap.add_argument(
        "--angles", default="all", metavar="LIST",
        help=f"round-two angles, comma-separated ({', '.join(ANGLES)}), 'all' or 'none'",
    )  # fmt: skip
    ap.add_argument("--junk-rate", type=int, default=1000, help="crowd: datagrams/s, one port each")
    ap.add_argument("--tcp-crowd", type=int, default=50, help="crowd: idle TCP clients")
    ap.add_argument("--oversized", type=int, default=100, help="zenoh: oversized queries")
    ap.add_argument("--angle-seconds", type=float, default=8.0, help="each angle's seconds")
    ap.add_argument("--set-rate", type=int, default=3000, help="params: PARAM_SETs a second")


def from_args(args: Any, step: Callable[[float, str], None] | None = None) -> list[Figure]:
    """The figures of the angles ``args`` (from :func:`add_arguments`) ask for."""
    names = ANGLES if args.angles == "all" else tuple(a for a in args.angles.split(",") if a)
    if args.angles == "none":
        return []
    return run_angles(
        names,
        junk_rate=args.junk_rate,
        tcp_crowd=args.tcp_crowd,
        oversized=args.oversized,
        seconds=args.angle_seconds,
        set_rate=args.set_rate,
        step=step,
    )


def params_storm(tmp: Path, set_rate: int, seconds: float) -> list[Figure]:
    """A PARAM_SET storm; params.json writes counted by its inode (module docstring)."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    udp = free_port(socket.SOCK_DGRAM)
    config = f'[mavlink]\nendpoints = ["udpin:127.0.0.1:{udp}"]\n[zenoh]\nenabled = false\n'
    doc = tmp / "params-state" / "params.json"
    inodes: list[int] = []
    final = math.nan
    with _daemon(tmp, "params", config) as (proc, _fw, errlog):
        gcs = Gcs(udp, None)
        stop = threading.Event()

        def watch() -> None:  # a rename is a new inode: one per write
            while not stop.is_set():
                with contextlib.suppress(OSError):
                    ino = doc.stat().st_ino
                    if not inodes or inodes[-1] != ino:
                        inodes.append(ino)
                stop.wait(0.005)

        watcher = threading.Thread(target=watch, daemon=True)
        try:
            if not wait_until(lambda: len(gcs.of("HEARTBEAT")) >= 2, 30.0):
                raise RuntimeError(f"the daemon did not answer (log: {errlog})")
            mav = apm.MAVLink(None, 255, 190)
            real32 = apm.MAV_PARAM_TYPE_REAL32
            watcher.start()
            t0, n = time.monotonic(), 0
            while time.monotonic() - t0 < seconds:
                for _ in range(max(1, set_rate // 100)):
                    msg = mav.param_set_encode(1, 1, b"BRG_SR_HUD", float(1 + n % 30), real32)
                    gcs.sock.sendto(bytes(msg.pack(mav)), gcs.addr)
                    n += 1
                time.sleep(max(0.0, t0 + n / set_rate - time.monotonic()))
            storm_s = time.monotonic() - t0
            writes = max(0, len(inodes) - 1)  # the first inode may be the file from before
            time.sleep(0.5)
            msg = mav.param_set_encode(1, 1, b"BRG_SR_HUD", 37.0, real32)  # the last word
            gcs.sock.sendto(bytes(msg.pack(mav)), gcs.addr)
            time.sleep(0.3)  # in force (echoed), not yet written: then the bridge stops
            proc.terminate()
            proc.wait(10.0)
            payload = json.loads(doc.read_text())["payload"]["set"]
            final = float(payload.get("BRG_SR_HUD", math.nan))
        finally:
            stop.set()
            if watcher.is_alive():
                watcher.join(2.0)
            gcs.close()
        tracebacks = _tracebacks(errlog)
    return [
        Figure("params_writes_per_s", writes / storm_s, "writes/s", 1.5, detail={
            "sets_sent": n, "sets_per_s": round(n / storm_s), "seconds": round(storm_s, 1),
            "writes": writes}),
        Figure("params_lost_at_shutdown", int(final != 37.0), "", 0.0, detail={
            "stored_after_sigterm": final, "set_before_sigterm": 37.0}),
        Figure("params_tracebacks", tracebacks, "", 0.0),
    ]  # fmt: skip


def run_angles(
    angles: tuple[str, ...],
    *,
    junk_rate: int = 1000,
    tcp_crowd: int = 50,
    oversized: int = 100,
    seconds: float = 8.0,
    set_rate: int = 3000,
    step: Callable[[float, str], None] | None = None,
) -> list[Figure]:
    """The angles asked for, each against its own daemon; their figures."""
    figures: list[Figure] = []
    with tempfile.TemporaryDirectory(prefix="cb-fuzz2-") as name:
        tmp = Path(name)
        for i, angle in enumerate(angles):
            if step is not None:
                step(i / len(angles), f"angle {angle}")
            if angle == "crowd":
                figures += crowd(tmp, junk_rate, tcp_crowd, seconds)
            elif angle == "zenoh":
                figures += oversized_zenoh(tmp, oversized)
            elif angle == "silent":
                figures += silent_device(tmp, seconds)
            elif angle == "late":
                figures += late_device(tmp, seconds)
            elif angle == "params":
                figures += params_storm(tmp, set_rate, seconds)
            else:
                raise ValueError(f"unknown angle {angle!r} (one of {', '.join(ANGLES)})")
    return figures
