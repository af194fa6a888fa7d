"""A long run of the real daemon: ``python -m benchmarks soak [--minutes 10]``.

The bridge runs for hours on a vehicle, so what it holds must not grow with the
frames it has read or the requests it has answered. One daemon child (``python -m
bridge run``) on its built-in simulated compass at 100 Hz, MAVLink (``udpout`` to a
ground station in this process) and Zenoh (a loopback listener) on, every other
setting as shipped. Every ``--period`` seconds the ground station does what one does
in service: a PARAM_REQUEST_LIST (every PARAM_VALUE counted), a PARAM_SET (a stream
rate, between two values: the parameter store writes ``params.json`` each time) and
a GET_MESSAGE_INTERVAL command. Every ``--sample`` seconds the child's resident set
(``VmRSS``), threads (``/proc/PID/task``) and open files (``/proc/PID/fd``) are read.

Figures, from the samples after the warm-up (:func:`warmup_s`: the first third of the
run, at least 60 s -- buffers, histories and caches filling to their caps):

* **rss_growth** -- the least-squares slope of the resident set, MB an hour. Target
  1 MB/h (a day of service within the memory a small companion computer spares).
* **threads_change**, **fds_change** -- how far the count's floor moved: the least count of
  each run of :data:`FLOOR_READINGS` readings, the largest of those minus the smallest.
  A file open for a moment (``params.json`` being written, caught mid-way on a loaded
  host) lifts one reading; a leak lifts every one after it. Target 0.
* **lists_answered** -- the share of the parameter lists that came whole. Target 100 %.

``--unplug-every S`` runs the compass as a vehicle's USB-serial adapter does: a separate
simulated compass on a pseudo-terminal (``python -m bridge simulate``), which the daemon
reads through pyserial as it reads a real one. Every S seconds the simulator's cable is
pulled (SIGUSR1: the pty goes, a new one comes ``--unplug-s`` later) and, half-way
between, it sends a burst of line noise (SIGUSR2). Threads and files are then judged on
the readings taken with the link back (its "Compass link restored" heard, the last pull
:data:`SETTLE_S` past its return), and one figure more:

* **link_returns** -- the share of the pulls the link came back from (a STATUSTEXT
  "Compass link restored" for each). Target 100 %.
* **reconnects_unheard** -- the daemon's own count of its port's reopenings (SYS_STATUS
  ``errors_count2``, 1 Hz) against the returns the ground station heard, on the last
  settled reading: a reopening nobody was told of, or a return with none. Target 0.

Every run also reads the daemon's other counters from SYS_STATUS (``errors_comm``: the
lines dropped as noise; ``errors_count1`` lost frames; ``errors_count4`` pipeline
errors), and one figure more:

* **pipeline_errors** -- frames the daemon's pipeline failed on. Target 0.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.figures import Figure, Step, no_step, report, report_options
from benchmarks.procstat import (
    free_port,
    process_rss_mb,
    start_bridge,
    start_daemon,
    stop_child,
    wait_until,
)
from bridge.mavlink.paramproto import LIST_INTERVAL_S

log = logging.getLogger(__name__)

#: The parameter the ground station sets back and forth (a stream rate, Hz).
SET_PARAM = "BRG_SR_HUD"
SET_VALUES = (2.0, 4.0)
RSS_TARGET_MB_PER_H = 1.0
#: After a pull, readings count for threads and files this long past the pty's return.
SETTLE_S = 3.0
#: Threads and files are judged by their floor over runs of this many readings.
FLOOR_READINGS = 6
#: The link's events as the MAVLink adapter words them (bridge.app.pipeline).
LINK_LOST, LINK_RESTORED = "Compass link lost", "Compass link restored"


@dataclass
class Sample:
    """One reading of the child: seconds since the first, resident MB, threads, files."""

    t: float
    rss_mb: float
    threads: int
    fds: int
    settled: bool = True  #: the link up and settled (always, without pulls)
    #: The daemon's port reopenings (its SYS_STATUS; None before one came) and the
    #: returns heard, both at this reading.
    reconnects: int | None = None
    restored: int = 0


@dataclass
class GroundStation:
    """What the ground station asked and got: parameter lists and how many came whole."""

    lists: int = 0
    whole: int = 0
    sets: int = 0
    acks: int = 0
    lost: int = 0  #: "Compass link lost" heard
    restored: int = 0  #: "Compass link restored" heard
    #: The daemon's own link counters, from its last SYS_STATUS (None: none came yet).
    reconnects: int | None = None
    lost_frames: int = 0
    bad_lines: int = 0
    pipeline_errors: int = 0

    def hear(self, text: str) -> None:
        """Count a STATUSTEXT that tells of the compass link."""
        self.lost += text.startswith(LINK_LOST)
        self.restored += text.startswith(LINK_RESTORED)

    def status(self, msg: Any) -> None:
        """Take the daemon's link counters from a SYS_STATUS (bridge.mavlink.telemetry)."""
        self.reconnects = int(msg.errors_count2)
        self.lost_frames = int(msg.errors_count1)
        self.bad_lines = int(msg.errors_comm)
        self.pipeline_errors = int(msg.errors_count4)

    def take(self, msg: Any) -> bool:
        """A STATUSTEXT or SYS_STATUS counted (True), or another message (False)."""
        kind = msg.get_type()
        if kind == "STATUSTEXT":
            self.hear(msg.text)
        elif kind == "SYS_STATUS":
            self.status(msg)
        else:
            return False
        return True


