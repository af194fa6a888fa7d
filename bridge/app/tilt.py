"""Where each frame's tilt comes from: the application's owner of the tilt estimate.

:class:`TiltSources` is the attitude engine's tilt policy
(:class:`~bridge.core.attitude.TiltPolicy`): for every frame the pipeline
solves, it gives the down to compensate the heading with, from the pure
estimate (:class:`~bridge.core.tilt.TiltFilter`) fed with that frame's vectors
and, in the companion role, the autopilot's attitude at the frame's instant.

The MAVLink adapter hands it what the autopilot says -- its ATTITUDE /
ATTITUDE_QUATERNION (:meth:`TiltSources.autopilot_attitude`) and the answers
to the bridge's TIMESYNC requests (:meth:`TiltSources.autopilot_timesync`) --
from its endpoint threads; the pipeline asks :meth:`TiltSources.tilt` from the
link's reader thread. The autopilot's side is behind a lock (several endpoint
threads may deliver); the pipeline reads immutable snapshots, and owns the
filter and the mounting residual alone.

Why taking the autopilot's tilt while feeding it a heading makes no loop that
can run away: its roll and pitch come from its gyros and accelerometers; the yaw
the bridge feeds it corrects its heading. The one path between them is the
horizontal acceleration its estimator rotates by the heading to compare with
GPS velocities: a heading error ``e`` during an acceleration ``a`` can bend its
tilt by at most ``e * a / g`` (slowly), which bends our heading by ``tan(dip)``
times that -- a loop gain below one (0.6 at 0.3 g and a dip of 63 deg), over
seconds. docs/tilt.md has the longer account.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bridge.core.aligned import AttitudeSample, AttitudeTrack, ClockMap, MountingResidual
from bridge.core.tilt import TILT_SOURCES, TiltEstimate, TiltFilter, TiltSource
from bridge.core.tilt_settings import TiltSettings
from bridge.core.vectors import Vec3, unit

log = logging.getLogger(__name__)

#: The autopilot's sigma (deg) assumed until the residual's scatter says better (an
#: unlearnt mounting residual is worth about this much), and never exceeded.
UNLEARNT_AUTOPILOT_SIGMA_DEG = 1.0
#: The autopilot's roll/pitch are never taken to be better than this (deg).
MIN_AUTOPILOT_SIGMA_DEG = 0.1
#: A $PGMRA line's length in bits on the wire (10 per byte, about 64 bytes): the
#: frame was sampled that long before its last byte came.
PGMRA_LINE_BITS = 640


def frame_latency_s(baud: int) -> float:
    """How long before its arrival a compass frame was sampled: its line's time on the
    wire at ``baud`` (the firmware samples and sends at the tick)."""
    return PGMRA_LINE_BITS / baud if baud > 0 else 0.0


@dataclass(slots=True)
class AutopilotLink:
    """What the bridge has heard of the autopilot's attitude (counters for ``status``)."""

    messages: int = 0  #: ATTITUDE / ATTITUDE_QUATERNION taken
    refused: int = 0  #: dropped: non-finite, or an autopilot clock going back mid-stream
    last_arrival: float | None = None  #: monotonic time of the last one
    reboots: int = 0  #: times its clock went back (it rebooted)
    timesyncs: int = 0  #: TIMESYNC answers taken
    rate_hz: float = 0.0  #: its message rate, low-passed


@dataclass(slots=True)
class TiltCounts:
    """Frames per tilt source since the start."""

    by_source: dict[str, int] = field(default_factory=lambda: dict.fromkeys(TILT_SOURCES, 0))


