"""What every output receives: the sample, the status, and the output contract.

These are the application's ports towards its adapters: MAVLink, Zenoh, the
console and the service's status line all receive the same
:class:`CompassSample` through :meth:`Output.publish`, and read the same
:class:`DaemonStatus`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Literal, Protocol

from bridge.core.attitude import AttitudeSolution
from bridge.protocol.device import LinkCounters, LinkState
from bridge.types import HeadingReference

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------
# What outputs receive
# ---------------------------------------------------------------------------


# Not frozen, on purpose (as AttitudeSolution): built for every frame, and a frozen
# dataclass's __init__ costs 2-3x plain slot stores when run cold at 100 Hz. Read-only by
# contract: the same instance goes to every output, in several threads.
@dataclass(slots=True)
class CompassSample:
    """One frame's result, as every output receives it (read-only by contract).

    ``source`` says who computed the heading: ``"host"`` (the attitude engine
    on the raw GMR vectors, calibrated on the host) or ``"device"`` (a
    heading-only compass's own heading, forwarded). ``heading_deg`` is the
    published heading, [0, 360) clockwise from the north ``heading_reference``
    names; the magnetic and true headings are given separately where known
    (true needs a declination). Angles in degrees; ``attitude`` carries the
    full host solution (radians, quaternion, calibrated vectors, quality
    flags) when ``source == "host"``. ``t`` is the monotonic time the frame
    arrived.
    """

    t: float
    source: Literal["host", "device"]
    heading_deg: float
    heading_reference: HeadingReference
    heading_magnetic_deg: float | None
    heading_true_deg: float | None
    declination_deg: float | None
    pitch_deg: float | None
    roll_deg: float | None
    seq: int | None = None
    device_heading_deg: float | None = None  #: the GMR's on-board heading, for comparison
    saturated: bool = False  #: a raw channel sat at an ADC rail: the vectors are clipped
    attitude: AttitudeSolution | None = None
    #: The frame's raw ADC counts (mx, my, mz, ax, ay, az), for MAVLink RAW_IMU; GMR frames only.
    raw_counts: tuple[int, int, int, int, int, int] | None = None

    @property
    def tilt_source(self) -> str | None:
        """Where roll and pitch came from: ``"accelerometer"``, ``"autopilot"`` or
        ``"magnetometer"`` (host samples); ``"device"`` for a heading-only compass's own."""
        a = self.attitude
        if a is not None:
            return a.tilt_source
        return "device" if self.pitch_deg is not None else None

    @property
    def heading_sigma_deg(self) -> float | None:
        """The heading error (1 sigma, degrees) the tilt's uncertainty leaves; None when
        the bridge does not know it (no tilt estimate, a heading-only compass)."""
        a = self.attitude
        return a.heading_sigma_deg if a is not None else None

    @classmethod
    def from_solution(
        cls,
        a: AttitudeSolution,
        t: float,
        seq: int | None = None,
        device_heading_deg: float | None = None,
        saturated: bool = False,
        raw_counts: tuple[int, int, int, int, int, int] | None = None,
    ) -> CompassSample:
        """The host sample of the attitude engine's solution ``a`` (pitch and roll in degrees)."""
        # Positional, in the fields' order (t, source, heading_deg, heading_reference,
        # heading_magnetic_deg, heading_true_deg, declination_deg, pitch_deg, roll_deg,
        # seq, device_heading_deg, saturated, attitude, raw_counts): every frame, and
        # fourteen keywords cost a dataclass's __init__ more than its own stores.
        return cls(
            t,
            "host",
            a.heading_deg,
            a.heading_reference,
            a.heading_magnetic_deg,
            a.heading_true_deg,
            a.declination_deg,
            math.degrees(a.pitch),
            math.degrees(a.roll),
            seq,
            device_heading_deg,
            saturated,
            a,
            raw_counts,
        )


class Output(Protocol):
    """A consumer of samples (console, MAVLink, Zenoh ...).

    ``publish`` is called from the pipeline -- the link's reader thread -- for every
    sample and MUST NOT block or raise: do the I/O elsewhere (see :class:`LatestSampleWorker`).
    """

    @property
    def name(self) -> str:
        """Short name for logs."""
        ...

    def start(self) -> None:
        """Start the output's own thread(s)."""
        ...

    def publish(self, sample: CompassSample) -> None:
        """Hand over one sample; never blocks."""
        ...

    @property
    def due_at(self) -> float:
        """The earliest monotonic time a sample handed over could go out at once.

        ``-inf``: any sample may (every frame must be handled as it arrives);
        ``+inf``: none will (the output paces itself or keeps only the latest).
        The compass link reads the port in bursts until shortly before the
        earliest of these (:meth:`bridge.app.pipeline.Pipeline.due_at_time`).
        """
        ...

    def close(self, timeout: float) -> None:
        """Stop within about ``timeout`` seconds."""
        ...


@dataclass(frozen=True, slots=True)
class DaemonStatus:
    """A snapshot for status displays."""

    port: str
    state: LinkState
    counters: LinkCounters
    samples: int
    pipeline_errors: int
    calibration_source: str
    #: why params.json was last refused ("": it was not; retried by the parameter store)
    parameters_error: str = ""


# ---------------------------------------------------------------------------
# Output helpers
# ---------------------------------------------------------------------------


class LatestSampleWorker:
    """Base for outputs: ``publish`` stores the latest sample; a thread emits it.

    Two pacings:

    * ``wake_on_publish=True`` (network outputs): :meth:`emit` runs for each
      new sample, at most once per ``interval`` seconds (a rate limit);
    * ``wake_on_publish=False`` (the console): :meth:`emit` runs every
      ``interval`` seconds with the latest sample, new or not (``None``
      before the first).

    Either way a slow consumer sees the newest data and skips the rest
    (counted, approximately, in ``skipped``) instead of stalling the pipeline.
    Errors in ``emit`` are counted and logged once, never fatal.
    """

    def __init__(self, name: str, interval: float, *, wake_on_publish: bool = True) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be positive, got {interval}")
        self._name = name
        self.interval = interval
        self._wake_on_publish = wake_on_publish
        self._latest: CompassSample | None = None
        self._fresh = False
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.skipped = 0
        self.errors = 0

    @property
    def name(self) -> str:
        """Short name for logs."""
        return self._name

    def start(self) -> None:
        """Start the worker thread."""
        if self._thread is not None:
            raise RuntimeError(f"{self._name} already started")
        self._thread = threading.Thread(target=self._run, name=f"output-{self._name}", daemon=True)
        self._thread.start()

    @property
    def due_at(self) -> float:
        """``-inf`` for an output woken by every sample; ``+inf`` for a clock-paced one
        (it shows the latest sample on its own clock)."""
        return -math.inf if self._wake_on_publish else math.inf

    def publish(self, sample: CompassSample) -> None:
        """Keep ``sample`` as the latest; O(1), no lock (one reference store, then a flag)."""
        if self._fresh:
            self.skipped += 1
        self._latest = sample
        self._fresh = True
        if self._wake_on_publish:
            self._wake.set()

    def _next(self, due: float) -> bool:
        """Wait for the next emit; False when stopping."""
        if self._wake_on_publish:
            while not self._fresh:
                self._wake.wait(0.5)  # bounded, so a stop is seen even without samples
                self._wake.clear()
                if self._stop.is_set():
                    return False
        return not self._stop.wait(max(0.0, due - time.monotonic()))

    def _run(self) -> None:
        # A clock-paced output waits one interval first: at start there is nothing to show yet.
        due = time.monotonic() + (0.0 if self._wake_on_publish else self.interval)
        while self._next(due):
            due = time.monotonic() + self.interval
            sample, self._fresh = self._latest, False
            try:
                self.emit(sample)
            except Exception:
                self.errors += 1
                if self.errors == 1:
                    log.exception("output %s failed (further failures are only counted)", self.name)
        try:
            self.finish()
        except Exception:
            log.exception("output %s failed to finish", self.name)

    def emit(self, sample: CompassSample | None) -> None:
        """Do the output's I/O for the latest sample (in the worker thread)."""
        raise NotImplementedError

    def finish(self) -> None:
        """Called once in the worker thread after the stop (flush, close)."""

    def close(self, timeout: float) -> None:
        """Stop the worker within ``timeout`` seconds."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("output %s did not stop within %.1f s", self.name, timeout)
