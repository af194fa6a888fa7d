"""Hostile input against a running daemon: ``python -m benchmarks fuzz`` (the further
angles -- many-peer junk, a TCP crowd, oversized Zenoh arguments, a silent or a late
compass -- are :mod:`benchmarks.fuzz_hostile`, run after these unless ``--angles none``).

A real daemon (a child ``compass-bridge run``) reads a pseudo-terminal this
process serves as the compass, speaks MAVLink on ``udpin:127.0.0.1`` and keeps
its state in a temporary directory. Two phases:

1. **serial** -- ``--chunks`` fuzz chunks (default 10^6) go down the pty:
   valid ``$PGMRA`` frames of a unit turning through 360 headings, mixed with
   random bytes, lines truncated anywhere, lines with bytes flipped, inserted or
   deleted, lines with a field replaced by a boundary or random token and the
   checksum made right again, other sentences, stray ``$``/``*``/CR/LF. Every
   byte written is also decoded here, offline; an ATTITUDE whose roll, pitch
   and yaw match no frame of that offline decode is a **false frame**.
2. **mavlink** -- ``--messages`` unsigned messages (default 10^5) over UDP:
   every message type of the dialect with random field values, the ones the
   bridge handles (COMMAND_LONG/INT, PARAM_SET/REQUEST_READ/REQUEST_LIST,
   positions) with fuzzed fields, random message ids with valid framing,
   corrupted packets, random bytes. Meanwhile valid frames keep coming at 100 Hz.

Then it prints: false frames, **crashes** (the daemon died, stopped answering a
PARAM_REQUEST_READ, or did not stop cleanly on SIGTERM), **tracebacks** in its
log, **state changes** (every parameter read back, every state file hashed,
before and after; legitimate only when a well-formed message that can make the
change was sent: a PARAM_SET naming the parameter, a calibration command for
COMPASS_*/BRG_ALIGN_*, SET_MESSAGE_INTERVAL for BRG_SR_*, PREFLIGHT_STORAGE 2
for all) and **memory growth** (RSS after start-up and at the end). All must be
zero but legitimate state changes (memory: under ``--max-growth-mb``).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import logging
import math
import os
import random
import select
import socket
import sys
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks import fuzz_hostile
from benchmarks.figures import Figure, report, report_options
from benchmarks.procstat import (
    DatagramReceiver,
    free_port,
    process_rss_mb,
    start_daemon,
    stop_child,
    udp_socket,
    wait_until,
)

log = logging.getLogger(__name__)

Step = Callable[[float, str], None]

#: ATTITUDE is float32: a frame's angles come back within this (radians).
MATCH_TOL_RAD = 2e-5
#: Calibration commands (ArduPilot's flow and PREFLIGHT_CALIBRATION) may change these.
CAL_COMMANDS = {42424, 42425, 42426, 42004, 42006, 241}
CAL_PREFIXES = ("COMPASS_", "BRG_ALIGN_", "BRG_CAL")
SET_MESSAGE_INTERVAL = 511
PREFLIGHT_STORAGE = 245
#: Boundary and malformed tokens a damaged or lax firmware could put in a field.
TOKENS = ["0", "65535", "65536", "-1", "4095", "4096", "360.0", "359.9", "360.1", "90.1",
          "-180.1", "-0.0", "1e3", "nan", "inf", "", "+1", ".5", "00", "1F", "20", "FF", "x"]  # fmt: skip


def _no_step(frac: float, note: str) -> None:
    """No progress display."""


# ---------------------------------------------------------------------------- serial fuzz


def palette(n: int = 360) -> list[tuple[int, ...]]:
    """Raw counts of a level unit at ``n`` headings (one frame shape per heading)."""
    from bridge.core import sensor

    out = []
    for i in range(n):
        h = math.radians(360.0 * i / n)
        # A field with 0.2 G north, 0.45 G down, seen by a unit yawed by h (level).
        mag = (0.2 * math.cos(h), -0.2 * math.sin(h), 0.45)
        m = sensor.gauss_to_mag_counts(mag)
        a = sensor.g_to_acc_counts((0.0, 0.0, 1.0))
        out.append(tuple(round(float(v)) for v in (*m, *a)))
    return out


class SerialFuzz:
    """Fuzz chunks of the GMR serial protocol (deterministic for a seed)."""

    def __init__(self, rng: random.Random) -> None:
        from bridge.protocol.gmr import AckFrame, CalProgressFrame, ParamsFrame

        self.rng = rng
        self.seq = 0
        self.palette = palette()
        self.others: list[Any] = [
            AckFrame.rate_ok(100),
            AckFrame.failure("MAGCAL", "STATE"),
            ParamsFrame.factory(),
            CalProgressFrame(12, 100, 200, 300, 400, 0, 0),
        ]

    def valid(self) -> bytes:
        """The next valid $PGMRA line (consecutive seq, the unit turning)."""
        from bridge.protocol.gmr import AttitudeFrame, Flags, encode

        mx, my, mz, ax, ay, az = self.palette[self.seq % len(self.palette)]
        line = encode(AttitudeFrame(self.seq, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, Flags.MAGOK))
        self.seq = (self.seq + 1) % 65536
        return line

    def chunk(self) -> bytes:
        """One fuzz chunk: valid, truncated, corrupted, re-checksummed, random, other."""
        from bridge.protocol.framing import render_line
        from bridge.protocol.gmr import encode

        r = self.rng
        kind = r.random()
        if kind < 0.25:
            return self.valid()
        if kind < 0.40:
            line = self.valid()
            return line[: r.randrange(len(line))]
        if kind < 0.55:
            raw = bytearray(self.valid())
            for _ in range(r.randint(1, 3)):
                at = r.randrange(len(raw))
                op = r.random()
                if op < 0.4:
                    raw[at] = r.randrange(256)
                elif op < 0.7:
                    raw.insert(at, r.choice(b"0123456789.,-*$\r\n\x00\xff"))
                elif len(raw) > 1:
                    del raw[at]
            return bytes(raw)
        if kind < 0.70:
            parts = self.valid()[1:-5].decode().split(",")
            i = r.randrange(1, len(parts))
            parts[i] = r.choice(TOKENS) if r.random() < 0.7 else r.choice(["", "-", "1.2.3"])
            if r.random() < 0.1:
                parts.insert(r.randrange(1, len(parts)), "0")
            with contextlib.suppress(ValueError):
                return render_line(",".join(parts))
            return b"$" + ",".join(parts).encode() + b"*00\r\n"
        if kind < 0.85:
            return r.randbytes(r.randint(1, 120))
        if kind < 0.92:
            return encode(r.choice(self.others))
        if kind < 0.97:
            alphabet = b"$*,.-0123456789PGMRA\r\n"
            return bytes(r.choice(alphabet) for _ in range(r.randint(1, 40)))
        return r.choice([b"$", b"*", b"\r", b"\n", b"\r\n", b"$PGMRA,", b"*5"])


class PtyCompass:
    """The compass side of a pty: every write is decoded offline too; commands are answered."""

    def __init__(self) -> None:
        from bridge.protocol.gmr import GmrDecoder

        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.offline = GmrDecoder()
        self.frames: list[Any] = []  #: every AttitudeFrame of the offline decode
        self.bytes = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._answer, name="fuzz-device", daemon=True)
        self._thread.start()

    def write(self, data: bytes) -> None:
        """Write all of ``data`` (blocking: the daemon's reads pace us) and decode it here."""
        from bridge.protocol.gmr import AttitudeFrame

        with self._lock:
            view = memoryview(data)
            while view:
                view = view[os.write(self.master, view) :]
            self.bytes += len(data)
            self.frames += [f for f in self.offline.feed(data) if isinstance(f, AttitudeFrame)]

    def _answer(self) -> None:
        """The handshake (VER, RATE, PAR,GET) answered as the datasheet says."""
        from bridge.protocol.gmr import (
            AckFrame,
            CommandFrame,
            GmrDecoder,
            ParamsFrame,
            VersionFrame,
            encode,
        )

        dec = GmrDecoder("device")
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            for cmd in dec.feed(data):
                if not isinstance(cmd, CommandFrame):
                    continue
                if cmd.command == "VER":
                    self.write(encode(VersionFrame("2.1.0", "B3", "GMR-FUZZ")))
                elif cmd.key == "PAR,GET":
                    self.write(encode(ParamsFrame.factory()))
                elif cmd.command == "RATE" and cmd.error() is None:
                    self.write(encode(AckFrame.rate_ok(cmd.rate_hz())))
                else:
                    self.write(encode(cmd.ack_err("STATE")))

    def close(self) -> None:
        """Stop answering, close both ends."""
        self._stop.set()
        self._thread.join(2.0)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


# ---------------------------------------------------------------------------- MAVLink fuzz


@dataclass
class Effects:
    """What the well-formed messages sent may legitimately change."""

    params: set[str] = field(default_factory=set)
    prefixes: set[str] = field(default_factory=set)
    all_params: bool = False
    calibration: bool = False

    def note(self, msg: Any) -> None:
        """Record what ``msg`` (a pymavlink message we sent) may change."""
        kind = msg.get_type()
        if kind == "PARAM_SET":
            name = msg.param_id
            name = name.decode("latin-1") if isinstance(name, bytes) else str(name)
            self.params.add(name.split("\x00", 1)[0])
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            cmd = int(msg.command)
            if cmd in CAL_COMMANDS:
                self.calibration = True
                self.prefixes.update(CAL_PREFIXES)
            elif cmd == SET_MESSAGE_INTERVAL:
                self.prefixes.add("BRG_SR_")
            elif cmd == PREFLIGHT_STORAGE:  # 1 writes the calibration file, 2 resets all
                self.calibration = True
                self.all_params |= 1.5 <= float(msg.param1) < 2.5
        elif kind in ("GLOBAL_POSITION_INT", "GPS_RAW_INT"):
            self.params.add("COMPASS_DEC")  # the declination follows the position

    def allows(self, name: str) -> bool:
        """Whether parameter ``name`` may have changed."""
        return self.all_params or name in self.params or name.startswith(tuple(self.prefixes))


_LIMITS = {
    "int8_t": (-128, 127),
    "uint8_t": (0, 255),
    "int16_t": (-32768, 32767),
    "uint16_t": (0, 65535),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
    "uint64_t": (0, 2**64 - 1),
}
_FLOATS = [0.0, -0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-45, 2.0**31,
           3.6e9, 1e-4, 0.5, 100.0]  # fmt: skip


class MavlinkFuzz:
    """Fuzzed MAVLink 2 packets from this process as system 255 (a ground station)."""

    def __init__(self, rng: random.Random, param_names: list[str]) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        self.rng = rng
        self.mav = mav
        self.link = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        self.classes = sorted(mav.mavlink_map.values(), key=lambda c: c.id)
        self.names = param_names or ["COMPASS_OFS_X"]
        self.effects = Effects()
        self.handled = [mav.MAVLink_command_long_message, mav.MAVLink_command_int_message,
                        mav.MAVLink_param_set_message, mav.MAVLink_param_request_read_message,
                        mav.MAVLink_param_request_list_message, mav.MAVLink_global_position_int_message,
                        mav.MAVLink_gps_raw_int_message, mav.MAVLink_timesync_message]  # fmt: skip
        self.commands = [42424, 42425, 42426, 42004, 42006, 241, 245, 511, 510, 512, 520, 246, 0]

    def _value(self, name: str, ftype: str, length: int) -> Any:
        r = self.rng
        if length and ftype != "char":
            return [self._value(name, ftype, 0) for _ in range(length)]
        if ftype == "char":
            if name == "param_id" and r.random() < 0.7:
                return r.choice(self.names).encode()
            return r.randbytes(r.randint(0, max(1, length)))
        if ftype in ("float", "double"):
            return r.choice(_FLOATS) if r.random() < 0.5 else r.uniform(-1e6, 1e6)
        lo, hi = _LIMITS[ftype]
        if name == "command":
            return r.choice(self.commands) if r.random() < 0.8 else r.randint(lo, hi)
        if name in ("target_system", "target_component"):
            return r.choice([0, 1, 1, 1, r.randint(lo, hi)])
        return r.choice([lo, hi, 0, 1]) if r.random() < 0.3 else r.randint(lo, hi)

    def _message(self, cls: Any) -> Any:
        values = []
        for i, name in enumerate(cls.fieldnames):
            length = cls.array_lengths[cls.ordered_fieldnames.index(name)]
            values.append(self._value(name, cls.fieldtypes[i], length))
        return cls(*values)

    def _pack(self, msg: Any, *, sent_intact: bool = True) -> bytes:
        buf = bytes(msg.pack(self.link))
        self.link.seq = (self.link.seq + 1) % 256
        if sent_intact:  # a corrupted copy cannot take effect
            self.effects.note(msg)
        return buf

    def packet(self) -> bytes:
        """One fuzz packet (its effects noted when it is a well-formed message)."""
        r = self.rng
        kind = r.random()
        try:
            if kind < 0.35:
                return self._pack(self._message(r.choice(self.classes)))
            if kind < 0.60:
                return self._pack(self._message(r.choice(self.handled)))
            if kind < 0.75:
                return self._random_id()
            if kind < 0.90:
                msg = self._message(r.choice(self.handled))
                raw = bytearray(self._pack(msg, sent_intact=False))
                at = r.randrange(len(raw))
                if r.random() < 0.5:
                    raw[at] ^= 1 << r.randrange(8)
                else:
                    del raw[at:]
                return bytes(raw) or b"\xfd"
        except Exception:
            # A value pymavlink refuses to pack (struct range, encoding): random bytes instead.
            pass
        return r.randbytes(r.randint(1, 280))

    def _random_id(self) -> bytes:
        """A MAVLink 2 frame with a random message id and payload, framing and CRC valid."""
        r = self.rng
        payload = r.randbytes(r.randint(0, 255))
        header = bytes([0xFD, len(payload), 0, 0, self.link.seq, 255, 190]) + r.randbytes(3)
        crc = self.mav.x25crc(header[1:] + payload)
        crc.accumulate(bytes([r.randrange(256)]))
        return header + payload + crc.crc.to_bytes(2, "little")


class MavlinkPeer(DatagramReceiver):
    """A UDP ground station on 127.0.0.1: sends, and collects ATTITUDE and PARAM_VALUE."""

    def __init__(self, daemon_port: int) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        super().__init__(udp_socket(0.1), "fuzz-udp")
        self.mav = mav
        self.addr = ("127.0.0.1", daemon_port)
        self.link = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True
        self.attitudes: list[tuple[float, float, float]] = []
        self.params: dict[str, float] = {}
        self.param_count = 0
        self.received = 0
        self.start()

    def send(self, data: bytes) -> None:
        """One datagram to the daemon (dropped silently if the socket buffer is full)."""
        with contextlib.suppress(OSError):
            self.sock.sendto(data, self.addr)

    def send_msg(self, msg: Any) -> None:
        """A well-formed message."""
        self.send(bytes(msg.pack(self.link)))
        self.link.seq = (self.link.seq + 1) % 256

    def handle(self, data: bytes) -> None:
        try:
            msgs = self.parser.parse_buffer(data) or []
        except self.mav.MAVError:
            return
        for m in msgs:
            self.received += 1
            kind = m.get_type()
            if kind == "ATTITUDE":
                self.attitudes.append((float(m.roll), float(m.pitch), float(m.yaw)))
            elif kind == "PARAM_VALUE":
                name = m.param_id.split("\x00", 1)[0]
                self.params[name] = float(m.param_value)
                self.param_count = int(m.param_count)

    def read_params(self, timeout: float = 5.0) -> dict[str, float]:
        """Every parameter, by PARAM_REQUEST_LIST then PARAM_REQUEST_READ of what is missing."""
        self.params = {}
        self.param_count = 0
        self.send_msg(self.mav.MAVLink_param_request_list_message(0, 0))
        end = time.monotonic() + timeout
        index = 0
        while time.monotonic() < end:
            time.sleep(0.1)
            if self.param_count and len(self.params) >= self.param_count:
                break
            if self.param_count and index < self.param_count:
                # Whatever a rate limit or a lost datagram held back, one at a time.
                for i in range(index, min(self.param_count, index + 10)):
                    self.send_msg(self.mav.MAVLink_param_request_read_message(0, 0, b"", i))
                index += 10
        return dict(self.params)


# ---------------------------------------------------------------------------- the run


def _state_files(directory: Path) -> dict[str, str]:
    files = sorted(directory.iterdir()) if directory.is_dir() else []
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.is_file()}