class TiltSources:
    """The engine's tilt policy and the autopilot's attitude (see the module docstring).

    ``frame_latency`` is how long before its arrival a compass frame was sampled
    (:func:`frame_latency_s`); ``clock`` the monotonic clock the MAVLink adapter
    stamps arrivals with (the pipeline's frames carry the same clock).
    """

    def __init__(
        self,
        settings: TiltSettings | None = None,
        *,
        frame_latency: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.filter = TiltFilter(settings)
        self.frame_latency = frame_latency
        self.clock = clock
        self.residual = MountingResidual()
        self.link = AutopilotLink()
        self.counts = TiltCounts()
        self.last: TiltEstimate | None = None
        self._clock_map = ClockMap()
        self._track = AttitudeTrack()
        self._lock = threading.Lock()
        self._reset_pending = False

    # -- the autopilot's side (MAVLink endpoint threads) --------------------------------

    def autopilot_attitude(
        self, time_boot_ms: int, down: Vec3, arrival: float, rate: Vec3 | None = None
    ) -> None:
        """The autopilot's ATTITUDE(_QUATERNION): its stamp, the unit down in its body axes
        (from its roll and pitch), when it arrived (our monotonic clock), and its body
        rates (rad/s) when given."""
        # (Written out, not all() over generators: this runs for every message.)
        dx, dy, dz = down
        if not (
            math.isfinite(dx)
            and math.isfinite(dy)
            and math.isfinite(dz)
            and math.sqrt(dx * dx + dy * dy + dz * dz) > 0.5  # norm(down)
        ):
            self.link.refused += 1
            return
        if rate is not None and not (
            -50.0 < rate[0] < 50.0 and -50.0 < rate[1] < 50.0 and -50.0 < rate[2] < 50.0
        ):  # (NaN fails every comparison)
            rate = None  # a gyro's word it cannot have meant: extrapolate without it
        remote = time_boot_ms / 1000.0
        with self._lock:
            link = self.link
            if link.last_arrival is not None:
                gap = arrival - link.last_arrival
                if gap > 0.0:
                    link.rate_hz += 0.1 * (1.0 / max(gap, 1e-3) - link.rate_hz)
            if self._clock_map.arrival(remote, arrival):
                link.reboots += 1
                self._track.clear()
                log.info("tilt: the autopilot's clock went back (a reboot): its track starts anew")
            self._track.add(AttitudeSample(remote, unit(down), rate))
            link.messages += 1
            link.last_arrival = arrival

    def autopilot_timesync(self, sent: float, remote_s: float, received: float) -> None:
        """An answer to our TIMESYNC request: sent and received on our clock, the
        autopilot's time in between (its ``tc1``, seconds)."""
        with self._lock:
            self._clock_map.round_trip(sent, remote_s, received)
            self.link.timesyncs += 1

    def heard_autopilot(self, within_s: float = 5.0) -> bool:
        """The autopilot's attitude arrived within ``within_s`` (it streams)."""
        last = self.link.last_arrival
        return last is not None and self.clock() - last < within_s

    # -- the pipeline's side (the link's reader thread) ---------------------------------

    def _autopilot_down(self, t: float) -> tuple[Vec3, Vec3, float] | None:
        """(raw down, down in the compass's axes, extrapolated s) at frame time ``t``."""
        offset = self._clock_map.offset
        if offset is None:
            return None
        got = self._track.at(t - self.frame_latency - offset)
        if got is None:
            return None
        raw = unit(got[0])
        return raw, self.residual.apply(raw), got[1]

    def _autopilot_sigma_deg(self) -> float:
        scatter = self.residual.scatter_deg
        if scatter is None:
            return UNLEARNT_AUTOPILOT_SIGMA_DEG
        # The scatter is of the two downs together (3-D angle: both axes); the
        # accelerometer's share is its white noise.
        per_axis = 0.5 * scatter * scatter - self.filter.white_deg**2
        return min(
            UNLEARNT_AUTOPILOT_SIGMA_DEG,
            max(MIN_AUTOPILOT_SIGMA_DEG, math.sqrt(max(0.0, per_axis))),
        )

    def tilt(self, mag: Vec3, accel: Vec3, t: float, *, field_ok: bool) -> TiltEstimate:
        """The engine's tilt policy: this frame's down (see :class:`TiltFilter`)."""
        if self._reset_pending:
            self._reset_pending = False
            self.filter.reset()
            self.residual.reset()
        f = self.filter
        # (No autopilot's clock, no autopilot's down: checked here, not in a call, for the
        # standalone frames.)
        ap = None if self._clock_map.offset is None else self._autopilot_down(t)
        if ap is None:  # standalone (nearly always where no autopilot streams)
            est = f.update(mag, accel, t, field_ok=field_ok)
        else:
            est = f.update(
                mag,
                accel,
                t,
                external=ap[1],
                external_sigma_deg=self._autopilot_sigma_deg(),
                field_ok=field_ok,
            )
            gx, gy, gz = accel
            if (
                not est.manoeuvre
                and ap[2] < 0.3
                and abs(math.sqrt(gx * gx + gy * gy + gz * gz) - 1.0) < 0.03  # norm(accel)
                and abs(f.turn_rate_dps) < 0.5 * f.settings.turn_dps
            ):
                # Quasi-static: the accelerometer's down is gravity's; it teaches the residual.
                self.residual.add(unit(accel), ap[0])
        self.counts.by_source[est.source] += 1
        self.last = est
        return est

    def reset(self, why: str) -> None:
        """The compass's mounting or calibration changed: the estimate and the learnt
        mounting residual start again (at the pipeline's next frame)."""
        log.info("tilt: estimate restarts (%s)", why)
        self._reset_pending = True

    # -- status -------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """The tilt source's state, JSON-ready (``status``, Zenoh status@1 ``tilt``)."""
        est = self.last
        link = self.link
        now = self.clock()
        cm = self._clock_map
        f = self.filter
        out: dict[str, Any] = {
            "source": est.source if est is not None else None,
            "heading_sigma_deg": _r(est.heading_sigma_deg) if est is not None else None,
            "manoeuvre": est.manoeuvre if est is not None else None,
            "frames": dict(self.counts.by_source),
            "learned_dip_deg": _r(f.learned_dip_deg),
            "vibration_deg": _r(f.white_deg),
            "autopilot": {
                "heard": self.heard_autopilot(),
                "messages": link.messages,
                "refused": link.refused,
                "age_s": _r(now - link.last_arrival) if link.last_arrival is not None else None,
                "rate_hz": _r(link.rate_hz),
                "reboots": link.reboots,
                "timesyncs": link.timesyncs,
                "clock": "timesync"
                if cm.synced
                else ("arrivals" if cm.offset is not None else None),
                "round_trip_ms": _r(1000.0 * cm.round_trip_s)
                if cm.round_trip_s is not None
                else None,
                "residual_deg": _r(self.residual.rotation_deg()),
                "residual_pairs": round(self.residual.pairs),
                "sigma_deg": _r(self._autopilot_sigma_deg()) if link.messages else None,
            },
        }
        return out


def tilt_source_index(source: TiltSource | str) -> int:
    """A tilt source's number (MAVLink ``TILT_SRC``): 0 accelerometer, 1 autopilot, 2 magnetometer."""
    return TILT_SOURCES.index(source)


def _r(v: float | None, digits: int = 2) -> float | None:
    return None if v is None or not math.isfinite(v) else round(v, digits)


__all__ = [
    "AutopilotLink",
    "TiltSources",
    "frame_latency_s",
    "tilt_source_index",
]
