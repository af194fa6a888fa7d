"""What the live benchmarks read of a child process from outside (one copy for pipeline,
versus and the fuzzers): its CPU (per thread too), its memory, its ATTITUDE datagrams, the
datagrams a receiving thread reads (:func:`datagrams`); and the one bounded wait they poll
it with (:func:`wait_until`)."""

from __future__ import annotations

import math
import os
import random
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from bridge.types import ClosedOnExit


def wait_until(pred: Callable[[], object], timeout_s: float, poll_s: float = 0.05) -> bool:
    """Whether ``pred()`` held within ``timeout_s``, asked every ``poll_s`` and once more at
    the end. For watching a child process, or a real thread, from outside: nothing to wait
    on but the thing itself (the integration tests poll through it too: tests/waiting.py)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(poll_s)
    return bool(pred())


def process_cpu_s(pid: int) -> float:
    """User+system CPU seconds of process ``pid`` so far, all its threads, exited ones too.

    Read from the process's CPU-time clock, to the nanosecond: the clock id is what
    clock_getcpuclockid(3) returns on Linux (the pid, complemented, shifted past the
    clock type; 2 = CPUCLOCK_SCHED). /proc/PID/stat, the fallback, counts whole 10 ms
    ticks: 0.1 % steps over the 10 s window, too coarse for a 3 % target.
    """
    try:
        return time.clock_gettime((~pid << 3) | 2)
    except OSError:
        pass
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    # utime, stime are fields 14, 15 (1-based) of stat; after the ")" they are 12th/13th.
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_stats(pid: int) -> dict[int, tuple[str, int, int, int]]:
    """tid -> (name, run ns, voluntary, involuntary switches) of every live thread of ``pid``
    (``/proc/PID/task``: schedstat, comm, status)."""
    out: dict[int, tuple[str, int, int, int]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            run_ns = int((task / "schedstat").read_text().split()[0])
            name = (task / "comm").read_text().strip()
            vol = inv = 0
            for line in (task / "status").read_text().splitlines():
                if line.startswith("voluntary_ctxt_switches:"):
                    vol = int(line.split()[1])
                elif line.startswith("nonvoluntary_ctxt_switches:"):
                    inv = int(line.split()[1])
        except (OSError, ValueError, IndexError):
            continue  # the thread ended meanwhile
        out[int(task.name)] = (name, run_ns, vol, inv)
    return out


#: Where :func:`free_port` picks: below the kernel's ephemeral ports (Linux's
#: ip_local_port_range, 32768-60999), so no socket the kernel numbers itself -- any process's
#: client socket -- takes the port between the pick and its use (a MAVProxy told to listen on
#: a port picked seconds before found it taken once: "Address already in use"); above the
#: autopilots' fixed ports (ArduPilot's 5760 and up, PX4's 13030-19460 plus the instance).
PICK_PORTS = (20000, 32000)
#: Its own generator, seeded from the OS: Hypothesis seeds the global one for each example,
#: which would give every pytest-xdist worker the same picks.
_pick = random.Random()


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port of ``kind`` (``socket.SOCK_STREAM``, the default, or ``SOCK_DGRAM``) free on
    127.0.0.1 just now, in :data:`PICK_PORTS` (the tests' rigs take theirs here too)."""
    for _ in range(100):
        port = _pick.randint(*PICK_PORTS)
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:  # in use (or in TIME_WAIT): another
                continue
            return port
    with socket.socket(socket.AF_INET, kind) as s:  # a crowded range: the kernel's pick
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def udp_socket(timeout_s: float | None = None) -> socket.socket:
    """A UDP socket bound to a port of 127.0.0.1 the kernel picks, its reads given up after
    ``timeout_s`` (so that a receiving loop -- :func:`datagrams` -- looks at its stop and
    deadline while nothing arrives; ``None``: reads block)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(timeout_s)
    return sock


def datagrams(
    sock: socket.socket, stop: threading.Event | None = None, within_s: float = math.inf
) -> Iterator[bytes]:
    """The datagrams arriving on ``sock`` until ``stop`` is set, ``within_s`` seconds have
    passed since the first read, or the socket is closed: the loop of a receiving thread
    (``stop``), or of a test that listens for a bounded time (``within_s``). ``sock`` has a
    timeout, so that both are looked at while nothing arrives (the integration tests'
    receivers and listeners read through it too)."""
    end = time.monotonic() + within_s
    while not (stop is not None and stop.is_set()) and time.monotonic() < end:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        except OSError:
            return
        yield data


class DatagramReceiver(ClosedOnExit):
    """A socket and the thread that hands each datagram arriving on it to :meth:`handle`,
    from :meth:`start` until :meth:`close` (the loop is :func:`datagrams`, so the socket
    has a read timeout: :func:`udp_socket`). The receiving side of the benchmarks' ground
    stations and of the tests' (tests/service_harness.py: the fake service manager too);
    a subclass may add threads of its own that watch the same stop (``_threads``, before
    :meth:`start`)."""

    def __init__(self, sock: socket.socket, name: str | None = None) -> None:
        self.sock = sock
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._receive, name=name, daemon=True)]

    def start(self) -> None:
        """Start the receiving thread (and any the subclass added)."""
        for t in self._threads:
            t.start()

    def _receive(self) -> None:
        for data in datagrams(self.sock, self._stop):
            self.handle(data)

    def handle(self, data: bytes) -> None:
        """One datagram, on the receiving thread."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the threads (2 s each at most) and close the socket."""
        self._stop.set()
        for t in self._threads:
            t.join(2.0)
        self.sock.close()