def slope_per_hour(samples: Sequence[Sample]) -> float:
    """The least-squares slope of ``rss_mb`` over ``t``, MB an hour (NaN without two
    readings at different times: no slope to give)."""
    n = len(samples)
    mt = sum(s.t for s in samples) / n if n else 0.0
    mr = sum(s.rss_mb for s in samples) / n if n else 0.0
    sxx = sum((s.t - mt) ** 2 for s in samples)
    if sxx == 0.0:
        return math.nan
    sxy = sum((s.t - mt) * (s.rss_mb - mr) for s in samples)
    return sxy / sxx * 3600.0


def warmup_s(minutes: float) -> float:
    """The warm-up of a run of ``minutes``: its first third, at least 60 s; none in a run
    of 90 s or less (a check of the rig, too short to judge growth)."""
    run_s = minutes * 60.0
    return max(60.0, run_s / 3.0) if run_s > 90.0 else 0.0


def floor_change(counts: Sequence[int], run: int = FLOOR_READINGS) -> float:
    """How far the floor of ``counts`` moved: the least count of each run of ``run``
    readings (a short last run joins the one before it), the largest floor minus the
    smallest; NaN without readings."""
    if not counts:
        return math.nan
    starts = list(range(0, len(counts), run))
    if len(starts) > 1 and len(counts) - starts[-1] < run:
        starts.pop()  # the short tail joins the run before it
    ends = [*starts[1:], len(counts)]
    floors = [min(counts[a:b]) for a, b in zip(starts, ends, strict=True)]
    return float(max(floors) - min(floors))


def after_warmup(samples: Sequence[Sample], warmup_s: float) -> list[Sample]:
    """The samples from ``warmup_s`` on."""
    return [s for s in samples if s.t >= warmup_s]


def figures(
    samples: Sequence[Sample], gcs: GroundStation, warmup_s: float, pulls: int = 0
) -> list[Figure]:
    """The soak's figures (see the module docstring) from its samples after ``warmup_s``;
    ``pulls``: the pulls of the compass's cable (none: no ``link_returns``)."""
    kept = after_warmup(samples, warmup_s)
    span = (kept[-1].t - kept[0].t) if kept else 0.0
    growth = slope_per_hour(kept)
    rss = {"first_mb": kept[0].rss_mb, "last_mb": kept[-1].rss_mb} if kept else {}

    def change(name: str, what: str) -> Figure:
        values = [getattr(s, name) for s in kept if s.settled]
        seen = {"readings": len(values), "counts": sorted(set(values))}
        moved = floor_change(values)
        return Figure(f"{name}_change", moved, f"{what} (floor's change)", 0.0, detail=seen)

    returns = []
    if pulls:
        last = next((s for s in reversed(samples) if s.settled and s.reconnects is not None), None)
        unheard = math.nan if last is None else float(abs((last.reconnects or 0) - last.restored))
        counted = (
            {}
            if last is None
            else {
                "at_s": round(last.t, 1),
                "reconnects": last.reconnects,
                "restored": last.restored,
            }
        )
        returns += [
            Figure(
                "link_returns",
                100.0 * min(gcs.restored, pulls) / pulls,
                "% of cable pulls the link came back from",
                100.0,
                lower_is_better=False,
                detail={"pulls": pulls, "lost": gcs.lost, "restored": gcs.restored},
            ),
            Figure(
                "reconnects_unheard",
                unheard,
                "port reopenings not heard as returns, or returns without one",
                0.0,
                detail={**counted, "bad_lines": gcs.bad_lines, "lost_frames": gcs.lost_frames},
            ),
        ]
    return [
        Figure(
            "rss_growth",
            growth,
            "MB/h of resident set",
            RSS_TARGET_MB_PER_H,
            detail={**rss, "samples": len(kept), "over_s": round(span, 1)},
        ),
        change("threads", "threads"),
        change("fds", "open files"),
        Figure(
            "lists_answered",
            100.0 * gcs.whole / gcs.lists if gcs.lists else math.nan,
            "% of parameter lists whole",
            100.0,
            lower_is_better=False,
            detail={"lists": gcs.lists, "sets": gcs.sets, "command_acks": gcs.acks},
        ),
        Figure(
            "pipeline_errors",
            math.nan if gcs.reconnects is None else float(gcs.pipeline_errors),
            "frames the pipeline failed on (SYS_STATUS)",
            0.0,
        ),
        *returns,
    ]