def _expected_angles(frames: list[Any]) -> dict[int, list[tuple[float, float, float]]]:
    """Roll, pitch, yaw of every offline frame as the daemon computes them, binned by yaw."""
    from bridge.core.attitude import AttitudeEngine
    from bridge.core.calibration import Calibration

    engine = AttitudeEngine(Calibration(), reference=None, heading_reference="magnetic")
    seen: dict[tuple[int, ...], tuple[float, float, float]] = {}
    bins: dict[int, list[tuple[float, float, float]]] = {}
    for f in frames:
        key = (f.mx, f.my, f.mz, f.ax, f.ay, f.az)
        if key in seen:
            continue
        a = engine.solve_counts(*key)
        seen[key] = (a.roll, a.pitch, a.yaw)
        bins.setdefault(round(a.yaw * 1000), []).append(seen[key])
    return bins


def false_frames(
    attitudes: list[tuple[float, float, float]], bins: dict[int, list[tuple[float, float, float]]]
) -> int:
    """ATTITUDE messages whose angles match no frame that was sent."""
    bad = 0
    for roll, pitch, yaw in attitudes:
        b = round(yaw * 1000)
        near = [x for k in (b - 1, b, b + 1) for x in bins.get(k, ())]
        # +-pi: the same heading on both sides of the wrap
        if abs(abs(yaw) - math.pi) < 1e-3:
            near += [x for k in (-b - 1, -b, -b + 1) for x in bins.get(k, ())]
        if not any(
            abs(roll - r) <= MATCH_TOL_RAD
            and abs(pitch - p) <= MATCH_TOL_RAD
            and min(abs(yaw - y), 2 * math.pi - abs(yaw - y)) <= MATCH_TOL_RAD
            for r, p, y in near
        ):
            bad += 1
    return bad


