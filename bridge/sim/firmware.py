"""Sans-I/O emulation of the GMR compass firmware 2.x, to the letter of the datasheet.

The caller owns the clock: :meth:`Firmware.receive` takes host bytes at time
``now`` and :meth:`Firmware.poll` returns every byte the device has sent up to
``now`` (seconds, any monotonic origin). Internally it is a discrete-event
machine: frame ticks, command handling, calibration sampling and flash writes
are events on one timeline, so the output does not depend on how often it is
polled.

Readings of the datasheet taken here (a firmware engineer's choices):

* **Frame timing.** A frame is sampled *exactly at its tick* and its line leaves
  at that instant (the wire's own delay is the transport's business). Ticks are
  ``anchor + k / rate`` with integer ``k``, so there is no drift; the anchor is
  the boot instant or the moment a ``RATE`` command is handled (the next frame
  comes one new period later).
* **Power-up.** ``$PGMRV`` at the boot instant, the first frame (``seq`` 0) one
  period later. ``RESET``: ``$PGMRK,RESET,OK``, then 300 ms of silence in which
  the device hears nothing, then a power-up (10 Hz, ``seq`` 0, CAL cleared).
* **Answers.** A command is handled 1-15 ms after its line arrives (the main
  loop picks it up), in order, never during a flash write (the UART buffers it).
  Answers that write flash (``MAGCAL,END``, ``ACCCAL``, ``PAR,SET``) are sent when
  the write ends. Flash writes take 30-50 ms; ticks falling inside one are not
  sampled nor sent and do not advance ``seq``.
* **Tilt** for the MAGCAL level check is the angle between the accelerometer's
  gravity vector g (the datasheet's g, level reference applied) and body z:
  ``acos(gz / |g|) < 20 deg``. **On its side** is ``|gz| < 0.35 * 491.5`` counts,
  i.e. the component itself in nominal g, not normalised.
* MAGCAL tracks min/max on every frame sample (the ADC samples once per frame);
  ``$PGMRC`` ``samples`` counts samples the routine *used* (level or on its side).
  x and y start being tracked together at the first level sample.
* **ACCCAL** samples the accelerometer at 50 Hz for 1 s (50 samples) whatever the
  output rate; **spread** is max - min per axis, MOTION if any exceeds 20 counts.
  Frames keep flowing meanwhile. The answer comes about 1.05 s after the command.
* Stored values are rounded to the published precision (offsets 0.1 count, gains
  0.0001) so ``PAR,GET`` shows exactly what the firmware computes with.
* ``PAR,SET`` sets MAGOK when the magnetometer values differ from factory and
  ACCOK when the level reference does (writing factory values back clears them).
  MAGCAL,END sets MAGOK, ACCCAL sets ACCOK.
* Not in the datasheet's STATE list but refused with ``ERR,STATE`` as well:
  ``ACCCAL``, ``PAR,SET`` and ``MAGCAL,START`` while an ACCCAL is averaging
  (they would race its flash write or its samples).
* ``MAGCAL,END`` leaves calibration mode whatever the outcome (RANGE, FLASH).
* On-board angles have no extra filtering: they are computed from the very
  counts of the frame, so a host can check them; ``-0.0`` is printed ``0.0`` and
  a heading that rounds to 360.0 is sent as 0.0.
* If the caller stops polling for more than 2 s (a suspended host), the ticks
  older than that are fast-forwarded: ``seq`` advances as if those frames had
  been sent and lost on the wire, without computing them.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.core.sensor import ACC_COUNTS_PER_G
from bridge.protocol.framing import fmt_fixed
from bridge.protocol.gmr import (
    AckFrame,
    AckReason,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    GmrDecoder,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
)
from bridge.sim.flash import Flash, FlashPage
from bridge.sim.motion import Motion, YawTurns, linear_acc_of
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors
from bridge.types import FloatArray

DEFAULT_RATE_HZ = 10
RESET_SILENCE_S = 0.3
CMD_LATENCY_S = (0.001, 0.015)
FLASH_WRITE_S = (0.030, 0.050)
PROGRESS_PERIOD_S = 1.0
ACCCAL_RATE_HZ = 50
ACCCAL_SAMPLES = 50  #: one second at ACCCAL_RATE_HZ
ACCCAL_MAX_SPREAD = 20  #: counts, max - min per axis
MAGCAL_LEVEL_TILT_DEG = 20.0
MAGCAL_SIDE_GZ_G = 0.35
MAGCAL_MIN_SPAN = 400  #: counts
MAX_BACKLOG_S = 2.0
SEQ_MODULO = 65536
FACTORY = FlashPage.factory()

# (time, tie-break order, action, liveness check: a stale event -- older boot,
# ended calibration, replaced frame schedule -- is skipped)
_Event = tuple[float, int, Callable[[float], None], Callable[[], bool] | None]


def _three_floats(v: tuple[int, int, int] | npt.ArrayLike) -> tuple[float, float, float]:
    # The firmware's own frames hand over tuples of ints (every frame): taken as they are,
    # without the round trip through a numpy array (the same floats: counts are exact).
    if type(v) is tuple and len(v) == 3:
        return float(v[0]), float(v[1]), float(v[2])
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return x, y, z


def onboard_attitude(
    m: tuple[int, int, int] | npt.ArrayLike,
    a: tuple[int, int, int] | npt.ArrayLike,
    page: FlashPage,
) -> tuple[float, float, float]:
    """The datasheet's on-board (heading, pitch, roll) in degrees, unrounded.

    ``H = K * (m - off)``, ``g = a - Goff + (0, 0, 491.5)``; pitch = -asin(gx/|g|),
    roll = atan2(gy, gz), heading = atan2(-Y, X) folded into [0, 360).
    A zero g (impossible on a working unit) gives pitch 0 instead of a NaN.
    """
    mx, my, mz = _three_floats(m)
    ax, ay, az = _three_floats(a)
    hx = page.kx * (mx - page.xoff)
    hy = page.ky * (my - page.yoff)
    hz = page.kz * (mz - page.zoff)
    gx = ax - page.gxoff
    gy = ay - page.gyoff
    gz = az - page.gzoff + ACC_COUNTS_PER_G
    gn = math.sqrt(gx * gx + gy * gy + gz * gz)
    theta = -math.asin(max(-1.0, min(1.0, gx / gn))) if gn > 0.0 else 0.0
    gamma = math.atan2(gy, gz)
    st, ct = math.sin(theta), math.cos(theta)
    sg, cg = math.sin(gamma), math.cos(gamma)
    X = hx * ct + hy * st * sg + hz * st * cg
    Y = hy * cg - hz * sg
    hdg = math.degrees(math.atan2(-Y, X)) % 360.0
    return hdg, math.degrees(theta), math.degrees(gamma)


def gravity_counts(a: tuple[int, int, int] | npt.ArrayLike, page: FlashPage) -> FloatArray:
    """The datasheet's g vector in counts: ``a - (Gxoff, Gyoff, Gzoff) + (0, 0, 491.5)``."""
    v = np.asarray(a, dtype=np.float64).reshape(3)
    return v - np.array([page.gxoff, page.gyoff, page.gzoff - ACC_COUNTS_PER_G])


