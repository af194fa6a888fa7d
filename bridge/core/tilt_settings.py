"""The tilt estimate's assumptions (:class:`TiltSettings`; the filter: :mod:`bridge.core.tilt`)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class TiltSettings:
    """The filter's assumptions (the defaults suit road vehicles and boats; docs/tilt.md).

    * ``accel_noise_g`` -- the accelerometer's white noise per axis and frame, the
      floor of what the filter learns (vibration adds to it);
    * ``tilt_rate_dps`` -- how fast roll and pitch change on a calm road (a random walk,
      deg/sqrt(s)): how fast the estimate follows when quiet, and a held one blurs;
    * ``heave_tilt_dps_per_g`` -- how much faster per g of vertical acceleration: swell
      rocks a vehicle as it heaves it (which does not turn the accelerometer's down);
    * ``gate`` -- an accelerometer down further from the estimate, along an axis,
      than the square root of this many sigmas is a manoeuvre, not a tilt;
    * ``turn_dps`` -- turning faster than this is a manoeuvre (a centripetal
      acceleration comes with it);
    * ``dip_sigma_deg`` -- how well the measured dip matches the expected one;
      ``dip_alarm_deg`` -- the accelerometer's down giving a dip off by more than
      this is a manoeuvre (an acceleration with a north-south part);
      ``dip_push_deg`` -- the most the dip may move a held axis in one manoeuvre;
    * ``release_s`` -- a manoeuvre ends this long after its last evidence;
      ``max_hold_s`` -- an axis held on the gate alone (no turn, no dip) this long
      takes the accelerometer again: no braking lasts so long, the tilt changed;
    * ``persist_s`` -- the gate and the dip alarm are evidence once they have held, one
      way, this long: a hand's shake (0.4-2.5 Hz) swings back sooner;
    * ``settle_s`` -- an accelerometer steady this long (its down still, 1 g, no turn)
      ends a manoeuvre and is taken: re-oriented by hand, no vehicle brakes so steadily;
    * ``spin_dps`` -- the field turning (about any axis) faster than this: turned by
      hand, faster than any vehicle turns or rocks; the accelerometer is followed;
    * ``max_accel_deg`` -- the accelerometer's (low-passed) down this far from the
      estimate (25 deg: 0.47 g) is more than a vehicle's acceleration: followed too;
    * ``heave_g`` -- above this vertical acceleration (low-passed) the vehicle is
      taken to be rocking in swell, and its turn rate is not believed;
    * ``lookback_s`` -- on a manoeuvre's onset the estimate goes back to the one
      this long before (its first frames were taken for tilt);
    * ``drift_s`` / ``drift_dps`` -- the accelerometer's down (low-passed) moving
      further than ``drift_dps`` per second (plus its noise) from the estimate of
      ``drift_s`` ago is a manoeuvre too: a braking vehicle's down moves as fast as
      a tilt, but not as far;
    * ``autopilot_sigma_deg`` -- the autopilot's roll/pitch error.
    """

    accel_noise_g: float = 0.004
    tilt_rate_dps: float = 1.0
    heave_tilt_dps_per_g: float = 60.0
    gate: float = 16.0
    turn_dps: float = 4.0
    dip_sigma_deg: float = 0.5
    dip_alarm_deg: float = 2.5
    dip_push_deg: float = 5.0
    release_s: float = 1.5
    lookback_s: float = 1.0
    drift_s: float = 1.5
    drift_dps: float = 1.0
    max_hold_s: float = 15.0
    settle_s: float = 1.0
    persist_s: float = 1.5
    spin_dps: float = 20.0
    max_accel_deg: float = 25.0
    heave_g: float = 0.05
    autopilot_sigma_deg: float = 0.3

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
