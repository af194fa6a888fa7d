"""What the live benchmarks read of a child process from outside (one copy for pipeline,
versus and the fuzzers): its CPU, its memory, its ATTITUDE datagrams."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import threading
import time
from pathlib import Path


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


class AttitudeTap:
    """ATTITUDE datagrams a child sends to ``port`` on 127.0.0.1, each kept as (monotonic
    arrival time, yaw in radians) by a receiving thread."""

    def __init__(self, name: str) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
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
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            t = time.monotonic()
            try:
                msgs = parser.parse_buffer(data) or []
            except mav.MAVError:
                continue
            self.received.extend((t, float(m.yaw)) for m in msgs if m.get_type() == "ATTITUDE")
