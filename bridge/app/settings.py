"""The one writer of the attitude engine's settings.

Calibration, mounting, declination and expected field, quality limits and the
published heading reference can be changed by several parts of the bridge --
a parameter set over MAVLink, an accepted calibration, the autopilot's
position, a configuration reload. They all go through :class:`EngineSettings`,
which applies the change to the :class:`~bridge.core.attitude.AttitudeEngine`
(one reference swap each: the pipeline never sees half a change) and tells its
subscribers what changed and who changed it, in order. Nobody polls.

Guards (:meth:`EngineSettings.add_guard`) may refuse a change that would step
the heading -- a calibration, a mounting, a declination moved by at least
:data:`REFERENCE_STEP_DEG` -- with :class:`~bridge.events.ChangeRefusedError`; the
MAVLink adapter refuses them while an armed ArduPilot takes its yaw from the
bridge (docs/mavlink.md, "Heading changes and the autopilot").

The declination rule (ArduPilot's COMPASS_AUTODEC / COMPASS_DEC) lives here
too: the published declination is the World Magnetic Model's at the known
position unless a fixed one is set; the expected field strength and dip always
come from the model.
"""

from __future__ import annotations

import logging
import threading
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from bridge.core.attitude import AttitudeEngine, FieldReference
from bridge.core.calibration import Calibration
from bridge.core.mounting import Mounting
from bridge.core.quality import QualityLimits
from bridge.core.wmm import EarthField, earth_field
from bridge.events import ChangeRefusedError, Subscribers
from bridge.types import HeadingReference

log = logging.getLogger(__name__)

Aspect = Literal["calibration", "mounting", "reference", "limits", "heading_reference"]
#: A declination change smaller than this (a moving vehicle's position updates) is not a
#: heading step: guards are not asked about it.
REFERENCE_STEP_DEG = 0.5


@dataclass(frozen=True, slots=True)
class SettingsChange:
    """One applied change: which ``aspect`` and who made it (``source``)."""

    aspect: Aspect
    source: str


Listener = Callable[[SettingsChange], None]
#: ``(aspect, source) -> reason`` ("" lets the change through; see :meth:`EngineSettings.add_guard`).
Guard = Callable[[Aspect, str], str]


