"""Live quality flags: magnetic disturbance and acceleration, cheap enough for every frame.

* **Disturbed** -- the measured field no longer looks like the Earth's: its
  strength differs from the expected one by more than ``field_tolerance`` (a
  fraction), or its dip (inclination, measured against the accelerometer's
  down) differs by more than ``dip_tolerance_deg``. Nearby iron, a motor
  current or a magnet does both; heading is then not trustworthy.
* **Accelerating** -- the accelerometer's magnitude is more than
  ``accel_tolerance_g`` away from 1 g: it is not measuring gravity alone, so
  roll/pitch (and through them the tilt-compensated heading) are unreliable.
  The dip check is skipped in that state, since it relies on the accelerometer.

The flags are debounced with frame counts (no clock: the core is pure) so one
noisy sample does not make them flap: a flag rises after ``raise_after``
consecutive bad frames and clears after ``clear_after`` consecutive good ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class QualityLimits:
    """Thresholds for the quality flags and the degraded-geometry zone.

    ``degraded_pitch_deg``: beyond this |pitch| roll and heading are ill-conditioned
    (gimbal zone), so the attitude is flagged degraded. Raises ``ValueError`` on
    out-of-range values.
    """

    field_tolerance: float = 0.15
    dip_tolerance_deg: float = 5.0
    accel_tolerance_g: float = 0.1
    degraded_pitch_deg: float = 85.0
    raise_after: int = 3
    clear_after: int = 5

    def __post_init__(self) -> None:
        for name in ("field_tolerance", "dip_tolerance_deg", "accel_tolerance_g"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not (
            isinstance(self.degraded_pitch_deg, int | float)
            and 0.0 < self.degraded_pitch_deg <= 90.0
        ):
            raise ValueError(
                f"degraded_pitch_deg must be in (0, 90], got {self.degraded_pitch_deg!r}"
            )
        for name in ("raise_after", "clear_after"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")


def field_out_of_limits(
    field_G: float,
    dip_deg: float | None,
    expected_total_G: float | None,
    expected_dip_deg: float | None,
    limits: QualityLimits,
) -> bool:
    """True when |B| or the dip angle is outside the limits around the expected values.

    A ``None`` expectation (unknown) or measurement (dip without gravity) is not
    checked. A non-finite measurement counts as out of limits.
    """
    if not math.isfinite(field_G):
        return True
    if (
        expected_total_G is not None
        and expected_total_G > 0.0
        and abs(field_G - expected_total_G) > limits.field_tolerance * expected_total_G
    ):
        return True
    # "not <=" so a NaN dip counts as out of limits
    return (
        dip_deg is not None
        and expected_dip_deg is not None
        and not abs(dip_deg - expected_dip_deg) <= limits.dip_tolerance_deg
    )


def accel_out_of_limits(accel_norm_g: float, limits: QualityLimits) -> bool:
    """True when the accelerometer magnitude is not 1 g within the tolerance (or not finite)."""
    return not (abs(accel_norm_g - 1.0) <= limits.accel_tolerance_g)


def heading_usable(saturated: bool, disturbed: bool) -> bool:
    """Whether a heading can be trusted: no raw channel at an ADC rail, the field not disturbed.

    The one judgement behind "healthy" wherever a heading is offered or reported
    (the autopilot feed, the magnetometer health bit, a bridge's status): with a
    channel clipped or a magnet nearby the heading is wrong by an unknown amount.
    Acceleration and the gimbal zone only make it less precise (a larger sigma).
    """
    return not saturated and not disturbed


class Debounce:
    """A boolean flag that rises after N consecutive ``True`` inputs and clears after M ``False``."""

    __slots__ = ("_clear_after", "_count", "_raise_after", "state")

    def __init__(self, raise_after: int = 1, clear_after: int = 1) -> None:
        if raise_after < 1 or clear_after < 1:
            raise ValueError("raise_after and clear_after must be >= 1")
        self._raise_after = raise_after
        self._clear_after = clear_after
        self._count = 0  # consecutive inputs that disagree with the current state
        self.state = False

    def update(self, bad: bool) -> bool:
        """Feed one frame's raw condition; returns the debounced flag."""
        if bad == self.state:
            self._count = 0
            return self.state
        self._count += 1
        if self._count >= (self._raise_after if bad else self._clear_after):
            self.state = bad
            self._count = 0
        return self.state

    def reset(self) -> None:
        """Back to cleared, forgetting any partial count."""
        self._count = 0
        self.state = False


class QualityMonitor:
    """Debounced disturbance and acceleration flags for a stream of frames (mutable, no I/O)."""

    __slots__ = ("_accel", "_field", "limits")

    def __init__(self, limits: QualityLimits | None = None) -> None:
        self.limits = limits if limits is not None else QualityLimits()
        self._field = Debounce(self.limits.raise_after, self.limits.clear_after)
        self._accel = Debounce(self.limits.raise_after, self.limits.clear_after)

    def update(
        self,
        field_G: float,
        dip_deg: float | None,
        accel_norm_g: float,
        expected_total_G: float | None,
        expected_dip_deg: float | None,
        *,
        down_trusted: bool | None = None,
    ) -> tuple[bool, bool]:
        """One frame in; ``(disturbed, accelerating)`` out, both debounced.

        The judgement is :func:`accel_out_of_limits` and :func:`field_out_of_limits`;
        under acceleration the "down" direction is wrong, so the dip says nothing
        about the field and only the magnitude is judged. ``down_trusted`` overrides
        that when the dip was measured against another down (a tilt source's).
        """
        lim = self.limits
        accel_bad = accel_out_of_limits(accel_norm_g, lim)
        trusted = not accel_bad if down_trusted is None else down_trusted
        field_bad = field_out_of_limits(
            field_G, dip_deg if trusted else None, expected_total_G, expected_dip_deg, lim
        )
        # (Debounce.update's first case -- the input agrees with the flag -- written out:
        # nearly every frame is one, and this runs for every frame.)
        f, a = self._field, self._accel
        if field_bad == f.state:
            f._count = 0
        else:
            f.update(field_bad)
        if accel_bad == a.state:
            a._count = 0
        else:
            a.update(accel_bad)
        return f.state, a.state

    @property
    def disturbed(self) -> bool:
        """Current debounced disturbance flag."""
        return self._field.state

    @property
    def accelerating(self) -> bool:
        """Current debounced acceleration flag."""
        return self._accel.state

    def reset(self) -> None:
        """Clear both flags (e.g. after a new calibration or reference)."""
        self._field.reset()
        self._accel.reset()
