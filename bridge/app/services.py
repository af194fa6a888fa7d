"""What every adapter receives from the application: one services object.

MAVLink and Zenoh (and the status tools) get the same :class:`BridgeServices`
when they are built; none of them looks for another adapter or into the
daemon. Reading is free; every change goes through a named owner: the
parameter store (:class:`~bridge.app.params.ParamStore`), the engine settings'
writer (:class:`~bridge.app.settings.EngineSettings`), the calibration
controller's commands.

The MAVLink mirror (Zenoh republishing what MAVLink sends) goes through
:class:`MessageTap`: the MAVLink adapter publishes each message it sends, the
Zenoh adapter subscribes, and neither knows the other.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bridge.app.calibration.controller import CalibrationController
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import ParamStore
from bridge.app.sample import DaemonStatus
from bridge.app.settings import EngineSettings
from bridge.app.tilt import TiltSources
from bridge.core.calibration import corrects_iron
from bridge.documents import DocumentStore
from bridge.events import EventBus, Subscribers
from bridge.protocol.device import DevicePort, LinkState

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SentMessage:
    """A MAVLink message as the bridge sent it: our ids and the message (a pymavlink
    message object; read-only by contract -- the same object went to every link)."""

    system_id: int
    component_id: int
    message: Any


class MessageTap:
    """Fan-out of the MAVLink messages the bridge sends, to whoever mirrors them.

    :meth:`publish` runs in the MAVLink sender's thread: subscribers must be
    quick and must not raise (a failure is counted, never passed on).
    """

    def __init__(self) -> None:
        self._subscribers: Subscribers[SentMessage] = Subscribers()
        self.errors = 0

    @property
    def active(self) -> bool:
        """Someone subscribes (the sender skips building messages otherwise)."""
        return bool(self._subscribers)

    def subscribe(self, fn: Callable[[SentMessage], None]) -> Callable[[], None]:
        """Register ``fn``; returns the function that removes it."""
        return self._subscribers.add(fn)

    def publish(self, message: SentMessage) -> None:
        """Hand ``message`` to every subscriber."""
        for fn in self._subscribers:
            try:
                fn(message)
            except Exception:
                self.errors += 1
                if self.errors == 1:
                    log.exception("message tap subscriber failed (further failures counted)")


@dataclass(frozen=True, slots=True)
class BridgeServices:
    """The running bridge as an adapter sees it (see the module docstring).

    * ``status()`` -- link state and counters, samples, calibration source, and why
      params.json was refused;
    * ``settings`` -- calibration, mounting, declination and field in use;
    * ``params`` -- the parameter table (read, set);
    * ``calibrator`` -- calibration commands and state;
    * ``calibrations`` -- the stored calibration and its report;
    * ``events`` -- operator events (subscribe; adapters may emit their own);
    * ``device`` -- the compass (version, parameters, state; commands);
    * ``mavlink_tap`` -- the MAVLink messages sent, for mirrors;
    * ``drift`` -- the calibration's drift monitor (status, undo of learned offsets);
    * ``tilt`` -- where each frame's tilt comes from: the companion role's MAVLink
      adapter hands it the autopilot's attitude; status reads it;
    * ``link_states`` -- every change of the link's state (``add`` a quick callback; it
      runs in the link's reader thread): a status that goes out when the state changes
      follows it rather than reading ``status()`` on a clock;
    * ``documents`` -- the state directory, for what an adapter must keep across a
      restart (MAVLink's signing replay table); None without one.
    """

    status: Callable[[], DaemonStatus]
    settings: EngineSettings
    params: ParamStore
    calibrator: CalibrationController
    calibrations: CalibrationStore
    events: EventBus
    device: DevicePort
    mavlink_tap: MessageTap
    drift: DriftMonitor
    tilt: TiltSources
    link_states: Subscribers[LinkState]
    documents: DocumentStore | None = None


def magnetometer_calibrated(svc: BridgeServices) -> bool | None:
    """Whether the heading is calibrated on the host: None for a heading-only compass
    (it calibrates itself), False when no hard- or soft-iron correction is in use."""
    if svc.device.protocol != "gmr":
        return None
    return corrects_iron(svc.settings.calibration.mag)
