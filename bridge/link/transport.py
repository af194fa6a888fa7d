"""Byte transports for the compass link: a real serial port, the simulator, a replay.

Modelled on python-can's bus interfaces: one small :class:`Transport`
protocol with interchangeable implementations, picked from a port string by
:func:`open_transport`:

* a device path (``/dev/ttyUSB0``, a pty symlink)  -> :class:`SerialTransport`
* ``"sim"``            -> :class:`SimTransport`, the in-process simulated compass
* ``"replay:PATH"``    -> :class:`ReplayTransport`, a recording from :mod:`bridge.link.record`

All three hand the link the same thing -- raw bytes -- so the decoder is
exercised identically whichever is used. Transports are thin: no decoding,
no retries; losing the port is reported as an exception and the link decides
what to do about it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import select
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Protocol, runtime_checkable

import serial

from bridge.link.record import Chunk, RecordingReader
from bridge.types import Clock

_POLLNVAL = select.POLLNVAL  # a module constant: read() tests it for every frame

log = logging.getLogger(__name__)

Sleep = Callable[[float], None]


class TransportError(OSError):
    """The port cannot be opened, has gone away, or failed a read/write.

    A subclass of OSError so that one ``except OSError`` covers it together
    with whatever the OS raises directly.
    """


class EndOfRecording(TransportError):  # noqa: N818 - named by the link interface
    """A replay has played its whole recording; it will not produce more bytes.

    The link treats it as the device being absent for good; the CLI uses it to
    exit when replaying.
    """


@runtime_checkable
class Transport(Protocol):
    """A byte pipe to a compass (python-can style bus interface).

    ``open()`` may be called again after ``close()`` (the link reopens a port
    that went away). ``read()`` returns ``b""`` on timeout and raises
    :class:`TransportError` (or another OSError) when the port is gone --
    never an endless stream of empty reads. ``interactive`` is False when
    writes go nowhere (a replay), so the link skips its connect handshake.
    """

    @property
    def name(self) -> str:
        """The port as the user named it (for logs)."""
        ...

    @property
    def interactive(self) -> bool:
        """Whether bytes written reach a device that answers."""
        ...

    def open(self) -> None:
        """Open (or reopen) the port; raises TransportError when it cannot."""
        ...

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Up to ``max_bytes`` bytes, waiting at most ``timeout`` s for the first one."""
        ...

    def write(self, data: bytes) -> None:
        """Send ``data``; raises TransportError when the port is gone."""
        ...

    def close(self) -> None:
        """Close the port (idempotent)."""
        ...


