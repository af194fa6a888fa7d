"""A child process's CPU and memory, read from outside (the benchmarks' one copy)."""

from __future__ import annotations

import math
import os
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


def process_rss_mb(pid: int) -> tuple[float, float]:
    """Resident set size and its high-water mark of process ``pid``, in MB."""
    rss = hwm = math.nan
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024.0
        elif line.startswith("VmHWM:"):
            hwm = int(line.split()[1]) / 1024.0
    return rss, hwm