def _config(tmp: Path, gcs_port: int, port: str = "sim") -> Path:
    cfg = tmp / "soak.toml"
    cfg.write_text(
        "\n".join(
            [
                "[device]",
                f'port = "{port}"',
                "rate_hz = 100",
                "[mavlink]",
                f'endpoints = ["udpout:127.0.0.1:{gcs_port}"]',
                "[zenoh]",
                "enabled = true",
                f'listen = ["tcp/127.0.0.1:{free_port()}"]',
                'key_prefix = "soak/compass"',
                "[storage]",
                f'dir = "{tmp}/state"',
                "",
            ]
        )
    )
    return cfg


def _ground_station(url: str, period_s: float, gcs: GroundStation, stop: threading.Event) -> None:
    """Every ``period_s``: a parameter list, a PARAM_SET and a command, to component 200."""
    from pymavlink import mavutil

    mav = mavutil.mavlink
    conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
    try:
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=15.0)
        if hb is None:
            return
        target = (hb.get_srcSystem(), hb.get_srcComponent())
        answers = ["PARAM_VALUE", "COMMAND_ACK", "STATUSTEXT", "SYS_STATUS"]
        k = 0
        while not stop.is_set():
            end = time.monotonic() + period_s
            conn.mav.param_request_list_send(*target)
            seen: set[int] = set()
            count = -1
            while time.monotonic() < end and not stop.is_set():
                m = conn.recv_match(type=answers, blocking=True, timeout=0.2)
                if m is None:
                    continue
                if gcs.take(m):
                    continue
                if m.get_type() == "COMMAND_ACK":  # the last period's, late
                    gcs.acks += 1
                    continue
                seen.add(m.param_index)  # (indices 0 .. count - 1)
                count = m.param_count
                if len(seen) >= count:
                    break
            whole = count > 0 and len(seen) >= count
            if stop.is_set() and not whole:
                break  # the run ended while this list came: not a list to judge
            gcs.lists += 1
            gcs.whole += whole
            # then a value set (its echo is not counted) and a command
            conn.mav.param_set_send(
                *target, SET_PARAM.encode(), SET_VALUES[k % 2], mav.MAV_PARAM_TYPE_REAL32
            )
            gcs.sets += 1
            conn.mav.command_long_send(
                *target, mav.MAV_CMD_GET_MESSAGE_INTERVAL, 0, mav.MAVLINK_MSG_ID_ATTITUDE,
                0, 0, 0, 0, 0, 0,
            )  # fmt: skip
            while time.monotonic() < end and not stop.is_set():
                m = conn.recv_match(type=answers, blocking=True, timeout=0.2)
                if m is not None and not gcs.take(m):
                    gcs.acks += m.get_type() == "COMMAND_ACK"
            k += 1
    finally:
        conn.close()


@dataclass
class SoakRun:
    """What a run gave: the readings, the ground station's counts, the cable pulls."""

    samples: list[Sample]
    gcs: GroundStation
    pulls: int = 0


def _start_simulator(link: Path, unplug_s: float, log: Path) -> subprocess.Popen[bytes]:
    """``python -m bridge simulate`` serving on a pty at ``link`` (a symlink), its log to
    ``log``: the compass as the daemon meets a real one, through pyserial."""
    proc = start_bridge(["simulate", "--link", str(link), "--unplug-s", f"{unplug_s:g}"], log)
    if not wait_until(lambda: link.exists() or proc.poll() is not None, 30.0) or not link.exists():
        stop_child(proc)
        raise RuntimeError(f"the simulated compass did not serve ({log.read_text()[-500:]})")
    return proc