def start_bridge(args: Sequence[str], log: Path) -> subprocess.Popen[bytes]:
    """``python -m bridge ARGS`` as a child, its log (stderr) to the file ``log``: a pipe
    nobody reads would fill over a long run and stop the child on its next warning. Stop
    it with :func:`stop_child`."""
    with open(log, "wb") as err:
        return subprocess.Popen(
            [sys.executable, "-m", "bridge", *args],
            stdout=subprocess.DEVNULL,
            stderr=err,
            env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
        )


def start_daemon(config: Path, log: Path) -> subprocess.Popen[bytes]:
    """``python -m bridge run --config CONFIG`` as a child (:func:`start_bridge`)."""
    return start_bridge(["run", "--config", str(config)], log)


def stop_child(proc: subprocess.Popen[bytes]) -> bytes:
    """Stop a benchmark's child: SIGTERM, 10 s to exit, then SIGKILL. Returns what it wrote
    to a piped stderr (``b""`` when not piped); its exit status is ``proc.returncode``."""
    if proc.poll() is None:
        proc.terminate()
    try:
        _, err = proc.communicate(timeout=10.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate(timeout=5.0)
    return err or b""


def process_rss_mb(pid: int) -> tuple[float, float]:
    """Resident set size and its high-water mark of process ``pid``, in MB."""
    rss = hwm = math.nan
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024.0
        elif line.startswith("VmHWM:"):
            hwm = int(line.split()[1]) / 1024.0
    return rss, hwm


#: Linux's SO_TIMESTAMPNS (asm-generic/socket.h; the socket module does not name it): each
#: datagram carries, as ancillary data, the CLOCK_REALTIME instant the kernel queued it.
SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")
_ANC_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)


def realtime_to_monotonic() -> float:
    """CLOCK_MONOTONIC minus CLOCK_REALTIME now, from the closest of several back-to-back
    readings (a thread switched out between the two would skew one pair by its time away)."""
    best = (math.inf, 0.0)
    for _ in range(20):
        m0 = time.monotonic()
        r = time.time()
        m1 = time.monotonic()
        best = min(best, (m1 - m0, (m0 + m1) / 2.0 - r))
    return best[1]


class AttitudeTap:
    """ATTITUDE datagrams a child sends to ``port`` on 127.0.0.1, each kept as (monotonic
    arrival time, yaw in radians) by a receiving thread.

    The arrival time is the kernel's: when the datagram was queued on this socket
    (SO_TIMESTAMPNS), converted to the monotonic clock. So the figure ends where the
    program under test is done, and this process's own wake-up -- a thread of a
    Python process whose other thread writes the compass's bytes, on a 2-core machine
    -- is not in it (measured: 0.1-0.3 ms at the median, more in the tail). Without
    the stamp (not Linux) the thread's clock after ``recv`` is used.
    """

    def __init__(self, name: str) -> None:
        self.sock = udp_socket(0.2)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self.kernel_stamps = True
        except OSError:
            self.kernel_stamps = False
        self._offset = realtime_to_monotonic()
        self.port: int = self.sock.getsockname()[1]
        self.received: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> AttitudeTap:
        """Start receiving."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop receiving and close the socket."""
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()

    def _run(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        while not self._stop.is_set():
            try:
                data, ancdata, _flags, _addr = self.sock.recvmsg(4096, _ANC_SPACE)
            except TimeoutError:
                continue
            except OSError:
                return
            t = time.monotonic()
            for level, kind, payload in ancdata:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, ns = _TIMESPEC.unpack(payload[: _TIMESPEC.size])
                    t = sec + ns * 1e-9 + self._offset
            try:
                msgs = parser.parse_buffer(data) or []
            except mav.MAVError:
                continue
            self.received.extend((t, float(m.yaw)) for m in msgs if m.get_type() == "ATTITUDE")