_CAL, _MAGOK, _ACCOK = int(Flags.CAL), int(Flags.MAGOK), int(Flags.ACCOK)
_SAT, _FLASHERR = int(Flags.SAT), int(Flags.FLASHERR)


def _round1(x: float) -> float:
    return float(fmt_fixed(x, 1))


def _round4(x: float) -> float:
    return float(fmt_fixed(x, 4))


@dataclass(frozen=True, slots=True)
class FrameTruth:
    """What was true when a frame was sampled (kept for tests and benchmarks).

    ``t`` is the device clock (the caller's ``now`` scale); ``motion_t`` the time
    given to the motion script; ``R`` the attitude; ``*_body_*`` the ideal vectors.
    """

    t: float
    motion_t: float
    R: FloatArray
    mag_body_G: FloatArray
    acc_body_g: FloatArray
    frame: AttitudeFrame


@dataclass
class _MagCal:
    """On-board min/max state (None = axis not tracked yet)."""

    samples: int = 0
    xy: list[int] | None = None  # [xmin, xmax, ymin, ymax]
    z: list[int] | None = None  # [zmin, zmax]

    def progress(self) -> CalProgressFrame:
        xy = self.xy or [0, 0, 0, 0]
        z = self.z or [0, 0]
        return CalProgressFrame(self.samples, xy[0], xy[1], xy[2], xy[3], z[0], z[1])

    def spans(self) -> tuple[int, int, int]:
        xy = self.xy or [0, 0, 0, 0]
        z = self.z or [0, 0]
        return (xy[1] - xy[0], xy[3] - xy[2], z[1] - z[0])