class SerialTransport:
    """A real serial port through pyserial: 8N1, no flow control, exclusive.

    On Linux a vanished port (USB unplug, pty master closed) either fails a
    read with EIO or polls readable and reads nothing. Both come out of
    :meth:`read` as :class:`TransportError`, so the link sees the loss at
    once instead of spinning on empty reads.
    """

    #: A write that cannot drain in this long means the port is wedged.
    WRITE_TIMEOUT_S = 0.5

    def __init__(self, port: str, baud: int) -> None:
        if not port:
            raise ValueError("serial port path is empty")
        if baud <= 0:
            raise ValueError(f"baud must be positive, got {baud}")
        self.port = port
        self.baud = baud
        self._ser: serial.Serial | None = None
        self._fd = -1
        self._poller: select.poll | None = None

    @property
    def name(self) -> str:
        """The device path."""
        return self.port

    @property
    def interactive(self) -> bool:
        """A real device answers."""
        return True

    def open(self) -> None:
        """Open the port exclusively (a second reader would steal bytes)."""
        self.close()
        try:
            self._ser = serial.Serial(
                self.port,
                self.baud,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                xonxoff=False,
                rtscts=False,
                dsrdtr=False,
                timeout=0.05,
                write_timeout=self.WRITE_TIMEOUT_S,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as e:
            raise TransportError(f"cannot open {self.port}: {e}") from e
        # pyserial opened the fd O_NONBLOCK: read() polls it directly (see read()).
        self._fd = self._ser.fd
        poller = select.poll()
        poller.register(self._fd, select.POLLIN | select.POLLPRI)
        self._poller = poller

    def _port(self) -> serial.Serial:
        if self._ser is None:
            raise TransportError(f"{self.port} is not open")
        return self._ser

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Whatever has arrived (up to ``max_bytes``), waiting up to ``timeout`` for a byte.

        The hot path bypasses pyserial's ``read()`` (a select() on two fds, a
        Timeout object and a per-chunk loop on every call) and its
        ``in_waiting`` ioctl: one poll() on the port's non-blocking fd, then one
        os.read() of everything that has arrived -- one wake and two system
        calls per burst. pyserial still opens, configures, writes and closes.
        """
        poller = self._poller
        if poller is None or self._fd < 0:
            raise TransportError(f"{self.port} is not open")
        try:
            events = poller.poll(math.ceil(timeout * 1000.0) if timeout > 0 else 0)
            if not events:
                return b""
            if events[0][1] & _POLLNVAL:
                raise TransportError(f"{self.port}: port descriptor is no longer valid")
            data = os.read(self._fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""  # readiness that another reader took (exclusive makes it rare): no data
        except OSError as e:
            # EIO: the pty master closed or the USB adapter went away.
            raise TransportError(f"{self.port}: read failed: {e}") from e
        if not data:
            # A vanished port (hang-up) polls readable forever and reads nothing: without
            # this the link would spin on empty reads instead of reopening.
            raise TransportError(
                f"{self.port}: device reports readiness to read but returned no data "
                "(device disconnected?)"
            )
        return data

    def write(self, data: bytes) -> None:
        """Write all of ``data`` (bounded by :attr:`WRITE_TIMEOUT_S`)."""
        ser = self._port()
        try:
            ser.write(data)
        except (serial.SerialException, OSError) as e:
            raise TransportError(f"{self.port}: {e}") from e

    def close(self) -> None:
        """Close the port (idempotent; errors from a vanished port are ignored)."""
        ser, self._ser = self._ser, None
        self._fd, self._poller = -1, None
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                ser.close()


class FirmwareLike(Protocol):
    """What :class:`SimTransport` needs of ``bridge.sim.firmware.Firmware``."""

    def receive(self, data: bytes, now: float) -> None:
        """Host bytes in at time ``now``."""
        ...

    def poll(self, now: float) -> bytes:
        """Everything the device sends up to ``now``."""
        ...

    def next_event_at(self) -> float | None:
        """When the device next does something (None: nothing scheduled)."""
        ...


class SimTransport:
    """The in-process simulated compass (``device.port = "sim"``).

    :meth:`read` polls the sans-I/O firmware with ``clock()`` so frames come
    at real-time pace, sleeping until the firmware's next event (or until a
    :meth:`write` from another thread wakes it: a command's answer is due
    within milliseconds, sooner than the next frame at a low rate).
    :meth:`write` feeds the firmware. The firmware keeps running while the
    transport is closed and reopened, like a USB device that stays powered.
    ``sleep`` replaces the real-time wait when ``clock`` is a simulated clock.
    """

    #: Longest single wait: bounds the damage if the firmware's schedule is ever empty.
    MAX_WAIT_S = 0.05

    def __init__(
        self,
        firmware: FirmwareLike,
        clock: Clock = time.monotonic,
        *,
        sleep: Sleep | None = None,
        name: str = "sim",
    ) -> None:
        self._fw = firmware
        self._clock = clock
        self._sleep = sleep
        self._name = name
        self._buf = bytearray()
        self._open = False
        self._attached_before = False
        # The reader polls and a command thread writes: the firmware is not thread-safe.
        self._cond = threading.Condition()

    @property
    def name(self) -> str:
        """``"sim"``."""
        return self._name

    @property
    def interactive(self) -> bool:
        """The simulated firmware answers commands."""
        return True

    @property
    def firmware(self) -> FirmwareLike:
        """The simulated device behind this transport."""
        return self._fw

    def open(self) -> None:
        """Attach to the firmware (bytes it sent while detached are lost, as on a real line)."""
        with self._cond:
            if self._attached_before:
                self._fw.poll(self._clock())
            # else: the first poll powers the device up, and its $PGMRV is for the host to see.
            self._attached_before = True
            self._buf.clear()
            self._open = True

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Poll the firmware until it has sent something or ``timeout`` passes."""
        deadline = self._clock() + timeout
        with self._cond:
            while True:
                if not self._open:
                    raise TransportError(f"{self._name} is not open")
                now = self._clock()
                self._buf += self._fw.poll(now)
                if self._buf:
                    out = bytes(self._buf[:max_bytes])
                    del self._buf[:max_bytes]
                    return out
                wait = min(deadline - now, self.MAX_WAIT_S)
                if wait <= 0:
                    return b""
                due = self._fw.next_event_at()
                if due is not None:
                    wait = min(wait, max(due - now, 0.0))
                if self._sleep is not None:
                    self._sleep(wait)
                elif wait > 0:
                    self._cond.wait(wait)  # released while waiting: write() can get in

    def write(self, data: bytes) -> None:
        """Feed host bytes to the firmware (and wake a waiting read)."""
        with self._cond:
            if not self._open:
                raise TransportError(f"{self._name} is not open")
            self._fw.receive(data, self._clock())
            self._cond.notify_all()

    def close(self) -> None:
        """Detach (the firmware keeps running)."""
        with self._cond:
            self._open = False
            self._buf.clear()
            self._cond.notify_all()


