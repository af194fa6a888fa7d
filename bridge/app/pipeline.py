"""The per-frame pipeline: one received frame to one :class:`CompassSample`, to every output.

It runs in the compass link's reader thread (:meth:`Pipeline.on_frame` is the
link's frame callback): a frame wakes one thread, not two -- a hand-off to a
second thread costs more CPU at 100 Hz than the whole attitude solution. So
everything it calls must be quick and must never block: the calibrator's
``feed`` (O(1) while idle), the attitude engine, and each output's
``publish`` (an output encodes and hands off; its I/O happens elsewhere).

Per frame:

* ``$PGMRA``: :meth:`AttitudeEngine.solve_counts
  <bridge.core.attitude.AttitudeEngine.solve_counts>` (nominal transfer ->
  calibration -> tilt-compensated heading, declination; the tilt from the
  engine's tilt policy, :mod:`bridge.app.tilt`, given the frame's sampling instant
  from its ``seq``: :class:`~bridge.core.aligned.FrameClock`), plus the
  disturbance events (start / end, at most one per
  :data:`DISTURBANCE_EVENT_MIN_S` of the frames' sampling instants, none while a
  calibration tumbles); the drift monitor's sample, at that instant too;
* a heading-only sentence (NMEA / OceanServer): forwarded, with the
  declination from the World Magnetic Model (or the sentence's own variation);
* anything else (``$PGMRV/P/K/C``): the link's business, no sample.

A frame that fails is counted (``pipeline_errors``) and logged once; the
bridge goes on. :attr:`Pipeline.alive_at` is what the service watchdog
watches: a frame stuck in the pipeline stops that clock.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence

from bridge.app.sample import CompassSample, Output
from bridge.core.aligned import FrameClock
from bridge.core.attitude import AttitudeEngine, AttitudeSolution
from bridge.core.geometry import wrap_degrees_360
from bridge.events import Event, EventBus, Severity
from bridge.protocol.device import LinkState, Received
from bridge.protocol.gmr import AttitudeFrame
from bridge.protocol.heading import HeadingFrame
from bridge.types import HeadingReference

log = logging.getLogger(__name__)


#: Disturbance start/end events: at most one per this many seconds (no flapping on the links).
DISTURBANCE_EVENT_MIN_S = 5.0


class Pipeline:
    """Frames in, samples out to every output (see the module docstring).

    ``feed`` is the calibrator's per-frame hook (each frame with its instant: an attitude
    frame's sampling instant from :attr:`frame_clock`, another frame's arrival) and
    ``calibrating`` tells whether a calibration runs (disturbance events are muted meanwhile);
    ``observe`` sees every host solution with its frame's sampling instant and saturation
    (the drift monitor's hook: one comparison per frame). ``clock``: the clock the compass's
    frames are timed on when it is not the link's (a simulation's clock running faster
    than the link's real time): the frame clock takes a frame's arrival on it, so the
    sampling instants the engine, the calibrator and the drift monitor get are the
    simulated compass's.
    """

    def __init__(
        self,
        engine: AttitudeEngine,
        events: EventBus,
        *,
        feed: Callable[[object, float], None],
        calibrating: Callable[[], bool],
        observe: Callable[[AttitudeSolution, float, bool], None] | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.engine = engine
        self._clock = clock
        self.events = events
        self._feed = feed
        self._calibrating = calibrating
        self._observe = observe
        #: The outputs, in publish order; replaced whole (one reference store) on reload.
        self.outputs: tuple[Output, ...] = ()
        self.samples = 0
        self.errors = 0
        self._frame_started_at: float | None = None  # set while a frame is in the pipeline
        self._disturbed = False  # disturbance state last reported as an event
        self._disturbed_at = -math.inf  # when it was reported
        #: A change of the disturbance state went unreported because a calibration ran.
        self.muted_while_calibrating = False
        self._link_lost = False  # link.lost emitted, link.restored not yet
        #: The frames' sampling instants (from seq, not arrival) for the tilt policy.
        self.frame_clock = FrameClock()

    @property
    def alive_at(self) -> float:
        """Monotonic time up to which the pipeline is known not to be stuck (the watchdog's).

        Now while it waits for a frame; the time the current frame went in while
        one is being processed, so a frame that never comes out stops the clock.
        """
        started = self._frame_started_at
        return time.monotonic() if started is None else started

    def due_at_time(self) -> float:
        """The earliest time an output could send a sample at once (``min`` of the
        outputs' :attr:`~bridge.app.sample.Output.due_at`; ``+inf`` with none): frames
        before it may be read in bursts, the first after it must be handled as it comes."""
        return min((out.due_at for out in self.outputs), default=math.inf)

    def set_outputs(self, outputs: Sequence[Output]) -> None:
        """The outputs every sample goes to, in order (one reference store)."""
        self.outputs = tuple(outputs)

    # -- the per-frame path --------------------------------------------------------

    def on_frame(self, item: Received) -> None:
        """The per-frame path, run in the link's reader thread for every frame."""
        self._frame_started_at = item.t  # when the reader got it: the same monotonic clock
        try:
            sample = self.process(item.frame, item.t, item.read_at)
            if sample is not None:
                self.samples += 1
                for out in self.outputs:
                    try:
                        out.publish(sample)
                    except Exception:
                        self.errors += 1
                        log.exception("output %s: publish raised", out.name)
        except Exception:
            # A bad frame must not stop the bridge: count it, say so once.
            self.errors += 1
            if self.errors == 1:
                log.exception("pipeline: frame %r failed (further failures counted)", item)
        finally:
            self._frame_started_at = None

    def process(
        self, frame: object, t: float, read_at: float | None = None
    ) -> CompassSample | None:
        """One received frame to a sample (None for frames that carry no heading): ``t`` the
        time the outputs pace it by, ``read_at`` when it was read if that differs
        (:class:`~bridge.protocol.device.Received`)."""
        # When the reader got it, on the compass's clock (frames read in one burst share it).
        arrival = t if read_at is None else read_at
        if self._clock is not None:
            arrival = self._clock()
        if isinstance(frame, AttitudeFrame):
            tf = self.frame_clock.at(frame.seq, arrival)  # when it was sampled
            self._feed(frame, tf)  # never raises; cheap when no calibration runs
            return self._from_gmr(frame, t, tf)
        self._feed(frame, arrival)
        if isinstance(frame, HeadingFrame):
            return self._from_heading(frame, t)
        return None  # $PGMRV/P/K/C: handled by the link

    def _from_gmr(self, f: AttitudeFrame, t: float, tf: float) -> CompassSample:
        a = self.engine.solve_counts(f.mx, f.my, f.mz, f.ax, f.ay, f.az, tf)
        if a.disturbed is not self._disturbed:
            # (its hold-off on the compass's clock too: the same frame ends it however read)
            self._disturbance_changed(a.disturbed, a, tf)
        saturated = f.sat_flag
        if self._observe is not None:
            # tf too: the monitor keeps a sample per 0.1 s and judges the heading rate in its
            # samples' own time (a burst's arrivals would put nine frames in one instant)
            self._observe(a, tf, saturated)
        # The sample keeps the arrival: an output takes its slots by it, and the link stamps
        # a burst's held frames so that none passes for the due one (serial_link._held).
        # (positionally: seq, device_heading_deg, saturated, raw_counts)
        return CompassSample.from_solution(
            a, t, f.seq, f.heading, saturated, (f.mx, f.my, f.mz, f.ax, f.ay, f.az)
        )

    def _from_heading(self, f: HeadingFrame, t: float) -> CompassSample | None:
        if f.heading_deg is None:
            return None  # $PTNTHPR in alarm: the device itself has no heading
        # Declination: the model's (or a fixed one) when known, else the sentence's own
        # variation (HDG); a heading-only compass is never re-calibrated here.
        ref = self.engine.reference
        decl = ref.declination_deg if ref is not None else None
        if decl is None:
            decl = f.variation_deg
        mag: float | None
        true: float | None
        if f.reference == "magnetic":
            mag = f.heading_deg
            true = wrap_degrees_360(f.heading_deg + decl) if decl is not None else None
        else:
            true = f.heading_deg
            mag = wrap_degrees_360(f.heading_deg - decl) if decl is not None else None
        # Publish the configured reference when it is known, else the one the sentence gave.
        published_ref: HeadingReference = "magnetic"
        published = mag
        if (self.engine.heading_reference == "true" and true is not None) or mag is None:
            published_ref, published = "true", true
        assert published is not None  # one of the two is the sentence's own heading
        return CompassSample(
            t=t,
            source="device",
            heading_deg=published,
            heading_reference=published_ref,
            heading_magnetic_deg=mag,
            heading_true_deg=true,
            declination_deg=decl,
            pitch_deg=f.pitch_deg,
            roll_deg=f.roll_deg,
        )

    # -- operator events -----------------------------------------------------------

    def _disturbance_changed(self, disturbed: bool, a: AttitudeSolution, t: float) -> None:
        """Disturbance start / end as operator events (on transitions only).

        At most one event per :data:`DISTURBANCE_EVENT_MIN_S`: a badly calibrated unit
        turning near the threshold would flap; a change inside the hold-off is reported
        when it ends, if it still holds then.
        """
        if self._calibrating():
            # An uncalibrated unit tumbling for its calibration is "disturbed" half the
            # time: that is expected, not news. The state is re-judged once it ends.
            self.muted_while_calibrating = True
            return
        if t - self._disturbed_at < DISTURBANCE_EVENT_MIN_S:
            return
        self._disturbed, self._disturbed_at = disturbed, t
        data = {"field_mG": round(1000.0 * a.field_strength_G, 1), "dip_deg": round(a.dip_deg, 1)}
        if disturbed:
            text, sev = "Magnetic disturbance: heading unreliable", Severity.WARNING
        else:
            text, sev = "Magnetic disturbance cleared", Severity.NOTICE
        kind = "disturbance.start" if disturbed else "disturbance.end"
        self.events.emit(Event(kind, text, sev, data))

    def on_link_state(self, old: LinkState, new: LinkState) -> None:
        """Link lost / restored as operator events (called in the link's reader thread)."""
        down = (LinkState.STALE, LinkState.ABSENT)
        if old is LinkState.STREAMING and new in down:
            self._link_lost = True
            self.frame_clock.reset()
            why = "stale" if new is LinkState.STALE else "port gone"
            self.events.emit(
                Event(
                    "link.lost", f"Compass link lost ({why})", Severity.ERROR, {"state": new.value}
                )
            )
        elif new is LinkState.STREAMING and self._link_lost:  # via OPENING after a reopen
            self._link_lost = False
            self.events.emit(Event("link.restored", "Compass link restored", Severity.NOTICE))