class Firmware:
    """The simulated device. Not thread-safe: one caller at a time (a lock in the server).

    ``power_on_at``: the instant the device boots; by default the first ``now``
    it is given. The motion script's time is ``now - power_on_at`` and keeps
    running across RESETs and power cycles (the world does not reboot).
    """

    def __init__(
        self,
        sensor: SensorModel,
        motion: Motion,
        flash: Flash,
        rng: np.random.Generator,
        *,
        version: tuple[str, str, str] = ("2.1.0", "B3", "GMR-000417"),
        power_on_at: float | None = None,
        truth_log: int = 2048,
    ) -> None:
        self.sensor = sensor
        self.motion = motion
        self.flash = flash
        self._rng = rng
        # independent streams: command timing and garbage must not shift the noise sequence
        self._rng_timing, self._rng_garbage = rng.spawn(2)
        self.version = VersionFrame(*version)
        self.truth: deque[FrameTruth] = deque(maxlen=truth_log)
        self.decoder = GmrDecoder(direction="device")
        self._events: list[_Event] = []
        self._order = itertools.count()
        self._out = bytearray()
        self._now = -math.inf
        self._epoch: float | None = power_on_at
        self._powered = True
        self._running = False  # booted and listening (False during RESET silence)
        self._gen = 0  # boot generation: events of an older boot are void
        self.rate_hz = DEFAULT_RATE_HZ
        self.seq = 0  #: seq of the next frame
        self._frame_gen = 0
        self._anchor = 0.0
        self._k = 0
        self._busy_until = -math.inf
        self._last_cmd_t = -math.inf
        self._magcal: _MagCal | None = None
        self._cal_gen = 0
        self._acccal: list[tuple[int, int, int]] | None = None
        self._acc_gen = 0
        # hard-iron changes still to come: (motion time, delta gauss), in time order
        self._iron_steps: list[tuple[float, FloatArray]] = []
        #: Faults out of the datasheet (tests, ``bench fuzz``): every command handled this
        #: much later than the datasheet allows; no ``$PGMRA`` at all while False.
        self.answer_delay_s = 0.0
        self.streaming = True
        self.frames_sent = 0
        self.frames_skipped = 0  #: ticks lost to flash writes
        self.commands_dropped = 0  #: lines that arrived while the device was not listening
        if power_on_at is not None:
            self._boot(power_on_at)

    # ------------------------------------------------------------------ public API

    @property
    def motion_epoch(self) -> float | None:
        """The caller's time at which the motion script's t = 0 (first power-on)."""
        return self._epoch

    @property
    def calibrating(self) -> bool:
        """MAGCAL mode (flag CAL)."""
        return self._magcal is not None

    @property
    def running(self) -> bool:
        """Powered, booted and listening."""
        return self._powered and self._running

    def receive(self, data: bytes, now: float) -> None:
        """Host bytes arriving at ``now``. Lines with a bad checksum get no answer."""
        self._advance(now)
        if not self.running:
            # a rebooting or unpowered MCU hears nothing; a partial line is lost
            self.commands_dropped += data.count(b"\n")
            self.decoder.reset()
            return
        for frame in self.decoder.feed(data):
            if not isinstance(frame, CommandFrame):  # the device decoder yields only these
                continue
            latency = float(self._rng_timing.uniform(*CMD_LATENCY_S)) + self.answer_delay_s
            t = max(self._now + latency, self._last_cmd_t)
            self._last_cmd_t = t
            self._schedule(t, *self._bind_command(frame, self._gen))

    def poll(self, now: float) -> bytes:
        """Everything the device has sent up to ``now`` (and not returned before)."""
        self._advance(now)
        out = bytes(self._out)
        self._out.clear()
        return out

    def change_hard_iron(self, delta_G: npt.ArrayLike, at_s: float | None = None) -> None:
        """From motion time ``at_s`` on (default: the next frame) the unit carries ``delta_G``
        more hard iron (sensor axes, gauss): a bracket bolted on while it runs.

        The change belongs to the world, not to the device: it survives RESETs and power
        cycles, and frames sampled from then on (and their truth) show it.
        """
        d = np.asarray(delta_G, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(d)):
            raise ValueError(f"delta_G must be finite, got {delta_G!r}")
        at = -math.inf if at_s is None else float(at_s)
        if math.isnan(at):
            raise ValueError("at_s must be a time, got NaN")
        self._iron_steps.append((at, d))
        self._iron_steps.sort(key=lambda step: step[0])

    def inject_garbage(self, n: int) -> None:
        """``n`` random bytes appear in the output at once (line noise, a glitch)."""
        n = int(n)
        if n > 0:
            self._out += self._rng_garbage.integers(0, 256, size=n, dtype=np.uint8).tobytes()

    def next_event_at(self) -> float | None:
        """When the device next does something (for a server to sleep until then)."""
        while self._events and not self._live(self._events[0]):
            heapq.heappop(self._events)
        return self._events[0][0] if self._events else None

    def power_off(self, now: float) -> None:
        """Cut the power: output stops, RAM state (rate, CAL, pending answers) is lost."""
        self._advance(now)
        self._powered = False
        self._running = False
        self._gen += 1
        self._events.clear()

    def power_on(self, now: float) -> None:
        """Power back: flash re-read (FLASHERR forgotten), ``$PGMRV``, 10 Hz from seq 0."""
        if self._now > now:
            now = self._now
        self._now = now
        if self._epoch is None:
            self._epoch = now
        self.flash.power_cycle()
        self._powered = True
        self._boot(now)

    def flags(self, saturated: bool = False) -> Flags:
        """The flag byte a frame would carry now."""
        return Flags(self._flag_bits(saturated))

    def _flag_bits(self, saturated: bool) -> int:
        # The bits as a plain int: a frame built from ints takes AttitudeFrame's fast path
        # (every frame; the enum's operators cost more than the frame's other fields).
        page = self.flash.page
        return (
            (_CAL if self._magcal is not None else 0)
            | (_MAGOK if page.magok else 0)
            | (_ACCOK if page.accok else 0)
            | (_SAT if saturated else 0)
            | (_FLASHERR if self.flash.flasherr else 0)
        )

    # ------------------------------------------------------------------ event machinery

    def _schedule(
        self, t: float, fn: Callable[[float], None], live: Callable[[], bool] | None = None
    ) -> None:
        """Run ``fn(t)`` at ``t`` unless ``live()`` says by then that it is stale."""
        heapq.heappush(self._events, (t, next(self._order), fn, live))

    @staticmethod
    def _live(ev: _Event) -> bool:
        return ev[3] is None or ev[3]()

    def _advance(self, now: float) -> None:
        if self._epoch is None:
            self._epoch = now
            self._boot(now)
        if now < self._now:  # the caller's clock never runs backwards for us
            now = self._now
        self._now = now
        while self._events and self._events[0][0] <= now:
            ev = heapq.heappop(self._events)
            if self._live(ev):
                ev[2](ev[0])

    def _emit(self, frame: GmrFrame) -> None:
        self._out += encode(frame)

    # ------------------------------------------------------------------ boot and frames

    def _boot(self, t: float) -> None:
        self._gen += 1
        self._events.clear()
        self._running = True
        self.decoder.reset()
        self.rate_hz = DEFAULT_RATE_HZ
        self.seq = 0
        self._magcal = None
        self._acccal = None
        self._busy_until = -math.inf
        self._last_cmd_t = -math.inf
        self._emit(self.version)
        self._restart_frames(t)

    def _restart_frames(self, t: float) -> None:
        self._frame_gen += 1
        self._anchor = t
        self._k = 1
        self._schedule_frame()

    def _schedule_frame(self) -> None:
        gen, fgen = self._gen, self._frame_gen
        self._schedule(
            self._anchor + self._k / self.rate_hz,
            self._frame_tick,
            lambda: gen == self._gen and fgen == self._frame_gen,
        )

    def _frame_tick(self, t: float) -> None:
        self._k += 1
        horizon = self._now - MAX_BACKLOG_S
        if t < horizon:
            # the caller slept: this tick and those before the horizon are lost on the wire
            later = math.ceil((horizon - (self._anchor + self._k / self.rate_hz)) * self.rate_hz)
            skip = max(0, later)
            self._k += skip
            self.seq = (self.seq + 1 + skip) % SEQ_MODULO
            self._schedule_frame()
            return
        if t < self._busy_until:
            self.frames_skipped += 1  # flash write: not sampled, not sent, no seq step
        elif not self.streaming:
            pass  # the fault: its sampling stopped, its main loop still answers
        else:
            self._send_frame(t)
        self._schedule_frame()

    def _sample(self, t: float) -> tuple[FloatArray, Any]:
        mt = t - (self._epoch if self._epoch is not None else t)
        while self._iron_steps and self._iron_steps[0][0] <= mt:
            self.sensor = self.sensor.with_hard_iron_change(self._iron_steps.pop(0)[1])
        R = self.motion.attitude(mt)
        return R, self.sensor.sample(R, self._rng, linear_acc_of(self.motion, mt))

    def _send_frame(self, t: float) -> None:
        R, s = self._sample(t)
        # One conversion of each row to Python ints (six numpy scalars taken apart before).
        m0, m1, m2 = s.mag_counts[0].tolist()
        a0, a1, a2 = s.acc_counts[0].tolist()
        m, a = (m0, m1, m2), (a0, a1, a2)
        if self._magcal is not None:
            self._track(m, a)
        hdg, pitch, roll = onboard_attitude(m, a, self.flash.page)
        hdg = _round1(hdg)
        frame = AttitudeFrame(
            self.seq,
            0.0 if hdg >= 360.0 else hdg,
            _round1(pitch),
            _round1(roll),
            *m,
            *a,
            self._flag_bits(bool(s.saturated[0])),
        )
        self._emit(frame)
        self.frames_sent += 1
        mt = t - (self._epoch if self._epoch is not None else t)
        self.truth.append(FrameTruth(t, mt, R, s.mag_body_G[0], s.acc_body_g[0], frame))
        self.seq = (self.seq + 1) % SEQ_MODULO

    # ------------------------------------------------------------------ commands

    def _bind_command(
        self, cmd: CommandFrame, gen: int
    ) -> tuple[Callable[[float], None], Callable[[], bool]]:
        def run(t: float) -> None:
            if t < self._busy_until:  # the UART holds it until the flash write ends
                self._schedule(self._busy_until, run, live)
                return
            self._handle(cmd, t)

        def live() -> bool:
            return gen == self._gen

        return run, live

    def _handle(self, cmd: CommandFrame, t: float) -> None:
        reason = cmd.error()
        if reason is not None:
            self._emit(cmd.ack_err(reason))
            return
        key = cmd.key
        if key == "VER":
            self._emit(self.version)
        elif key == "RATE":
            self.rate_hz = cmd.rate_hz()
            self._emit(AckFrame.rate_ok(self.rate_hz))
            self._restart_frames(t)
        elif key == "PAR,GET":
            self._emit(self.flash.page.params())
        elif key == "PAR,SET":
            self._par_set(cmd, t)
        elif key == "MAGCAL,START":
            self._magcal_start(cmd, t)
        elif key == "MAGCAL,END":
            self._magcal_end(cmd, t)
        elif key == "MAGCAL,ABORT":
            if self._magcal is None:
                self._emit(cmd.ack_err(AckReason.STATE))
            else:
                self._magcal = None
                self._emit(cmd.ack_ok())
        elif key == "ACCCAL":
            self._acccal_start(cmd, t)
        elif key == "RESET":
            self._emit(cmd.ack_ok())
            self._running = False
            self._gen += 1
            self._events.clear()
            gen = self._gen
            self._schedule(t + RESET_SILENCE_S, self._boot, lambda: gen == self._gen)
        else:  # pragma: no cover - cmd.error() already answered every other word
            self._emit(cmd.ack_err(AckReason.UNKNOWN))

    def _write_flash(self, page: FlashPage, t: float, answer: GmrFrame, command: str) -> None:
        """Program the flash; the answer (or ERR,FLASH) leaves when the write is done."""
        done = t + float(self._rng_timing.uniform(*FLASH_WRITE_S))
        self._busy_until = done
        ok = self.flash.write(page)
        reply: GmrFrame = answer if ok else AckFrame.failure(command, AckReason.FLASH)
        gen = self._gen
        self._schedule(done, lambda _t: self._emit(reply), lambda: gen == self._gen)

    def _par_set(self, cmd: CommandFrame, t: float) -> None:
        if self._magcal is not None or self._acccal is not None:
            self._emit(cmd.ack_err(AckReason.STATE))
            return
        p = cmd.params()
        stored = ParamsFrame(
            *(_round1(v) for v in (p.xoff, p.yoff, p.zoff)),
            *(_round4(v) for v in (p.kx, p.ky, p.kz)),
            *(_round1(v) for v in (p.gxoff, p.gyoff, p.gzoff)),
        )
        v = stored.values()
        f = FACTORY.params().values()
        page = self.flash.page.with_params(stored, magok=v[:6] != f[:6], accok=v[6:] != f[6:])
        self._write_flash(page, t, cmd.ack_ok(), "PAR")

    def _magcal_start(self, cmd: CommandFrame, t: float) -> None:
        if self._magcal is not None or self._acccal is not None:
            self._emit(cmd.ack_err(AckReason.STATE))
            return
        self._magcal = _MagCal()
        self._cal_gen += 1
        self._emit(cmd.ack_ok())
        self._schedule_progress(t + PROGRESS_PERIOD_S)

    def _schedule_progress(self, t: float) -> None:
        gen, cgen = self._gen, self._cal_gen

        def tick(tt: float) -> None:
            if self._magcal is not None:
                self._emit(self._magcal.progress())
                self._schedule_progress(tt + PROGRESS_PERIOD_S)

        def live() -> bool:
            return gen == self._gen and cgen == self._cal_gen and self._magcal is not None

        self._schedule(t, tick, live)

    def _track(self, m: tuple[int, int, int], a: tuple[int, int, int]) -> None:
        cal = self._magcal
        assert cal is not None
        g = gravity_counts(a, self.flash.page)
        gn = float(np.linalg.norm(g))
        if gn == 0.0:
            return
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(g[2]) / gn))))
        level = tilt < MAGCAL_LEVEL_TILT_DEG
        side = abs(float(g[2])) < MAGCAL_SIDE_GZ_G * ACC_COUNTS_PER_G
        if level:
            mx, my = m[0], m[1]
            if cal.xy is None:
                cal.xy = [mx, mx, my, my]
            else:
                xy = cal.xy
                xy[0], xy[1] = min(xy[0], mx), max(xy[1], mx)
                xy[2], xy[3] = min(xy[2], my), max(xy[3], my)
        if side:
            mz = m[2]
            cal.z = [mz, mz] if cal.z is None else [min(cal.z[0], mz), max(cal.z[1], mz)]
        if level or side:
            cal.samples += 1

    def _magcal_end(self, cmd: CommandFrame, t: float) -> None:
        cal = self._magcal
        if cal is None:
            self._emit(cmd.ack_err(AckReason.STATE))
            return
        self._magcal = None  # END leaves calibration mode whatever happens next
        sx, sy, sz = cal.spans()
        if min(sx, sy, sz) < MAGCAL_MIN_SPAN or cal.xy is None or cal.z is None:
            self._emit(cmd.ack_err(AckReason.RANGE))
            return
        xy, z = cal.xy, cal.z
        offs = (
            _round1((xy[1] + xy[0]) / 2),
            _round1((xy[3] + xy[2]) / 2),
            _round1((z[1] + z[0]) / 2),
        )
        gains = (1.0, _round4(sx / sy), _round4(sx / sz))
        page = self.flash.page
        params = ParamsFrame(*offs, *gains, page.gxoff, page.gyoff, page.gzoff)
        self._write_flash(
            page.with_params(params, magok=True), t, AckFrame.magcal_ok(*offs, *gains), "MAGCAL"
        )

    def _acccal_start(self, cmd: CommandFrame, t: float) -> None:
        if self._magcal is not None or self._acccal is not None:
            self._emit(cmd.ack_err(AckReason.STATE))
            return
        self._acccal = []
        self._acc_gen += 1
        gen, agen = self._gen, self._acc_gen

        def live() -> bool:
            return gen == self._gen and agen == self._acc_gen

        for k in range(1, ACCCAL_SAMPLES + 1):
            self._schedule(t + k / ACCCAL_RATE_HZ, self._acccal_sample, live)
        self._schedule(t + ACCCAL_SAMPLES / ACCCAL_RATE_HZ, self._acccal_done, live)

    def _acccal_sample(self, t: float) -> None:
        if self._acccal is None:
            return
        _R, s = self._sample(t)
        a = s.acc_counts[0]
        self._acccal.append((int(a[0]), int(a[1]), int(a[2])))

    def _acccal_done(self, t: float) -> None:
        samples, self._acccal = self._acccal, None
        if not samples:  # pragma: no cover - the sample events always precede this one
            return
        arr = np.asarray(samples, dtype=np.float64)
        if float(np.max(arr.max(axis=0) - arr.min(axis=0))) > ACCCAL_MAX_SPREAD:
            self._emit(AckFrame.failure("ACCCAL", AckReason.MOTION))
            return
        gx, gy, gz = (_round1(float(v)) for v in arr.mean(axis=0))
        page = self.flash.page
        params = ParamsFrame(page.xoff, page.yoff, page.zoff, page.kx, page.ky, page.kz, gx, gy, gz)
        self._write_flash(
            page.with_params(params, accok=True), t, AckFrame.acccal_ok(gx, gy, gz), "ACCCAL"
        )