class EngineSettings:
    """Owns the engine's settings; every change goes through here (see the module docstring).

    ``field`` is the Earth field at the configured location (``[location]``),
    None when unknown; :meth:`set_position` replaces it (the autopilot's
    position in the companion role).
    """

    def __init__(self, engine: AttitudeEngine, *, field: EarthField | None = None) -> None:
        self.engine = engine
        self._lock = threading.RLock()
        self._emit_lock = threading.Lock()
        self._listeners: Subscribers[SettingsChange] = Subscribers()
        self._guards: tuple[Guard, ...] = ()  # replaced, never changed in place
        self._field = field
        self._declination_deg: float | None = None  # a fixed declination (COMPASS_AUTODEC=0)
        self._pending: list[SettingsChange] = []
        #: The engine generations whose configuration stepped the heading (a calibration, a
        #: mounting, a declination moved by REFERENCE_STEP_DEG or more), the oldest dropped.
        self._steps: list[int] = []
        self._steps_dropped = 0
        self._apply_reference("start")

    # -- reading -------------------------------------------------------------------

    @property
    def calibration(self) -> Calibration:
        """The calibration in use."""
        return self.engine.calibration

    @property
    def mounting(self) -> Mounting:
        """The mounting in use."""
        return self.engine.mounting

    @property
    def limits(self) -> QualityLimits:
        """The quality limits in use."""
        return self.engine.limits

    @property
    def reference(self) -> FieldReference | None:
        """The declination and expected field in use (None: unknown)."""
        return self.engine.reference

    @property
    def heading_reference(self) -> HeadingReference:
        """The published heading's north ("magnetic" or "true")."""
        return self.engine.heading_reference

    @property
    def field(self) -> EarthField | None:
        """The World Magnetic Model's field at the known position (None: no position)."""
        return self._field

    @property
    def wmm_declination_deg(self) -> float | None:
        """The model's declination at the known position (None: no position)."""
        f = self._field
        return f.declination_deg if f is not None else None

    def heading_steps(self, generation: int | None = None) -> int:
        """How many heading steps the engine's configurations up to ``generation`` hold
        (None: the one in use): a calibration, a mounting, a declination moved by
        :data:`REFERENCE_STEP_DEG` or more.

        PX4's ``reset_counter`` is this count for the sample's own solution
        (:attr:`~bridge.core.attitude.AttitudeSolution.generation`). It is recorded under
        the lock that swaps the engine's configuration and read under it here, so a
        solution of a configuration that stepped the heading is never counted without
        its step, nor one of the configuration before with it.
        """
        with self._lock:
            steps = self._steps
            n = len(steps) if generation is None else bisect_right(steps, generation)
            return self._steps_dropped + n

    def _stepped(self) -> None:
        """Record that the configuration just built stepped the heading (under the lock)."""
        self._steps.append(self.engine.generation)
        if len(self._steps) > 256:  # a sample is never that many steps behind
            del self._steps[:128]
            self._steps_dropped += 128

    # -- subscribing -----------------------------------------------------------------

    def subscribe(self, fn: Listener) -> Callable[[], None]:
        """Call ``fn(change)`` after every applied change; returns the unsubscribe function.

        Listeners run in a thread that made a change, one change at a time, in
        order, and must be quick; they may read the settings and change them
        (that change is delivered after the current one).
        """
        return self._listeners.add(fn)

    def add_guard(self, fn: Guard) -> Callable[[], None]:
        """Ask ``fn(aspect, source)`` before every change that steps the heading (a
        calibration, a mounting, a declination step of :data:`REFERENCE_STEP_DEG` or
        more); a non-empty answer refuses it (:class:`~bridge.events.ChangeRefusedError`
        with that text). Returns the remover. A guard must be quick and must not change
        the settings itself."""
        with self._lock:
            self._guards = (*self._guards, fn)

        def remove() -> None:
            with self._lock:
                self._guards = tuple(g for g in self._guards if g is not fn)

        return remove

    def _guard(self, aspect: Aspect, source: str) -> None:
        for fn in self._guards:
            reason = fn(aspect, source)
            if reason:
                raise ChangeRefusedError(reason)

    def _changed(self, aspect: Aspect, source: str) -> None:
        """Deliver a change to every listener, one change at a time and in order.

        A change made while another is being delivered (by a listener, or by another
        thread) is queued and delivered by the thread already delivering.
        """
        with self._lock:
            self._pending.append(SettingsChange(aspect, source))
        while self._emit_lock.acquire(blocking=False):
            try:
                while True:
                    with self._lock:
                        if not self._pending:
                            break
                        change = self._pending.pop(0)
                    for fn in self._listeners:
                        try:
                            fn(change)
                        except Exception:  # a broken listener must not undo the change
                            log.exception("settings listener failed on %s", change)
            finally:
                self._emit_lock.release()
            with self._lock:
                if not self._pending:  # nothing slipped in after the last look
                    return

    # -- writing -------------------------------------------------------------------

    def update_calibration(self, calibration: Calibration, source: str = "calibration") -> None:
        """Use ``calibration`` from now on (:class:`~bridge.events.ChangeRefusedError` if a guard
        says no)."""
        with self._lock:
            if calibration != self.engine.calibration:
                self._guard("calibration", source)
            self.engine.update_calibration(calibration)
            self._stepped()
        self._changed("calibration", source)

    def set_mounting(self, mounting: Mounting, source: str) -> None:
        """Use ``mounting`` (AHRS_ORIENTATION) from now on (guarded)."""
        with self._lock:
            if mounting == self.engine.mounting:
                return
            self._guard("mounting", source)
            self.engine.update_mounting(mounting)
            self._stepped()
        self._changed("mounting", source)

    def set_limits(self, limits: QualityLimits, source: str) -> None:
        """Use ``limits`` for the disturbance / acceleration flags from now on."""
        with self._lock:
            if limits == self.engine.limits:
                return
            self.engine.update_limits(limits)
        self._changed("limits", source)

    def set_heading_reference(self, reference: HeadingReference, source: str) -> None:
        """Publish the magnetic or the true heading from now on."""
        with self._lock:
            if reference == self.engine.heading_reference:
                return
            self.engine.set_heading_reference(reference)
        self._changed("heading_reference", source)

    def set_declination(self, declination_deg: float | None, source: str) -> None:
        """A fixed declination (COMPASS_AUTODEC = 0), or None for the model's (guarded)."""
        with self._lock:
            before = self._declination_deg
            self._declination_deg = declination_deg
            try:
                changed = self._apply_reference(source)
            except ChangeRefusedError:
                self._declination_deg = before
                raise
        if changed:
            self._changed("reference", source)

    def set_field(self, field: EarthField | None, source: str) -> None:
        """A new position's Earth field (a reload's ``[location]``), None when unknown
        (guarded)."""
        with self._lock:
            before = self._field
            self._field = field
            try:
                changed = self._apply_reference(source)
            except ChangeRefusedError:
                self._field = before
                raise
        if changed:
            self._changed("reference", source)

    def set_position(
        self, latitude_deg: float, longitude_deg: float, altitude_m: float, source: str
    ) -> EarthField:
        """The field at a new position (the autopilot's); ``ValueError`` on a bad position."""
        field = earth_field(latitude_deg, longitude_deg, altitude_m)
        self.set_field(field, source)
        return field

    def _apply_reference(self, source: str) -> bool:
        f = self._field
        if self._declination_deg is None:
            ref = FieldReference.from_earth_field(f) if f is not None else None
        else:
            ref = FieldReference(
                declination_deg=self._declination_deg,
                total_G=f.total_G if f is not None else None,
                dip_deg=f.inclination_deg if f is not None else None,
                source=source,
            )
        if ref == self.engine.reference:
            return False
        old = self.engine.reference
        old_dec = old.declination_deg if old is not None else None
        new_dec = ref.declination_deg if ref is not None else None
        step = old_dec != new_dec and (
            old_dec is None
            or new_dec is None
            or abs((new_dec - old_dec + 180.0) % 360.0 - 180.0) >= REFERENCE_STEP_DEG
        )
        if step:
            self._guard("reference", source)
        self.engine.update_reference(ref)
        if step:
            self._stepped()
        return True