def _config(tmp: Path, device: str, udp_port: int) -> Path:
    # Tilt frame by frame from the accelerometer: the false-frame judge decodes offline and
    # needs every ATTITUDE to be a function of one frame. Under "auto" a fuzzed frame whose
    # accelerometer reads far from 1 g (a boundary token with its checksum made right) is
    # acceleration, so the tilt is held and matched to the field (docs/tilt.md) and the next
    # ATTITUDEs rightly match no single frame.
    cfg = tmp / "fuzz.toml"
    cfg.write_text(
        f'[device]\nport = "{device}"\nrate_hz = 100\n[heading]\ntilt = "accelerometer"\n'
        f'[mavlink]\nendpoints = ["udpin:127.0.0.1:{udp_port}"]\nrate_attitude_hz = 50.0\n'
        f'[zenoh]\nenabled = false\n[storage]\ndir = "{tmp / "state"}"\n'
    )
    return cfg


def _paced_frames(pty: PtyCompass, gen: SerialFuzz, stop: threading.Event) -> None:
    """Valid frames at 100 Hz (the daemon stays streaming while MAVLink is fuzzed)."""
    nxt = time.monotonic()
    while not stop.is_set():
        pty.write(gen.valid())
        nxt += 0.01
        stop.wait(max(0.0, nxt - time.monotonic()))


