"""Tilt under acceleration: which "down" the heading is compensated with (pure, no I/O).

The tilt-compensated heading is only as good as the down direction it uses. The
compass's accelerometer measures gravity *minus* the vehicle's acceleration: at
0.3 g of horizontal acceleration its down is off by 17 deg, and the heading by up
to ``tan(dip)`` times that (two times at a dip of 63 deg). A vertical
acceleration (a bump, swell) only changes the reading's length, not its direction.

:class:`TiltFilter` gives every frame the down to use and says where it came from
(its *tilt source*, :data:`TILT_SOURCES`):

* ``accelerometer`` -- the vehicle is quiet: the accelerometer's down, smoothed;
* ``autopilot`` -- beside an autopilot (the companion role): its gyro-stabilised
  roll and pitch, taken at the frame's instant and turned into the compass's axes
  (:mod:`bridge.core.aligned`), which judge the accelerometer too;
* ``magnetometer`` -- standalone, while the vehicle manoeuvres: the tilt from the
  quasi-static frames before it, held in the vehicle's axes and kept matched to the
  field -- the measured field must keep the local dip against down
  (``d . m_hat = sin(dip)``), the "attitude matching" of the 12-position
  calibration paper, which pins the tilt about the field's east axis.

What the magnetometer cannot pin is the tilt about the field's horizontal (north)
axis: a rotation about it looks, to a magnetometer, like a turn. That is also the
only tilt error that moves the heading (a tilt error about the east axis leaves
it alone), ``tan(dip)`` times. So the held tilt's uncertainty about that axis,
growing while it is held, is the heading error the estimate announces
(``heading_sigma_deg``).

Everything is plain floats on 3-vectors (:mod:`bridge.core.vectors`): the
per-frame path runs at up to 100 Hz. Vectors are in the vehicle's body axes.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from operator import itemgetter
from typing import Literal

from bridge.core.tilt_kalman import Axes, basis, match, measure, rotation_about, turned
from bridge.core.tilt_settings import TiltSettings
from bridge.core.vectors import Vec3, angle_deg, dot

TiltSource = Literal["accelerometer", "autopilot", "magnetometer"]
#: The tilt sources, in the order MAVLink's ``TILT_SRC`` value numbers them (0, 1, 2).
TILT_SOURCES: tuple[TiltSource, ...] = ("accelerometer", "autopilot", "magnetometer")

_DEG = math.pi / 180.0
#: Steady frames (10 Hz ones' worth) before the learnt dip is used (matching, the alarm).
_DIP_FRAMES = 50
#: The accelerometer's white noise is learnt from frames at least this far apart (10 Hz).
_WHITE_SPACING_S = 0.075
_TIME = itemgetter(0)
#: The quiet estimates kept to roll back to on a manoeuvre's onset, seconds.
_HISTORY_S = 8.0
#: The held tilt is never assumed worse than this (radians; its variance beside it).
_MAX_SIGMA = 30.0 * _DEG
_MAX_VAR = _MAX_SIGMA**2
#: Turned by hand: the tilt's variance is floored at this, the frame's own down's noise at that.
_SPIN_FLOOR_VAR = (5.0 * _DEG) ** 2
_SPIN_MIN_WHITE = (0.2 * _DEG) ** 2
#: The accelerometer's down turning at 1 g is a turn by hand only from this far (degrees):
#: an acceleration that turned it so far would lengthen it by 1.5 %.
_HAND_MIN_DEG = 10.0
#: After a restart the accelerometer is followed as it is this long (s): the turn rates that
#: tell a hand from a vehicle need half a second of frames.
_FRESH_S = 0.5


# -- the estimate ---------------------------------------------------------------------


@dataclass(slots=True)
class TiltEstimate:
    """One frame's down direction and how it was found (read-only by contract).

    ``down`` is the unit gravity vector in vehicle axes; ``source`` one of
    :data:`TILT_SOURCES`; ``sigma_deg`` the tilt's 1-sigma error (the larger
    axis); ``heading_sigma_deg`` the heading error it gives (1 sigma);
    ``accel`` the accelerometer's own unit down this frame (:attr:`accel_deg`: how far
    it is from the estimate); ``manoeuvre`` whether the accelerometer is being
    distrusted (on any axis).
    """

    down: Vec3
    source: TiltSource
    sigma_deg: float
    heading_sigma_deg: float
    accel: Vec3
    manoeuvre: bool

    @property
    def accel_deg(self) -> float:
        """How far the accelerometer's own down is from the estimate, degrees (on
        request: nothing on the per-frame path needs it)."""
        return 0.0 if self.down is self.accel else angle_deg(self.accel, self.down)


class TiltFilter:
    """A Kalman filter on the down direction that knows when the accelerometer lies.

    The state is the down ``d`` (a unit vector) and its 2x2 covariance in the plane
    normal to it, on the basis ``e1`` (the vehicle's forward axis, levelled) and
    ``e2`` (its right axis, levelled): an error-state filter, each frame's
    correction folded into ``d``. The tilt is a random walk (``tilt_rate_dps``,
    faster while the vehicle heaves). Each axis is in one of two regimes:

    * **quiet**: the accelerometer's down along that axis is a measurement of ``d``
      with its white noise (learnt from the scatter ~0.1 s apart: vibration);
    * **manoeuvre**: it is not used; ``d`` is held along that axis, corrected only
      by the field's dip (and the autopilot's down when there is one).

    Why per axis: a vehicle accelerates along its own axes -- braking and driving
    off along x, turning along y (no sideslip) -- so while it brakes the
    accelerometer still gives the roll, and while it turns the pitch. An axis
    enters its manoeuvre on evidence (docs/tilt.md) and the estimate goes back to
    the one from before the onset; it leaves ``release_s`` after the last
    evidence, once the reading is back inside the gate (which widens as the held
    tilt's uncertainty grows, so a tilt that changed meanwhile is taken up).

    The magnetometer's dip (``d . m_hat = sin(dip)``, learnt on quiet frames)
    corrects held axes. Turned by hand, the frame's own down goes out as it is.
    Pure and single-threaded: the caller owns it.
    """

    #: The turn rate is measured over this long. Every window's edge (this one, the hand's
    #: half second, the spin's and the restart's hold) is a quarter frame interval inside
    #: it, so a frame on the edge -- at 10 Hz one is exactly there -- falls on one side
    #: whatever a millisecond of the frame clock or a rounding says.
    _TURN_BASE_S = 1.0

    def __init__(self, settings: TiltSettings | None = None) -> None:
        self.settings = settings if settings is not None else TiltSettings()
        self.reset()

    def reset(self) -> None:
        """Forget the estimate: the next frame starts from its accelerometer."""
        self._d: Vec3 | None = None
        self._P = [_MAX_VAR, 0.0, _MAX_VAR]  # (xx, xy, yy)
        self._t: float | None = None
        self._interval = 0.1  # the frames' mean interval, s
        self._g0 = 1.0  # |g| at rest (learnt: the accelerometer's scale)
        self._dip: float | None = None  # sin(dip) learnt from steady frames
        self._dip_n = 0.0  # 10 Hz frames' worth it was learnt from
        self._dip_alarm_since: float | None = None  # the dip contradicted since
        self._dip_alarm_sign = 0.0
        self._gate_since: list[float | None] = [None, None]  # outside the gate since, per axis
        self._gate_sign = [0.0, 0.0]
        self._gate_from: list[tuple[Vec3, Vec3]] = [((0, 0, 1), (0, 0, 0))] * 2  # (down, field)
        self._steady_since: float | None = None  # the accelerometer steady since
        self._steady_lp: Vec3 | None = None  # ... and its down then
        self._spinning_until = -math.inf  # turned by hand (faster than a vehicle) until
        self._fresh_until = -math.inf  # restarted: the accelerometer as it is until
        # (t, low-passed down, field, the accelerometer's down, at 1 g)
        self._recent: deque[tuple[float, Vec3, Vec3, Vec3, bool]] = deque()
        self.spin_dps = 0.0  #: the field's turn rate about any axis over the last second
        self._white = self.settings.accel_noise_g**2  # learnt white noise (vibration)
        self._heave = 0.0  # low-passed vertical acceleration, g
        self._an_mean = 1.0  # |g| over the last 2 s
        self._prev: Vec3 | None = None  # an accelerometer direction ~0.1 s ago (white noise)
        self._prev_t = -math.inf
        self._lp: Vec3 | None = None  # low-passed accelerometer direction
        self._long: Vec3 | None = None  # its long-run mean (20 s)
        self._m_now: Vec3 = (0.0, 0.0, 0.0)  # this frame's field direction
        self._mags: deque[tuple[float, Vec3]] = deque()  # recent field directions (turn rate)
        self.turn_rate_dps = 0.0  #: the field's turn about down over the last second
        self._turn_from = -math.inf  # the current turn began
        self._turning_at = -math.inf  # last turning (faster than a quarter of turn_dps)
        self._evidence_at = [-math.inf, -math.inf]  # last evidence, per axis
        self._held_since = [-math.inf, -math.inf]
        # (time, estimate, its covariance, the field's direction then, the estimate's basis):
        # quiet frames only.
        self._history: deque[tuple[float, Vec3, tuple[float, float, float], Vec3, Axes]] = deque()
        # The basis of an estimate (made with it: the next frame's and the drift check's).
        self._axes_of: Vec3 | None = None
        self._axes: Axes = basis((0.0, 0.0, 1.0))
        self.held = [False, False]  #: per axis (forward, right): in a manoeuvre
        self._dip_push = [0.0, 0.0]  # the dip's corrections to the held axes since the onset
        self._onset: tuple[Vec3, Vec3] | None = None  # (down, field) before the manoeuvre
        self.why = ""  #: what started the current manoeuvre ("gate", "turn", "dip")

    @property
    def manoeuvre(self) -> bool:
        """Either axis is held."""
        return self.held[0] or self.held[1]

    @property
    def learned_dip_deg(self) -> float | None:
        """The dip measured on quiet frames (None before any)."""
        if self._dip is None or self._dip_n < _DIP_FRAMES:
            return None
        return math.degrees(math.asin(self._dip))

    @property
    def down(self) -> Vec3 | None:
        """The current estimate (None before the first frame)."""
        return self._d

    @property
    def white_deg(self) -> float:
        """The accelerometer's learnt white noise (vibration) per axis and frame, degrees."""
        return math.degrees(math.sqrt(self._white))

    def _evidence(
        self, t: float, axes: tuple[int, ...], why: str, lookback: float | None = None
    ) -> None:
        if t < self._spinning_until:
            return  # turned by hand: no manoeuvre of a vehicle's
        onset = not self.manoeuvre
        for i in axes:
            self._evidence_at[i] = t
            if not self.held[i]:
                self._held_since[i] = t
            self.held[i] = True
        if not onset:
            return
        self.why = why
        self._dip_push = [0.0, 0.0]
        # Its first frames were believed: go back to the estimate from before it began.
        horizon = t - (self.settings.lookback_s if lookback is None else lookback)
        back: tuple[Vec3, tuple[float, float, float], Vec3] | None = None
        for ht, hd, hp, hm, _ha in self._history:
            if ht >= horizon:
                break
            back = (hd, hp, hm)
        self._history.clear()
        # Unless the field turned with the down meanwhile: then the unit turned (a
        # hand), and the estimate of then is no longer this attitude's.
        if (
            back is not None
            and self._lp is not None
            and not turned(back[0], self._lp, back[2], self._m_now)
        ):
            self._d, self._P = back[0], list(back[1])
        self._onset = None if back is None else (back[0], back[2])

    def update(
        self,
        mag: Vec3,
        accel: Vec3,
        t: float,
        *,
        external: Vec3 | None = None,
        external_sigma_deg: float | None = None,
        field_ok: bool = True,
    ) -> TiltEstimate:
        """One frame in, the down to use out (see the class docstring).

        ``external``: the autopilot's unit down in the compass's vehicle axes, at
        this frame's instant, with its 1-sigma error. ``field_ok``: the field is not
        disturbed (the dip is only learnt and used then).
        """
        st = self.settings
        # (Every frame runs this: the state it reads more than once is held in locals, and
        # the vector helpers -- norm, unit, dot, angle_deg -- are written out where they run
        # on most frames: the same arithmetic, in the same order, without a call and a tuple.)
        gx, gy, gz = accel
        an = math.sqrt(gx * gx + gy * gy + gz * gz)
        ahat = (gx / an, gy / an, gz / an) if an > 1e-6 else (0.0, 0.0, 1.0)
        ax, ay, az = ahat
        t_last = self._t
        if self._d is None or t_last is None:
            self._d, t_last = ahat, t
            self._fresh_until = t + _FRESH_S - 0.25 * self._interval  # (edges: see _TURN_BASE_S)
        else:  # frames read in one burst share their arrival: half the mean interval apart
            gap = t - t_last
            gap = gap if gap < 1.0 else 1.0  # max(0, min(1, gap)) as comparisons: every frame
            self._interval += 0.02 * ((gap if gap > 0.0 else 0.0) - self._interval)
            if t <= t_last:
                t = t_last + 0.5 * max(self._interval, 0.005)
        dt = t - t_last
        dt = dt if dt < 1.0 else 1.0  # in [0, 1]: a gain dt / tau for tau >= 1 s needs no clamp
        self._t = t
        # -- what the frame says beside its down: vibration, heave, turning, dip.
        # Its scatter between frames ~0.1 s apart, whatever the rate: a hand's shake is
        # smooth from one 50 Hz frame to the next, and would pass for no noise at all.
        prev_t = self._prev_t
        if t - prev_t >= _WHITE_SPACING_S or t < prev_t:
            prev, self._prev, self._prev_t = self._prev, ahat, t
            if prev is not None:
                dd = (ax - prev[0]) ** 2 + (ay - prev[1]) ** 2 + (az - prev[2]) ** 2
                v, floor = 0.25 * dd, st.accel_noise_g**2  # max(v, floor) as a comparison
                self._white += 0.005 * ((floor if floor > v else v) - self._white)
        white = self._white
        white_deg = math.degrees(math.sqrt(white))  # (self.white_deg)
        # (The low-pass gains min(1, dt / tau) as comparisons: they are calls otherwise.)
        k = dt / 0.5 if dt < 0.5 else 1.0
        # Heave: the swinging part of |g| (about its 2 s mean), not its offset -- a
        # braking vehicle's |g| grows steadily by a_h^2 / 2 without rocking it.
        an_mean = self._an_mean = self._an_mean + dt / 2.0 * (an - self._an_mean)
        heave = self._heave = self._heave + k * (abs(an - an_mean) - self._heave)
        lp = self._lp
        if lp is None:
            lp = ahat
        else:
            ux, uy, uz = (
                lp[0] + k * (ax - lp[0]),
                lp[1] + k * (ay - lp[1]),
                lp[2] + k * (az - lp[2]),
            )
            n = math.sqrt(ux * ux + uy * uy + uz * uz)
            lp = (ux / n, uy / n, uz / n) if n > 0.0 else (0.0, 0.0, 1.0)
        self._lp = lp
        lx, ly, lz = lp
        lg = self._long
        if lg is None:
            self._long = ahat
        else:
            k = dt / 20.0
            ux, uy, uz = (
                lg[0] + k * (ax - lg[0]),
                lg[1] + k * (ay - lg[1]),
                lg[2] + k * (az - lg[2]),
            )
            n = math.sqrt(ux * ux + uy * uy + uz * uz)
            self._long = (ux / n, uy / n, uz / n) if n > 0.0 else (0.0, 0.0, 1.0)
        bx, by, bz = mag
        bn = math.sqrt(bx * bx + by * by + bz * bz)
        mhat = (bx / bn, by / bn, bz / bn) if bn > 0.0 else (0.0, 0.0, 0.0)
        has_field = mhat != (0.0, 0.0, 0.0)
        mx, my, mz = mhat
        self._m_now = mhat
        held = self.held  # (a new list wherever it changes: read again after those)
        history = self._history
        if not (held[0] or held[1]) and history and t - history[0][0] >= st.drift_s:
            # The estimate of drift_s ago (the newest kept that old, or the oldest).
            i = bisect_right(history, t - st.drift_s, key=_TIME)
            _ht, old, _hp, old_m, old_axes = history[i - 1 if i > 1 else 0]  # max(0, i - 1)
            o1x, o1y, o1z, o2x, o2y, o2z = old_axes
            rate_dps = st.drift_dps + st.heave_tilt_dps_per_g * heave
            allowed = (rate_dps * st.drift_s + 3.0 * math.degrees(math.sqrt(white / 5.0))) * _DEG
            off1 = abs(lx * o1x + ly * o1y + lz * o1z) > allowed
            off2 = abs(lx * o2x + ly * o2y + lz * o2z) > allowed
            # Moving away from the long-run mean down: a manoeuvre's onset. Moving back
            # towards it is the end of one the estimate followed: no rollback then.
            # (Judged only when the down has left along an axis: nearly every frame it has not.)
            if (
                (off1 or off2)
                and angle_deg(lp, self._long) > angle_deg(old, self._long) + 1.0
                and not turned(old, lp, old_m, mhat)
            ):
                axes: tuple[int, ...] = (0, 1) if off1 and off2 else ((0,) if off1 else (1,))
                self._evidence(t, axes, "drift", st.drift_s)
        sin_dip = self._dip if self._dip_n >= _DIP_FRAMES else None
        steady_lp = self._steady_lp
        still = (
            abs(an - self._g0) < 0.01
            and heave < 0.02
            and abs(self.turn_rate_dps) < 0.5 * st.turn_dps
            # its down where it was when this began (the tail of a braking creeps back)
            and (steady_lp is None or angle_deg(ahat, steady_lp) < 1.0 + 2.0 * white_deg)
        )
        if not still:
            self._steady_since, self._steady_lp = None, None
        elif self._steady_since is None:
            self._steady_since, self._steady_lp = t, ahat
        if has_field:
            # The field's rotation about down over the last second, rad/s (the yaw rate: the
            # tilt changes it only through its own rate, which a vehicle keeps low).
            d = self._d
            mags = self._mags
            mags.append((t, mhat))
            horizon = t - self._TURN_BASE_S + 0.25 * self._interval  # (the frame 1 s back)
            while len(mags) > 2 and mags[1][0] <= horizon:
                mags.popleft()
            t0, then = mags[0]
            if t - t0 < 0.5 * self._TURN_BASE_S - 0.25 * self._interval:
                rate = 0.0
            else:
                # (angle_deg(then, mhat) written out)
                m0x, m0y, m0z = then
                cx, cy, cz = m0y * mz - m0z * my, m0z * mx - m0x * mz, m0x * my - m0y * mx
                self.spin_dps = math.degrees(
                    math.atan2(
                        math.sqrt(cx * cx + cy * cy + cz * cz), m0x * mx + m0y * my + m0z * mz
                    )
                ) / (t - t0)
                rate = rotation_about(then, mhat, d) / (t - t0)
            self.turn_rate_dps = math.degrees(rate)
            # The low-passed down turning fast, with the field: a tilt faster than a
            # vehicle's (swell aside) -- a hand.
            rec = self._recent
            one_g = abs(an - self._g0) < 0.01
            rec.append((t, lp, mhat, ahat, one_g))
            # The frame half a second back, within a quarter of the frame interval: at 10 Hz
            # one frame is exactly 0.5 s back, and "<= t - 0.5" took it or the one 0.6 s
            # back by a millisecond of the frame clock (or a rounding). A tumble's down
            # swings back at its slow phases: 12.7 deg turned over 0.5 s, 5.2 over 0.6 s --
            # a hand missed for two frames, the heading 5-17 deg off (tests/test_tilt.py,
            # test_the_hands_half_second_back_is_one_frame_whatever_a_millisecond_says).
            horizon = t - 0.5 + 0.25 * self._interval
            while len(rec) > 2 and rec[1][0] <= horizon:
                rec.popleft()
            tr, dr, mr, ar, one_g_then = rec[0]
            # (angle_deg(lp, d) written out)
            dx, dy, dz = d
            cx, cy, cz = ly * dz - lz * dy, lz * dx - lx * dz, lx * dy - ly * dx
            # (A turn by hand is a spin far more often than a tilt alone: no need to look
            # at the tilt then.)
            if self.spin_dps > st.spin_dps or (
                # Just restarted: nothing yet tells a hand from a vehicle (as a hand's, then);
                # or a down further off than any vehicle accelerates (30 deg: 0.58 g): turned.
                t < self._fresh_until
                or math.degrees(
                    math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), lx * dx + ly * dy + lz * dz)
                )
                > st.max_accel_deg
                or (
                    t - tr >= 0.25
                    and angle_deg(dr, lp) / (t - tr) > st.spin_dps
                    and turned(dr, lp, mr, mhat)
                    and heave < st.heave_g
                )
                or (
                    # The accelerometer's own down turning as fast, at 1 g throughout: no
                    # acceleration turns it 10 deg without lengthening it 1.5 %. (A turn about
                    # an axis near the field's turns the down, hardly the field: neither the
                    # spin nor turned() sees it.)
                    one_g
                    and one_g_then
                    and t - tr >= 0.25
                    and heave < st.heave_g
                    and angle_deg(ar, ahat) > max(_HAND_MIN_DEG, st.spin_dps * (t - tr))
                )
            ):
                # Faster than a vehicle turns: a hand. Follow the accelerometer as it is.
                self._spinning_until = t + 0.5 - 0.25 * self._interval  # (edges: _TURN_BASE_S)
                self.held, self._d = [False, False], ahat
                # Nothing from before the turn may be rolled back to, nor drifted from.
                history.clear()
                P, f = self._P, _SPIN_FLOOR_VAR  # each variance at least f (max() as comparisons)
                self._P = [f if P[0] < f else P[0], P[1], f if P[2] < f else P[2]]
                if external is None:  # nothing to weigh: the frame's own down, its noise
                    w = _SPIN_MIN_WHITE if white < _SPIN_MIN_WHITE else white
                    return self._result(ahat, ahat, mhat, (w, 0.0, w), "accelerometer", False)
            # (While the vehicle heaves, its rocking about the field's horizontal looks
            # like turning -- the same illusion that makes that tilt unobservable.)
            # When the turn began (its rate above a quarter of the threshold): a slowly
            # tightening turn builds its centripetal acceleration before it is caught.
            quarter = 0.25 * st.turn_dps * _DEG
            if abs(rate) < quarter:
                self._turn_from = t
            elif not self.held[1] or abs(rotation_about(mags[0][1], mhat, lp)) >= quarter * (
                t - mags[0][0]
            ):
                # (About the accelerometer's down too while the lateral axis is held: a
                # held down far off makes a changing tilt look like a turn.)
                self._turning_at = t
            if abs(rate) > st.turn_dps * _DEG and heave < st.heave_g:
                # ... if it pulls the accelerometer sideways: a turn on the spot (a
                # turntable, a pivoting boat) has no centripetal acceleration to hide.
                # (Against the estimate from before the turn began: the one since may
                # have followed the centripetal pull.)
                i = bisect_right(history, self._turn_from, key=_TIME)
                pre = history[i - 1][1] if i > 0 else self._d
                _b, _b, _b, b2x, b2y, b2z = basis(pre)
                if abs(lx * b2x + ly * b2y + lz * b2z) > max(
                    0.5 * _DEG, 2.0 * math.sqrt(white / 5.0)
                ):
                    self._evidence(t, (1,), "turn", t - self._turn_from + st.lookback_s)
            if field_ok and sin_dip is not None:
                v = mx * ax + my * ay + mz * az  # dot(mhat, ahat), clamped to [-1, 1]
                v = v if v < 1.0 else 1.0
                off = math.asin(v if v > -1.0 else -1.0) - math.asin(sin_dip)
                if abs(off) <= st.dip_alarm_deg * _DEG:
                    self._dip_alarm_since = None
                elif self._dip_alarm_since is None or off * self._dip_alarm_sign < 0:
                    self._dip_alarm_since, self._dip_alarm_sign = t, off
                elif t - self._dip_alarm_since > st.max_hold_s and heave < st.heave_g:
                    # The accelerometer has contradicted the learnt dip longer than any
                    # manoeuvre lasts: the field (or its calibration) changed. Learn it anew.
                    self._dip, self._dip_n, self._dip_alarm_since = None, 0.0, None
                    self.held = [False, False]
                    off = 0.0
                since = self._dip_alarm_since
                if (
                    abs(off) > st.dip_alarm_deg * _DEG
                    and since is not None
                    and (t - since >= st.persist_s)
                ):
                    # The axes the accelerometer's down has left the estimate along.
                    b = basis(self._d)
                    lim = max(st.dip_alarm_deg * _DEG, 3.0 * math.sqrt(white))
                    axes = tuple(i for i, e in enumerate((b[:3], b[3:])) if abs(dot(ahat, e)) > lim)
                    self._evidence(t, axes or (0, 1), "dip", st.persist_s + st.lookback_s)
        held = self.held
        if (
            (held[0] or held[1])
            and self._steady_since is not None
            and t - self._steady_since > st.settle_s
            # ... and the field turned with the down since the onset (a braking vehicle's
            # down creeps as steadily at first, the field stays put), or the down is
            # further off than an acceleration at 1 g (|g| within 0.01) can put it
            and (
                self._onset is None
                or angle_deg(self._d, lp) > 10.0
                or turned(self._onset[0], lp, self._onset[1], mhat)
            )
        ):
            # Settled: re-oriented, not accelerated. Take the accelerometer's down.
            self.held = [False, False]
            self._d = lp
            r = max(white, (0.5 * _DEG) ** 2)
            self._P = [r, 0.0, r]
            history.clear()
        d = self._d
        # -- predict: the tilt drifts, faster while the vehicle heaves.
        rate_dps = st.tilt_rate_dps + st.heave_tilt_dps_per_g * heave
        q = (rate_dps * _DEG) ** 2 * dt
        pxx, pxy, pyy = self._P
        pxx, pyy = pxx + q, pyy + q
        pxx = _MAX_VAR if pxx > _MAX_VAR else pxx
        pyy = _MAX_VAR if pyy > _MAX_VAR else pyy
        self._P = [pxx, pxy, pyy]
        frame_axes = self._axes if self._axes_of is d else basis(d)
        e1x, e1y, e1z, e2x, e2y, e2z = frame_axes
        # -- the accelerometer's down, axis by axis, inside the gate.
        # Frames faster than 10 Hz bring no more information a second (vibration and the
        # device's filtering correlate them): their noise, and the dip's, as 10 Hz frames'.
        slow = 0.1 / dt if 0.0 < dt < 0.1 else 1.0  # max(1, 0.1 / dt)
        R = white * slow
        y1, y2 = ax * e1x + ay * e1y + az * e1z, ax * e2x + ay * e2y + az * e2z
        es = (
            external_sigma_deg if external_sigma_deg is not None else st.autopilot_sigma_deg
        ) * _DEG
        if external is not None:
            # Beside an autopilot its down judges the accelerometer's, axis by axis.
            ex, ey, ez = external
            z1, z2 = ex * e1x + ey * e1y + ez * e1z, ex * e2x + ey * e2y + ez * e2z
            z = y1 - z1
            if z * z > st.gate * (es * es + R):
                self._evidence(t, (0,), "autopilot", 0.0)
            z = y2 - z2
            if z * z > st.gate * (es * es + R):
                self._evidence(t, (1,), "autopilot", 0.0)
        gate = st.gate
        if y1 * y1 > gate * (pxx + R) or y2 * y2 > gate * (pyy + R):
            for i, yi, pii in ((0, y1, pxx), (1, y2, pyy)):
                if yi * yi > gate * (pii + R):
                    since = self._gate_since[i]
                    if since is None or yi * self._gate_sign[i] < 0:
                        self._gate_since[i], self._gate_sign[i] = t, yi
                        self._gate_from[i] = (d, mhat)
                        since = t
                    if not self.held[i]:
                        gd, gm = self._gate_from[i]
                        if t - since >= st.persist_s and not turned(gd, ahat, gm, mhat):
                            self._evidence(t, (i,), "gate", st.persist_s + st.lookback_s)
                    elif t - self._held_since[i] < st.max_hold_s and (
                        i == 0 or t - self._turning_at < st.release_s
                    ):
                        # (Not turning, a wheeled vehicle has no lateral acceleration.)
                        self._evidence(t, (i,), "gate")
                    elif t - self._evidence_at[i] > st.release_s:
                        # Held this long on the gate alone: no manoeuvre lasts so long, the
                        # tilt changed meanwhile. Take the accelerometer's again.
                        self.held[i] = False
                        self._P[0 if i == 0 else 2] += yi * yi
                else:
                    self._gate_since[i] = None
                    if self.held[i] and t - self._evidence_at[i] > st.release_s:
                        self.held[i] = False
        else:  # (both inside the gate, as nearly every frame: the loop's else, written out)
            gate_since, held, evidence_at = self._gate_since, self.held, self._evidence_at
            gate_since[0] = gate_since[1] = None
            if held[0] and t - evidence_at[0] > st.release_s:
                held[0] = False
            if held[1] and t - evidence_at[1] > st.release_s:
                held[1] = False
        if self._d is not d:  # rolled back: the basis moves with it
            d = self._d
            frame_axes = basis(d)
            e1x, e1y, e1z, e2x, e2y, e2z = frame_axes
            y1, y2 = ax * e1x + ay * e1y + az * e1z, ax * e2x + ay * e2y + az * e2z
            if external is not None:
                z1, z2 = ex * e1x + ey * e1y + ez * e1z, ex * e2x + ey * e2y + ez * e2z
        held = self.held
        x0 = x1 = 0.0
        pxx, pxy, pyy = self._P
        if not held[0]:
            x0, x1, pxx, pxy, pyy = measure(y1, 0, R, x0, x1, pxx, pxy, pyy)
        if not held[1]:
            x0, x1, pxx, pxy, pyy = measure(y2, 1, R, x0, x1, pxx, pxy, pyy)
        # -- the field's dip (attitude matching), every regime.
        if (held[0] or held[1]) and field_ok and has_field and sin_dip is not None:
            self._P = [pxx, pxy, pyy]
            x = [x0, x1]
            cos_dip = math.sqrt(max(1e-6, 1.0 - sin_dip * sin_dip))
            Rm = (cos_dip * st.dip_sigma_deg * _DEG) ** 2 * slow
            h0 = mx * e1x + my * e1y + mz * e1z
            h1 = mx * e2x + my * e2y + mz * e2z
            # The residual with the accelerometer's axes as they now are; the dip then
            # corrects the held axes only, and only where it sees them well: pushed
            # through a small part of it along a held axis, a residual a few tenths off
            # (the learnt dip, or the other axis's undetected acceleration) would move
            # that axis far, frame after frame.
            r = sin_dip - dot(mhat, d) - h0 * x[0] - h1 * x[1]
            hn = math.hypot(h0, h1)
            m0 = h0 if held[0] else 0.0
            m1 = h1 if held[1] else 0.0
            S = h0 * h0 * pxx + 2 * h0 * h1 * pxy + h1 * h1 * pyy + Rm
            lp_off = math.asin(max(-1.0, min(1.0, dot(mhat, lp)))) - math.asin(sin_dip)
            if r * r > st.gate * S and abs(lp_off) > st.dip_alarm_deg * _DEG:
                # More than the held axes can explain, and the accelerometer's own down
                # misses the dip too: its axes are not gravity's either. Hold them all.
                # (Its down matching the dip where the estimate does not: the estimate
                # is what is wrong -- no evidence against the accelerometer.)
                self._evidence(t, (0, 1), "dip", 0.0)
            elif max(map(abs, self._dip_push)) < st.dip_push_deg * _DEG:
                x_before = (x[0], x[1])
                if (held[0] and held[1]) or math.hypot(m0, m1) > 0.5 * hn:
                    self._P = match(r + m0 * x[0] + m1 * x[1], m0, m1, Rm, x, self._P)
                else:
                    self._P = match(r + h0 * x[0] + h1 * x[1], h0, h1, Rm, x, self._P)
                self._dip_push[0] += x[0] - x_before[0]
                self._dip_push[1] += x[1] - x_before[1]
            x0, x1 = x
            pxx, pxy, pyy = self._P
        # -- the autopilot's down.
        if external is not None:
            # (its components on the axes as they now are: z1, z2)
            x0, x1, pxx, pxy, pyy = measure(z1, 0, es * es, x0, x1, pxx, pxy, pyy)
            x0, x1, pxx, pxy, pyy = measure(z2, 1, es * es, x0, x1, pxx, pxy, pyy)
        ux, uy, uz = (
            d[0] + x0 * e1x + x1 * e2x,
            d[1] + x0 * e1y + x1 * e2y,
            d[2] + x0 * e1z + x1 * e2z,
        )
        n = math.sqrt(ux * ux + uy * uy + uz * uz)
        nd = (ux / n, uy / n, uz / n) if n > 0.0 else (0.0, 0.0, 1.0)
        self._d = nd
        self._axes_of, self._axes = nd, basis(nd)
        P = self._P = [pxx, pxy, pyy]
        held = self.held  # final for this frame from here on
        manoeuvre = held[0] or held[1]
        w = dt / 0.1 if dt < 0.1 else 1.0  # the frame's weight: its share of a 10 Hz frame
        g0 = self._g0
        if not manoeuvre:
            history.append((t, nd, (pxx, pxy, pyy), mhat, self._axes))
            horizon = t - _HISTORY_S
            while history and history[0][0] < horizon:
                history.popleft()
            if abs(an - g0) < 0.05:
                g0 = self._g0 = g0 + 0.01 * w * (an - g0)
        # Steady: learn the local dip. Steady is no manoeuvre, the accelerometer's
        # length at |g|, its down not moving, the vehicle not turning.
        if not manoeuvre and abs(an - g0) < 0.02 and heave < 0.02:
            # (angle_deg(lp, ahat) written out)
            cx, cy, cz = ly * az - lz * ay, lz * ax - lx * az, lx * ay - ly * ax
            steady = (
                math.degrees(
                    math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), lx * ax + ly * ay + lz * az)
                )
                < 3.0 * white_deg + 0.5
                and abs(self.turn_rate_dps) < 0.5 * st.turn_dps
            )
            if steady and field_ok and has_field and w > 0.0:
                sd = mx * ax + my * ay + mz * az
                self._dip_n += w
                rate = w / self._dip_n
                if 0.005 * w > rate:  # at least 0.005 of a 10 Hz frame: max() as a comparison
                    rate = 0.005 * w
                self._dip = sd if self._dip is None else self._dip + rate * (sd - self._dip)
        # -- which source carried it, and how well.
        if external is not None and (manoeuvre or es * es < R):
            source: TiltSource = "autopilot"
        else:
            source = "magnetometer" if manoeuvre else "accelerometer"
        return self._result(nd, ahat, mhat, P, source, manoeuvre, frame_axes)

    def _result(
        self, nd: Vec3, ahat: Vec3, mhat: Vec3, P: Sequence[float],
        source: TiltSource, manoeuvre: bool,
        basis: Axes | None = None,
    ) -> TiltEstimate:  # fmt: skip
        """The estimate ``nd`` with covariance ``P`` (xx, xy, yy on ``basis``'s axes, as
        :func:`~bridge.core.tilt_kalman.basis` gives them; none: the same on every axis) as it goes out."""
        sxx, sxy, syy = P
        v = 0.5 * (sxx + syy) + math.sqrt(0.25 * (sxx - syy) ** 2 + sxy * sxy)
        sigma = math.sqrt(v if v > 0.0 else 0.0)  # (max(0, v) as a comparison: every frame)
        hs = sigma
        if mhat != (0.0, 0.0, 0.0):
            # the field's east axis, east = nd x mhat (vector helpers written out: every frame)
            nx, ny, nz = nd
            mx, my, mz = mhat
            ex, ey, ez = ny * mz - nz * my, nz * mx - nx * mz, nx * my - ny * mx
            en = math.sqrt(ex * ex + ey * ey + ez * ez)
            if en > 1e-3:
                var = sxx
                if basis is not None:
                    b1x, b1y, b1z, b2x, b2y, b2z = basis
                    f1 = (ex * b1x + ey * b1y + ez * b1z) / en
                    f2 = (ex * b2x + ey * b2y + ez * b2z) / en
                    var = f1 * f1 * sxx + 2 * f1 * f2 * sxy + f2 * f2 * syy
                hs = math.sqrt(var if var > 0.0 else 0.0) * abs(mx * nx + my * ny + mz * nz) / en
        return TiltEstimate(nd, source, math.degrees(sigma), math.degrees(hs), ahat, manoeuvre)
