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
* **threads_change**, **fds_change** -- the largest minus the smallest count. Target 0.
* **lists_answered** -- the share of the parameter lists that came whole. Target 100 %.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from benchmarks.figures import Figure, Step, no_step, report, report_options
from benchmarks.procstat import (
    free_port,
    process_rss_mb,
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


@dataclass
class Sample:
    """One reading of the child: seconds since the first, resident MB, threads, files."""

    t: float
    rss_mb: float
    threads: int
    fds: int


@dataclass
class GroundStation:
    """What the ground station asked and got: parameter lists and how many came whole."""

    lists: int = 0
    whole: int = 0
    sets: int = 0
    acks: int = 0


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


def after_warmup(samples: Sequence[Sample], warmup_s: float) -> list[Sample]:
    """The samples from ``warmup_s`` on."""
    return [s for s in samples if s.t >= warmup_s]


def figures(samples: Sequence[Sample], gcs: GroundStation, warmup_s: float) -> list[Figure]:
    """The soak's figures (see the module docstring) from its samples after ``warmup_s``."""
    kept = after_warmup(samples, warmup_s)
    span = (kept[-1].t - kept[0].t) if kept else 0.0
    growth = slope_per_hour(kept)
    rss = {"first_mb": kept[0].rss_mb, "last_mb": kept[-1].rss_mb} if kept else {}

    def change(name: str) -> float:
        values = [getattr(s, name) for s in kept]
        return float(max(values) - min(values)) if values else math.nan

    return [
        Figure(
            "rss_growth",
            growth,
            "MB/h of resident set",
            RSS_TARGET_MB_PER_H,
            detail={**rss, "samples": len(kept), "over_s": round(span, 1)},
        ),
        Figure("threads_change", change("threads"), "threads (max - min)", 0.0),
        Figure("fds_change", change("fds"), "open files (max - min)", 0.0),
        Figure(
            "lists_answered",
            100.0 * gcs.whole / gcs.lists if gcs.lists else math.nan,
            "% of parameter lists whole",
            100.0,
            lower_is_better=False,
            detail={"lists": gcs.lists, "sets": gcs.sets, "command_acks": gcs.acks},
        ),
    ]


def _config(tmp: Path, gcs_port: int) -> Path:
    cfg = tmp / "soak.toml"
    cfg.write_text(
        "\n".join(
            [
                "[device]",
                'port = "sim"',
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
        answers = ["PARAM_VALUE", "COMMAND_ACK"]
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
                gcs.acks += m is not None and m.get_type() == "COMMAND_ACK"
            k += 1
    finally:
        conn.close()


def run(
    minutes: float = 10.0, *, period_s: float = 5.0, sample_s: float = 5.0, step: Step = no_step
) -> tuple[list[Sample], GroundStation]:
    """The daemon child for ``minutes``, the ground station beside it; the samples.
    ``period_s`` must be longer than the bridge's :data:`LIST_INTERVAL_S`: a peer asking
    for the list more often is refused by design (the list amplifier's limit)."""
    if period_s <= LIST_INTERVAL_S:
        raise ValueError(f"period_s must be > {LIST_INTERVAL_S} s (LIST_INTERVAL_S)")
    samples: list[Sample] = []
    gcs = GroundStation()
    stop = threading.Event()
    with tempfile.TemporaryDirectory(prefix="cb-soak-") as tmp:
        gcs_port = free_port(socket.SOCK_DGRAM)
        cfg = _config(Path(tmp), gcs_port)
        stderr = Path(tmp) / "daemon.log"
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
            while time.monotonic() < end:
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon exited ({proc.returncode})")
                rss, _ = process_rss_mb(proc.pid)
                samples.append(
                    Sample(
                        time.monotonic() - t0,
                        rss,
                        len(os.listdir(f"/proc/{proc.pid}/task")),
                        len(os.listdir(f"/proc/{proc.pid}/fd")),
                    )
                )
                step(min(1.0, (time.monotonic() - t0) / (minutes * 60.0)), f"{rss:.1f} MB")
                time.sleep(max(0.0, min(sample_s, end - time.monotonic())))
        finally:
            stop.set()
            station.join(period_s + 2.0)
            stop_child(proc)
        log.debug("daemon stderr: %s", stderr.read_text(errors="replace")[-2000:])
    return samples, gcs


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
    report_options(ap)
    args = ap.parse_args(argv)
    if args.minutes <= 0 or args.period <= LIST_INTERVAL_S or args.sample <= 0:
        ap.error(f"--minutes and --sample must be > 0, --period > {LIST_INTERVAL_S:g}")
    with Progress("soak", 1.0, enabled=args.progress) as bar:
        samples, gcs = run(
            args.minutes,
            period_s=args.period,
            sample_s=args.sample,
            step=lambda f, n: bar.update(f, note=n),
        )
    warmup = warmup_s(args.minutes)
    return report(figures(samples, gcs, warmup), args.json, warmup_s=warmup)


if __name__ == "__main__":
    sys.exit(main())
