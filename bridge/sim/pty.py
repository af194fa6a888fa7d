"""Serve the simulated compass on a real pseudo-terminal, at a stable symlinked path.

:class:`PtyCompass` opens a pty pair, puts the slave in raw mode, points
``link_path`` at the slave (``/dev/pts/N``) with an atomic symlink swap, and runs
the firmware in real time from one thread: ``select()`` on the master (and a
wake-up pipe) with a timeout up to the firmware's next event, then
``receive()``/``poll()`` with the monotonic clock. A host opens ``link_path``
with pyserial exactly as it would open ``/dev/ttyUSB0``.

Bytes the host does not read pile up in the pty; when it is full, further
output is dropped (a UART does not wait for its listener), so lines can arrive
cut -- as on a real line. pyserial flushes the input buffer on open, so a host
that connects late does not see stale frames.

:meth:`PtyCompass.unplug` emulates pulling the USB cable: the pty is closed
(the host's reads fail), the symlink removed, and after ``down_s`` a new pty
(a different ``/dev/pts/N``) appears at the same path. ``power_cycle`` chooses
whether the device lost power meanwhile (reboot: ``$PGMRV``, seq 0, 10 Hz) or
stayed powered like a self-powered unit behind a USB-serial adapter (state and
seq carry on; what it sent while unplugged is lost).
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import select
import signal
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

from bridge.sim.drive import Drive
from bridge.sim.firmware import Firmware, make_firmware
from bridge.sim.motion import Motion, Still, Tumble, YawTurns, with_shake
from bridge.types import Clock

_MAX_WAIT_S = 0.05  # upper bound of a select(): stop/unplug requests are seen this fast anyway
_JOIN_TIMEOUT_S = 5.0


def _replace_symlink(target: str, link: Path) -> None:
    """Point ``link`` at ``target`` atomically (a reader never sees it missing)."""
    tmp = link.with_name(f".{link.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)
    os.symlink(target, tmp)
    try:
        os.replace(tmp, link)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


class _Pty:
    """One pty pair: master (ours, non-blocking) and slave (kept open so it stays alive)."""

    def __init__(self, avoid: str | None = None) -> None:
        spares: list[tuple[int, int]] = []
        try:
            # The kernel reuses the lowest free pts number; a "new" device must differ
            # from the one just unplugged, so hold a clash open while taking another.
            for _ in range(4):
                master, slave = os.openpty()
                if os.ttyname(slave) != avoid:
                    break
                spares.append((master, slave))
            else:  # pragma: no cover - four clashes in a row cannot happen
                raise OSError(errno.EBUSY, "could not get a fresh pty")
        finally:
            for fds in spares:
                for fd in fds:
                    os.close(fd)
        self.master, self.slave = master, slave
        self.name = os.ttyname(slave)
        try:
            tty.setraw(slave)
            os.set_blocking(master, False)
        except OSError:
            self.close()
            raise

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self.master = self.slave = -1


class PtyCompass:
    """The firmware on a pty at ``link_path``; a context manager (``start``/``stop``).

    ``power_cycle_on_unplug``: default for :meth:`unplug` (False: the unit stays
    powered and keeps its state). ``clock`` is the firmware's time base.
    """

    def __init__(
        self,
        firmware: Firmware,
        link_path: str | os.PathLike[str],
        *,
        power_cycle_on_unplug: bool = False,
        clock: Clock = time.monotonic,
    ) -> None:
        self.firmware = firmware
        self.link_path = Path(link_path)
        self.power_cycle_on_unplug = power_cycle_on_unplug
        self._clock = clock
        self._lock = threading.RLock()  # firmware + pty state
        self._pty: _Pty | None = None
        self._replug_at: float | None = None
        self._replug_power = False
        self._last_name: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._plugged = threading.Condition(self._lock)
        self.bytes_out = 0
        self.bytes_in = 0
        self.bytes_dropped = 0  #: output lost because nobody read the pty
        self.error: BaseException | None = None  #: what ended the serve thread, if anything

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> PtyCompass:
        """Create the pty and the symlink, and start serving. Returns self."""
        with self._lock:
            if self._thread is not None:
                raise RuntimeError("already started")
            self._wake_r, self._wake_w = os.pipe()
            os.set_blocking(self._wake_r, False)
            os.set_blocking(self._wake_w, False)
            try:
                self._plug(avoid=None)
            except BaseException:
                self._close_pipe()
                raise
            self._stop.clear()
            self._thread = threading.Thread(target=self._serve, name="pty-compass", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close every fd, remove the symlink (idempotent)."""
        self._stop.set()
        self._wake()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(_JOIN_TIMEOUT_S)
        with self._lock:
            self._unplug_now()
            self._replug_at = None
            self._close_pipe()
            self._thread = None

    def __enter__(self) -> PtyCompass:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ controls

    @property
    def device(self) -> str | None:
        """The current slave device (``/dev/pts/N``), or None while unplugged."""
        with self._lock:
            return None if self._pty is None else self._pty.name

    @property
    def running(self) -> bool:
        """The serve thread is alive."""
        t = self._thread
        return t is not None and t.is_alive()

    def unplug(self, down_s: float, *, power_cycle: bool | None = None) -> None:
        """Pull the cable now; a new pty appears at ``link_path`` after ``down_s``.

        Returns once the old pty is gone (the host's next read fails). ``power_cycle``
        overrides ``power_cycle_on_unplug`` for this unplug.
        """
        if not (math.isfinite(down_s) and down_s >= 0.0):
            raise ValueError(f"down_s must be finite and >= 0, got {down_s!r}")
        with self._lock:
            if self._thread is None:
                raise RuntimeError("not started")
            self._unplug_now()
            pc = self.power_cycle_on_unplug if power_cycle is None else power_cycle
            now = self._clock()
            if pc:
                self.firmware.power_off(now)
            self._replug_power = pc
            self._replug_at = now + down_s
        self._wake()

    def wait_plugged(self, timeout: float) -> str | None:
        """Wait until a pty is served at ``link_path``; its device name, or None on timeout."""
        deadline = time.monotonic() + timeout
        with self._plugged:
            while self._pty is None:
                left = deadline - time.monotonic()
                if left <= 0.0 or not self.running:
                    return None
                self._plugged.wait(left)
            return self._pty.name

    def garbage(self, n: int) -> None:
        """``n`` random bytes of line noise in the output."""
        with self._lock:
            self.firmware.inject_garbage(n)
        self._wake()

    # ------------------------------------------------------------------ internals

    def _plug(self, avoid: str | None) -> None:
        p = _Pty(avoid)
        try:
            _replace_symlink(p.name, self.link_path)
        except BaseException:
            p.close()
            raise
        self._pty = p
        self._plugged.notify_all()

    def _unplug_now(self) -> None:
        p, self._pty = self._pty, None
        if p is None:
            return
        # remove the link first: a host that retries must not find the dying device
        with contextlib.suppress(FileNotFoundError):
            if self.link_path.is_symlink() and os.readlink(self.link_path) == p.name:
                os.unlink(self.link_path)
        self._last_name = p.name
        p.close()

    def _close_pipe(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = -1

    def _wake(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            if self._wake_w >= 0:
                os.write(self._wake_w, b"x")

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                self._step()
        except BaseException as e:  # keep the reason; stop() still cleans up
            self.error = e

    def _step(self) -> None:
        with self._lock:
            now = self._clock()
            if self._pty is None and self._replug_at is not None and now >= self._replug_at:
                self._replug_at = None
                self._plug(avoid=self._last_name)
                if self._replug_power:
                    self.firmware.power_on(now)
            fds = [self._wake_r] + ([self._pty.master] if self._pty is not None else [])
            nxt = self.firmware.next_event_at()
            wait = _MAX_WAIT_S if nxt is None else nxt - now
            if self._replug_at is not None:
                wait = min(wait, self._replug_at - now)
            wait = min(max(wait, 0.0), _MAX_WAIT_S)
        try:
            readable, _, _ = select.select(fds, [], [], wait)
        except (OSError, ValueError):
            return  # an fd was closed under us by unplug()/stop(): go round again
        with self._lock:
            if self._wake_r in readable:
                with contextlib.suppress(OSError):
                    os.read(self._wake_r, 4096)
            p = self._pty
            now = self._clock()
            if p is not None and p.master in readable:
                data = b""
                with contextlib.suppress(BlockingIOError, InterruptedError):
                    data = os.read(p.master, 4096)
                if data:
                    self.bytes_in += len(data)
                    self.firmware.receive(data, now)
            out = self.firmware.poll(now)
            if out and self._pty is not None:
                self._write(self._pty, out)
            elif out:
                self.bytes_dropped += len(out)  # unplugged: sent into thin air

    def _write(self, p: _Pty, data: bytes) -> None:
        try:
            n = os.write(p.master, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as e:
            if e.errno != errno.EIO:
                raise
            n = 0
        self.bytes_out += n
        self.bytes_dropped += len(data) - n


# ---------------------------------------------------------------------- CLI entry

MOTIONS: dict[str, Callable[[int], Motion]] = {
    "turns": lambda seed: YawTurns(10.0),
    "still": lambda seed: Still(),
    "tumble": lambda seed: Tumble(seed),
    "drive": lambda seed: Drive(seed),
}


def make_motion(name: str, seed: int, shake_g: float = 0.0) -> Motion:
    """The motion script ``name`` (one of :data:`MOTIONS`), held by a hand shaking ``shake_g``.

    ``shake_g`` is the linear acceleration, g RMS per axis (smooth, 0.4-2.5 Hz,
    seeded like the unit; :class:`~bridge.sim.motion.HandShake`); 0 = steady.
    """
    if name not in MOTIONS:
        raise ValueError(f"motion must be one of {sorted(MOTIONS)}, got {name!r}")
    return with_shake(MOTIONS[name](seed), shake_g, seed)


def run_simulator(
    link_path: str,
    seed: int = 1,
    location: tuple[float, float, float] | None = None,
    *,
    motion: Motion | str = "turns",
    flash_path: str | None = None,
    ideal: bool = False,
    shake_g: float = 0.0,
    stop: threading.Event | None = None,
    on_ready: Callable[[PtyCompass], None] | None = None,
    unplug_s: float = 1.0,
    garbage_bytes: int = 256,
    hard_iron_change: tuple[tuple[float, float, float], float] | None = None,
) -> int:
    """Serve a simulated compass at ``link_path`` until SIGINT/SIGTERM (or ``stop`` is set).

    ``seed`` draws the unit's errors; ``location`` is ``(lat_deg, lon_deg, alt_m)``
    (default: PX4 SITL's Zurich); ``motion`` a script or one of :data:`MOTIONS`;
    ``flash_path`` keeps the unit's calibration across runs; ``shake_g`` shakes a
    named motion like a hand (g RMS per axis); ``hard_iron_change`` ``(delta_G,
    at_s)`` changes the unit's hard iron while it runs
    (:meth:`~bridge.sim.firmware.Firmware.change_hard_iron`). Returns 0.

    Fault injection from outside, for integrators and the daemon's fault tests:
    SIGUSR1 pulls the cable (the pty goes away; a new one appears at
    ``link_path`` after ``unplug_s``), SIGUSR2 sends ``garbage_bytes`` of line noise.
    """
    if isinstance(motion, str):
        motion = make_motion(motion, seed, shake_g)
    fw = make_firmware(
        seed,
        location=location,
        motion=motion,
        flash_path=flash_path,
        ideal=ideal,
        hard_iron_change=hard_iron_change,
    )
    stop_event = stop if stop is not None else threading.Event()

    unplug_requested = threading.Event()
    garbage_requested = threading.Event()
    wake = threading.Event()

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        # Only set flags here: the work (which blocks) happens in the loop below.
        if signum == signal.SIGUSR1:
            unplug_requested.set()
        elif signum == signal.SIGUSR2:
            garbage_requested.set()
        else:
            stop_event.set()
        wake.set()

    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):
            previous[sig] = signal.signal(sig, _on_signal)
    try:
        with PtyCompass(fw, link_path) as sim:
            if on_ready is not None:
                on_ready(sim)
            # short waits keep the main thread responsive to signals
            while not stop_event.is_set():
                wake.wait(0.2)
                wake.clear()
                if not sim.running:
                    raise RuntimeError(f"simulator thread died: {sim.error!r}")
                if garbage_requested.is_set():
                    garbage_requested.clear()
                    sim.garbage(garbage_bytes)
                if unplug_requested.is_set():
                    unplug_requested.clear()
                    sim.unplug(unplug_s)
    finally:
        for signum, handler in previous.items():
            # None means "installed outside Python": the default is the closest we can restore
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
    return 0