def make_firmware(
    seed: int = 1,
    *,
    location: tuple[float, float, float] | None = None,
    motion: Motion | None = None,
    flash_path: str | None = None,
    ideal: bool = False,
    power_on_at: float | None = None,
    hard_iron_change: tuple[npt.ArrayLike, float] | None = None,
) -> Firmware:
    """A ready simulated compass: unit errors drawn from ``seed`` at ``location``.

    Defaults: PX4 SITL's Zurich site, slow level turns at 10 deg/s, flash in
    memory. ``ideal`` gives a perfect, noise-free unit. ``hard_iron_change``
    ``(delta_G, at_s)``: the unit's hard iron changes by ``delta_G`` (sensor axes,
    gauss) ``at_s`` seconds after power-up (:meth:`Firmware.change_hard_iron`).
    """
    errors = UnitErrors.ideal() if ideal else UnitErrors.draw(np.random.default_rng(seed))
    sensor = SensorModel.at_location(errors, location or DEFAULT_LOCATION)
    fw = Firmware(
        sensor,
        motion if motion is not None else YawTurns(10.0),
        Flash(flash_path),
        np.random.default_rng([seed, 1]),
        power_on_at=power_on_at,
    )
    if hard_iron_change is not None:
        fw.change_hard_iron(*hard_iron_change)
    return fw


__all__ = [
    "Firmware",
    "FrameTruth",
    "gravity_counts",
    "make_firmware",
    "onboard_attitude",
]