def run(
    minutes: float = 10.0,
    *,
    period_s: float = 5.0,
    sample_s: float = 5.0,
    unplug_every_s: float = 0.0,
    unplug_s: float = 2.0,
    step: Step = no_step,
) -> SoakRun:
    """The daemon child for ``minutes``, the ground station beside it; the readings.
    ``period_s`` must be longer than the bridge's :data:`LIST_INTERVAL_S`: a peer asking
    for the list more often is refused by design (the list amplifier's limit).
    ``unplug_every_s`` > 0: the compass on a pty, its cable pulled that often for
    ``unplug_s`` (line noise half-way between); see the module docstring."""
    if period_s <= LIST_INTERVAL_S:
        raise ValueError(f"period_s must be > {LIST_INTERVAL_S} s (LIST_INTERVAL_S)")
    if unplug_every_s and unplug_every_s <= unplug_s + SETTLE_S:
        raise ValueError(f"unplug_every_s must be > unplug_s + {SETTLE_S:g} s (SETTLE_S)")
    result = SoakRun([], GroundStation())
    gcs = result.gcs
    stop = threading.Event()
    with tempfile.TemporaryDirectory(prefix="cb-soak-") as tmp:
        here = Path(tmp)
        sim = None
        if unplug_every_s:
            sim = _start_simulator(here / "compass", unplug_s, here / "simulator.log")
        gcs_port = free_port(socket.SOCK_DGRAM)
        cfg = _config(here, gcs_port, str(here / "compass") if sim else "sim")
        stderr = here / "daemon.log"
        proc = start_daemon(cfg, stderr)
        station = threading.Thread(
            target=_ground_station,
            args=(f"udpin:127.0.0.1:{gcs_port}", period_s, gcs, stop),
            name="soak-gcs",
            daemon=True,
        )
        station.start()
        try:
            if not wait_until(lambda: gcs.lists > 0 or proc.poll() is not None, 30.0):
                raise RuntimeError("the ground station heard no HEARTBEAT within 30 s")
            t0 = time.monotonic()
            end = t0 + minutes * 60.0
            pulled_at = -math.inf  # the last pull, on the run's clock
            next_pull = t0 + unplug_every_s if sim else math.inf
            noise_at = math.inf  # the next burst of line noise
            next_sample = t0
            while (now := time.monotonic()) < end:
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon exited ({proc.returncode})")
                if sim is not None and sim.poll() is not None:
                    raise RuntimeError(f"the simulated compass exited ({sim.returncode})")
                if sim is not None and now >= next_pull:
                    sim.send_signal(signal.SIGUSR1)  # the cable out, back in unplug_s
                    result.pulls += 1
                    pulled_at, next_pull = now - t0, now + unplug_every_s
                    noise_at = now + unplug_every_s / 2
                if sim is not None and now >= noise_at:
                    sim.send_signal(signal.SIGUSR2)  # a burst of line noise
                    noise_at = math.inf
                if now >= next_sample:
                    rss, _ = process_rss_mb(proc.pid)
                    back = gcs.restored >= result.pulls  # every pull heard restored
                    result.samples.append(
                        Sample(
                            now - t0,
                            rss,
                            len(os.listdir(f"/proc/{proc.pid}/task")),
                            len(os.listdir(f"/proc/{proc.pid}/fd")),
                            settled=back and now - t0 >= pulled_at + unplug_s + SETTLE_S,
                            reconnects=gcs.reconnects,
                            restored=gcs.restored,
                        )
                    )
                    step(min(1.0, (now - t0) / (minutes * 60.0)), f"{rss:.1f} MB")
                    next_sample += sample_s
                due = min(next_sample, next_pull, noise_at, end)
                time.sleep(max(0.0, due - time.monotonic()))
        finally:
            stop.set()
            station.join(period_s + 2.0)
            stop_child(proc)
            if sim is not None:
                stop_child(sim)
        log.debug("daemon stderr: %s", stderr.read_text(errors="replace")[-2000:])
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks soak``: print the figures; exit 1 if any misses its target."""
    from bridge.tools.progress import Progress

    ap = argparse.ArgumentParser(
        prog="python -m benchmarks soak",
        description="A long run of the real daemon: memory, threads, files, answers.",
    )
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the run")
    ap.add_argument("--period", type=float, default=5.0, help="seconds between requests")
    ap.add_argument("--sample", type=float, default=5.0, help="seconds between readings")
    ap.add_argument(
        "--unplug-every",
        type=float,
        default=0.0,
        metavar="S",
        help="the compass on a pty, its cable pulled every S seconds (default 0: never)",
    )
    ap.add_argument(
        "--unplug-s", type=float, default=2.0, metavar="S", help="how long a pull lasts"
    )
    report_options(ap)
    args = ap.parse_args(argv)
    if args.minutes <= 0 or args.period <= LIST_INTERVAL_S or args.sample <= 0:
        ap.error(f"--minutes and --sample must be > 0, --period > {LIST_INTERVAL_S:g}")
    if args.unplug_every and args.unplug_every <= args.unplug_s + SETTLE_S:
        ap.error(f"--unplug-every must be > --unplug-s + {SETTLE_S:g}")
    with Progress("soak", 1.0, enabled=args.progress) as bar:
        soaked = run(
            args.minutes,
            period_s=args.period,
            sample_s=args.sample,
            unplug_every_s=args.unplug_every,
            unplug_s=args.unplug_s,
            step=lambda f, n: bar.update(f, note=n),
        )
    warmup = warmup_s(args.minutes)
    figs = figures(soaked.samples, soaked.gcs, warmup, soaked.pulls)
    return report(figs, args.json, warmup_s=warmup)


if __name__ == "__main__":
    sys.exit(main())