def run(
    chunks: int, messages: int, *, seed: int = 1, max_growth_mb: float = 16.0, step: Step = _no_step
) -> list[Figure]:
    """Both phases against one daemon child; the figures (see the module docstring)."""
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory(prefix="cb-fuzz-") as tmp_name:
        tmp = Path(tmp_name)
        pty = PtyCompass()
        udp_port = free_port(socket.SOCK_DGRAM)
        errlog = tmp / "daemon.log"
        serial = SerialFuzz(rng)
        stop_frames = threading.Event()
        frames = threading.Thread(
            target=_paced_frames, args=(pty, serial, stop_frames), daemon=True
        )
        frames.start()
        proc = start_daemon(_config(tmp, pty.path, udp_port), errlog)
        peer = MavlinkPeer(udp_port)
        heartbeat = peer.mav.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
        try:
            step(0.0, "starting the daemon")

            def started() -> bool:
                peer.send_msg(heartbeat)  # udpin: the daemon answers the peers it has heard
                return bool(peer.attitudes)

            if not wait_until(started, 20.0):
                raise RuntimeError(f"the daemon sent no ATTITUDE within 20 s (log: {errlog})")
            params_before = peer.read_params()
            files_before = _state_files(tmp / "state")
            rss_before = process_rss_mb(proc.pid)[0]
            stop_frames.set()
            frames.join(2.0)

            # -- phase 1: serial
            n_att = len(peer.attitudes)
            buf: list[bytes] = []
            size = 0
            t_beat = time.monotonic()
            for i in range(chunks):
                c = serial.chunk()
                buf.append(c)
                size += len(c)
                if size >= 4096 or i == chunks - 1:
                    pty.write(b"".join(buf))
                    buf, size = [], 0
                    if time.monotonic() - t_beat > 0.5:  # the daemon keeps us as a peer
                        peer.send_msg(heartbeat)
                        t_beat = time.monotonic()
                        step(0.5 * (i + 1) / chunks, f"serial {i + 1:,}/{chunks:,} chunks")
                    if proc.poll() is not None:
                        break
            pty.write(serial.valid() * 3)  # close the last partial line, flush the decode
            # What is still in the pty's buffer gets decoded and published (or the daemon died).
            wait_until(lambda: proc.poll() is not None, 1.5)
            serial_attitudes = peer.attitudes[n_att:]
            bins = _expected_angles(pty.frames)
            n_false = false_frames(serial_attitudes, bins)

            # -- phase 2: MAVLink
            stop_frames.clear()
            frames = threading.Thread(
                target=_paced_frames, args=(pty, serial, stop_frames), daemon=True
            )
            frames.start()
            fuzz = MavlinkFuzz(rng, sorted(params_before))
            for i in range(messages):
                peer.send(fuzz.packet())
                if i % 200 == 199:
                    time.sleep(0.01)  # ~20k/s: the daemon's inbox is bounded, not infinite
                    step(0.5 + 0.5 * (i + 1) / messages, f"mavlink {i + 1:,}/{messages:,}")
                    if proc.poll() is not None:
                        break
            time.sleep(1.0)  # coalesced parameter saves land
            alive = proc.poll() is None
            final = MavlinkPeer(udp_port)  # a new peer: no rate limit earned by the fuzzer
            final.send_msg(heartbeat)
            params_after = final.read_params() if alive else {}
            responsive = alive and bool(params_after)
            final.close()
            rss_after = process_rss_mb(proc.pid)[0] if alive else math.nan
            files_after = _state_files(tmp / "state")
        finally:
            stop_frames.set()
            frames.join(2.0)
            stop_child(proc)
            code = proc.returncode
            peer.close()
            pty.close()
        log_text = errlog.read_text(errors="replace")

    effects = fuzz.effects
    changed = sorted(
        n for n in set(params_before) | set(params_after) if params_before.get(n) != params_after.get(n)
    )  # fmt: skip
    unexplained = [n for n in changed if not effects.allows(n)]
    changed_files = sorted(
        n for n in set(files_before) | set(files_after) if files_before.get(n) != files_after.get(n)
    )  # fmt: skip
    legit_files = {"params.json", "params.json.prev"}
    if effects.calibration or any(n.startswith("COMPASS_") for n in effects.params):
        legit_files |= {"calibration.json", "calibration.json.prev"}
    unexplained += [f"file {n}" for n in changed_files if n not in legit_files]
    crashes = int(not alive) + int(alive and not responsive) + int(code != 0)
    tracebacks = log_text.count("Traceback (most recent call last)")
    first_tb = ""
    if tracebacks:  # one log record: the daemon logs a traceback as one line, \n escaped
        first_tb = log_text[log_text.find("Traceback") :].splitlines()[0][-1500:]
    growth = rss_after - rss_before
    return [
        Figure("false_frames", n_false, "ATTITUDE", 0.0, detail={
            "chunks": chunks, "bytes": pty.bytes, "valid_frames_sent": len(pty.frames),
            "attitude_checked": len(serial_attitudes)}),
        Figure("crashes", crashes, "", 0.0, detail={
            "alive": alive, "answers_param_read": responsive, "exit_code": code}),
        Figure("tracebacks", tracebacks, "in the daemon's log", 0.0,
               detail={"first": first_tb} if first_tb else {}),
        Figure("state_changes", len(unexplained), "unexplained", 0.0, detail={
            "messages": messages, "legitimate_params": [n for n in changed if effects.allows(n)],
            "files_changed": changed_files, "unexplained": unexplained}),
        Figure("memory_growth", growth, "MB RSS", max_growth_mb, detail={
            "rss_before_mb": round(rss_before, 1), "rss_after_mb": round(rss_after, 1)}),
    ]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks fuzz``: print the figures; exit 1 if any is not zero."""
    from bridge.tools.progress import Progress

    ap = argparse.ArgumentParser(
        prog="python -m benchmarks fuzz",
        description="Drive a running daemon with fuzzed serial chunks and MAVLink messages.",
    )
    ap.add_argument("--chunks", type=int, default=1_000_000, help="serial fuzz chunks")
    ap.add_argument("--messages", type=int, default=100_000, help="MAVLink fuzz messages")
    ap.add_argument("--seed", type=int, default=1, help="random seed (a run is repeatable)")
    ap.add_argument(
        "--max-growth-mb", type=float, default=16.0, help="RSS growth still counted as none"
    )
    report_options(ap)
    fuzz_hostile.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.chunks < 1 or args.messages < 1:
        ap.error("--chunks and --messages must be >= 1")
    with Progress("fuzz", 1.0, enabled=args.progress) as bar:
        figures = run(
            args.chunks,
            args.messages,
            seed=args.seed,
            max_growth_mb=args.max_growth_mb,
            step=lambda f, n: bar.update(f, note=n),
        )
        figures += fuzz_hostile.from_args(args, lambda f, n: bar.update(f, note=n))
    return report(figures, args.json)


if __name__ == "__main__":
    sys.exit(main())