class ReplayTransport:
    """Plays a recording back (``device.port = "replay:PATH"``).

    With ``realtime`` the recorded byte chunks come out at their recorded
    pace (relative to the first chunk); otherwise as fast as they are read.
    Writes are accepted and discarded (counted in :attr:`writes_discarded`).
    When the recording is exhausted, :meth:`read` -- and any later
    :meth:`open` -- raise :class:`EndOfRecording`. Closing and reopening in
    the middle resumes where it stopped, the schedule shifted so nothing is
    skipped. A recording cut by power loss plays up to the cut.
    """

    def __init__(
        self,
        path: str,
        realtime: bool = True,
        *,
        clock: Clock = time.monotonic,
        sleep: Sleep = time.sleep,
    ) -> None:
        self.path = path
        self.realtime = realtime
        self._clock = clock
        self._sleep = sleep
        self._reader: RecordingReader | None = None
        self._chunks: Iterator[Chunk] | None = None
        self._next: Chunk | None = None  # the chunk not yet (fully) delivered
        self._next_off = 0  # bytes of it already delivered
        self._anchor = 0.0  # clock time at which a chunk with t == 0 is due
        self._ended = False
        self._open = False
        self.writes_discarded = 0
        self.bytes_discarded = 0
        self.bytes_played = 0

    @property
    def name(self) -> str:
        """``replay:PATH``."""
        return f"replay:{self.path}"

    @property
    def interactive(self) -> bool:
        """A recording does not answer."""
        return False

    @property
    def ended(self) -> bool:
        """The whole recording has been played."""
        return self._ended

    def open(self) -> None:
        """Start (or resume) playing; raises EndOfRecording once it has all been played."""
        if self._ended:
            raise EndOfRecording(f"{self.name}: recording already played")
        if self._reader is None:
            try:
                self._reader = RecordingReader(self.path)
            except (OSError, ValueError) as e:
                # A missing or foreign file is a configuration error that retrying won't fix.
                raise EndOfRecording(f"{self.name}: {e}") from e
            self._chunks = self._reader.chunks()
            self._next = next(self._chunks, None)
            if self._next is None:
                self._finish()
                raise EndOfRecording(f"{self.name}: recording holds no data")
        assert self._next is not None
        self._anchor = self._clock() - self._next.t
        self._open = True

    def _finish(self) -> None:
        self._ended = True
        self._open = False
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        self._chunks = None
        self._next = None

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """The next recorded bytes, waiting (in realtime mode) until they are due."""
        if self._ended:
            raise EndOfRecording(f"{self.name}: end of recording")
        if not self._open:
            raise TransportError(f"{self.name} is not open")
        assert self._next is not None and self._chunks is not None
        if self.realtime:
            wait = self._anchor + self._next.t - self._clock()
            if wait > 0:
                self._sleep(min(wait, timeout))
                if self._anchor + self._next.t > self._clock():
                    return b""
        out = bytearray()
        now = self._clock()
        while self._next is not None and len(out) < max_bytes:
            if self.realtime and out and self._anchor + self._next.t > now:
                break
            data = self._next.data
            take = data[self._next_off : self._next_off + max_bytes - len(out)]
            out += take
            self._next_off += len(take)
            if self._next_off >= len(data):
                self._next = next(self._chunks, None)
                self._next_off = 0
        self.bytes_played += len(out)
        if self._next is None:
            # Keep the last bytes deliverable now; the next read reports the end.
            reader = self._reader
            self._chunks = None
            if reader is not None:
                reader.close()
                self._reader = None
            self._ended = True
        return bytes(out)

    def write(self, data: bytes) -> None:
        """Accept and discard (a recording cannot answer)."""
        self.writes_discarded += 1
        self.bytes_discarded += len(data)

    def close(self) -> None:
        """Pause playback (idempotent)."""
        self._open = False


def _build_sim_firmware(**options: Any) -> FirmwareLike:
    """The simulated compass the ``"sim"`` port stands for (bridge.sim.firmware.make_firmware)."""
    # Imported here: only the "sim" port needs the simulator (and numpy's RNG set-up).
    from bridge.sim.firmware import make_firmware

    return make_firmware(**options)


def open_transport(port: str, baud: int, **options: Any) -> Transport:
    """Make (not open) the transport a port string names.

    ``"sim"`` -> :class:`SimTransport` (``options`` go to
    :func:`bridge.sim.firmware.make_firmware`: ``seed``, ``location``,
    ``motion``, ``flash_path``, ``ideal``); ``"replay:PATH"`` -> :class:`ReplayTransport` (option
    ``realtime``, default True); anything else is a serial device path.
    Options that do not apply to the port's kind are ignored, so a caller can
    always pass its ``[sim]`` settings.
    """
    if not isinstance(port, str) or not port.strip():
        raise ValueError("device port is empty")
    if port == "sim":
        return SimTransport(_build_sim_firmware(**options))
    if port.startswith("replay:"):
        path = port[len("replay:") :]
        if not path:
            raise ValueError("replay: needs a file path, e.g. replay:/var/tmp/run.cbrec")
        # The simulator's options (e.g. the configured [sim] seed) do not apply to a replay.
        return ReplayTransport(path, realtime=bool(options.get("realtime", True)))
    return SerialTransport(port, baud)
