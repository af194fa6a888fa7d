"""The heading feed for an autopilot's estimator: PX4 ODOMETRY or ArduPilot VISION_POSITION_ESTIMATE.

:class:`HeadingFeed` encodes one sample of the feed the parameter BRG_HDG_FEED
chooses (the message layouts are :func:`bridge.mavlink.telemetry.odometry` and
:func:`~bridge.mavlink.telemetry.vision_position_estimate`), withholds it when
the heading is not fit for an estimator (disturbed, saturated, COMPASS_USE 0),
when the autopilot would drop it (it has our own system and component id), and turns a heading *step* -- a new
calibration, mounting or declination -- into the reset each autopilot honours:
PX4 a new ``reset_counter``, ArduPilot a yaw source switch
(:meth:`~bridge.mavlink.autopilot.AutopilotWatch.heading_stepped`).

Time stamps are Unix-epoch microseconds (:meth:`FeedOwner.epoch_us`), so the
feed's clock continues across bridge restarts: ArduPilot's lag correction
(``JitterCorrection``) and PX4's time sync see no jump.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

from bridge.app.sample import CompassSample
from bridge.app.services import BridgeServices
from bridge.app.settings import REFERENCE_STEP_DEG, SettingsChange
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.autopilot import AutopilotWatch
from bridge.mavlink.dialect import Message

log = logging.getLogger(__name__)


class FeedOwner(Protocol):
    """What the feed uses of the MAVLink output."""

    services: BridgeServices
    clock: Callable[[], float]
    autopilot: AutopilotWatch

    @property
    def companion(self) -> bool:
        """Beside an autopilot."""
        ...

    def epoch_us(self, t: float) -> int:
        """``t`` (output clock) as Unix-epoch microseconds."""
        ...


class HeadingFeed:
    """The feed's encoders and its reset bookkeeping (see the module docstring)."""

    def __init__(self, owner: FeedOwner) -> None:
        self.owner = owner
        ref = owner.services.settings.reference
        self._declination = ref.declination_deg if ref is not None else None
        self._warned_magnetic = False

    def ok(self, s: CompassSample) -> bool:
        """Whether ``s`` may be sent to the autopilot now."""
        o = self.owner
        if o.services.params.get("COMPASS_USE") == 0 or not T.feed_usable(s):
            return False
        watch = o.autopilot
        if watch.same_identity:
            return False  # it would drop it
        if s.heading_true_deg is None and not self._warned_magnetic:
            self._warned_magnetic = True
            log.warning(
                "mavlink: heading feed sends the MAGNETIC heading: no declination known "
                "(set [location], or COMPASS_AUTODEC=0 and COMPASS_DEC)"
            )
        return True

    def odometry(self, s: CompassSample) -> Message | None:
        """PX4's feed for ``s`` (None: withheld)."""
        if not self.ok(s):
            return None
        sigma = self.owner.services.params.get("BRG_YAW_SIGMA")
        return T.odometry(s, self.owner.epoch_us(s.t), sigma, self._counter(s))

    def vision_position_estimate(self, s: CompassSample) -> Message | None:
        """ArduPilot's feed for ``s`` (None: withheld)."""
        if not self.ok(s):
            return None
        sigma = self.owner.services.params.get("BRG_YAW_SIGMA")
        return T.vision_position_estimate(s, self.owner.epoch_us(s.t), sigma, self._counter(s))

    def _counter(self, s: CompassSample) -> int:
        """``reset_counter`` for ``s``: the heading steps its own solution's configuration
        holds (:meth:`~bridge.app.settings.EngineSettings.heading_steps`).

        The counter must move on the very sample that carries the step. PX4's EKF2 resets
        its yaw to the sample whose counter moved. A sample the old configuration solved,
        sent with the new counter, resets it to the *old* heading, and the new one then
        comes as an ordinary measurement through the innovation gate (0.64 s to follow a
        5 deg step in PX4 SITL, against 0.14 s). A sample the new configuration solved,
        sent with the old counter, is a step EKF2 is not told of. Counted when the
        settings changed, each happened; counted from the sample's own generation,
        neither can. A sample without a solution (a heading-only compass's) takes the
        configuration in use.
        """
        a = s.attitude
        return self.owner.services.settings.heading_steps(a.generation if a is not None else None)

    def on_settings(self, change: SettingsChange) -> None:
        """The engine's calibration, mounting or reference changed: a disarmed ArduPilot
        beside us resets its yaw through a source switch (PX4's ``reset_counter`` follows
        the samples themselves: :meth:`_counter`). A declination that moved less than
        REFERENCE_STEP_DEG (a moving vehicle's position updates) is no step."""
        if change.aspect not in ("calibration", "mounting", "reference"):
            return
        if change.aspect == "reference":
            ref = self.owner.services.settings.reference
            dec = ref.declination_deg if ref is not None else None
            before, self._declination = self._declination, dec
            if (
                before is not None
                and dec is not None
                and abs((dec - before + 180.0) % 360.0 - 180.0) < REFERENCE_STEP_DEG
            ):
                return
        if self.owner.companion:
            self.owner.autopilot.heading_stepped(change.aspect)
