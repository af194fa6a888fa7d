"""The autopilot's attitude, aligned to a compass frame: its clock, its samples, its mounting.

Beside an autopilot (the companion role) the compass gets the vehicle's roll and
pitch from the autopilot's ATTITUDE: gyro-stabilised, untouched by the vehicle's
acceleration. To use them for one compass frame they must be taken at that
frame's instant and turned into the compass's axes. Three pure pieces:

* :class:`ClockMap` -- the autopilot's boot clock (``time_boot_ms``, TIMESYNC
  ``tc1``) on our monotonic clock, from TIMESYNC round trips, or from the
  messages' arrivals when the autopilot does not answer TIMESYNC;
* :class:`AttitudeTrack` -- the recent samples on the autopilot's clock,
  interpolated at an instant (or extrapolated over the link's latency);
* :class:`MountingResidual` -- the small rotation between the autopilot's body
  axes and the compass's vehicle axes, learnt from quasi-static frames;
* :class:`FrameClock` -- the compass frames' own instants, from their sequence
  numbers, not their arrivals (a busy host reads them late and in bursts).

The compass's vehicle axes are its accelerometer's axes turned by its mounting
(``AHRS_ORIENTATION`` and trim, :mod:`bridge.core.mounting`); the magnetometer's
own alignment to the accelerometer (``COMPASS_ORIENT``, ``BRG_ALIGN_*``) is in its
calibration, so the field is in those same axes. The autopilot's ATTITUDE is its
own vehicle axes (it applies its own ``AHRS_ORIENTATION``). The residual is what
is left between the two: a degree of it is a degree of tilt error, two of heading.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

from bridge.core.vectors import Vec3
from bridge.protocol.gmr_frames import RATES_HZ

_DEG = math.pi / 180.0


class ClockMap:
    """The autopilot's clock on ours: ``local = remote + offset`` (seconds).

    Two kinds of observation give the offset:

    * a message's arrival: ``arrival - remote`` is the offset *plus* that message's
      one-way delay; the smallest over the window (:attr:`window_s`) is the offset
      plus the link's smallest delay -- biased by that delay;
    * a TIMESYNC round trip (our request at ``sent``, the autopilot's time
      ``remote`` in its answer, the answer at ``received``): the offset is
      ``(sent + received) / 2 - remote``, off only by half the difference of the
      two directions' delays. The round trip with the shortest duration in the
      window wins (the least queued).

    Round trips are preferred; the arrivals are the fallback (an autopilot that
    does not answer TIMESYNC). The remote clock going back (a reboot) forgets all.
    """

    def __init__(self, window_s: float = 30.0) -> None:
        self.window_s = window_s
        self._arrivals: deque[tuple[float, float]] = deque()  # (local time, candidate offset)
        # (local time, rtt, offset): a monotone deque whose head is the window's shortest
        # round trip (the oldest of equals), as the arrivals' below.
        self._syncs: deque[tuple[float, float, float]] = deque()
        self._last_remote = -math.inf
        self.round_trip_s: float | None = None  #: the best round trip in the window
        self.offset: float | None = None  #: the current estimate (None: nothing heard)
        self.synced = False  #: the estimate comes from TIMESYNC round trips
        self.reboots = 0  #: times the remote clock went back

    def _expire(self, now: float) -> None:
        horizon = now - self.window_s
        while self._arrivals and self._arrivals[0][0] < horizon:
            self._arrivals.popleft()
        while self._syncs and self._syncs[0][0] < horizon:
            self._syncs.popleft()

    def _remote_seen(self, remote: float) -> bool:
        """Note a remote time; True when it means the autopilot rebooted."""
        rebooted = remote + 1.0 < self._last_remote
        if rebooted:
            self._arrivals.clear()
            self._syncs.clear()
            self.reboots += 1
            self._last_remote = remote
        else:
            self._last_remote = max(remote, self._last_remote)
        return rebooted

    def _estimate(self) -> None:
        if self._syncs:
            best = self._syncs[0]  # the window's shortest round trip (see round_trip)
            self.round_trip_s, self.offset, self.synced = best[1], best[2], True
        elif self._arrivals:
            self.offset = self._arrivals[0][1]  # the window's minimum (see arrival)
            self.round_trip_s, self.synced = None, False
        else:
            self.offset, self.round_trip_s, self.synced = None, None, False

    def arrival(self, remote_s: float, local_s: float) -> bool:
        """A message stamped ``remote_s`` on the autopilot's clock arrived at ``local_s``.

        Returns True when the stamp shows the autopilot rebooted.
        """
        rebooted = self._remote_seen(remote_s)
        cand = local_s - remote_s
        # A monotone deque: its head is the window's minimum. A candidate no smaller
        # than a newer one can never be the minimum while that one is in the window.
        while self._arrivals and self._arrivals[-1][1] >= cand:
            self._arrivals.pop()
        self._arrivals.append((local_s, cand))
        self._expire(local_s)
        self._estimate()
        return rebooted

    def round_trip(self, sent_s: float, remote_s: float, received_s: float) -> None:
        """A TIMESYNC answer: our request left at ``sent_s``, the answer (autopilot time
        ``remote_s``) came at ``received_s``. A negative duration is ignored."""
        rtt = received_s - sent_s
        if not (rtt >= 0.0 and math.isfinite(remote_s) and math.isfinite(rtt)):
            return
        self._remote_seen(remote_s)
        # A round trip longer than a newer one can never be the window's shortest; an equal
        # one stays (the oldest of equals wins).
        syncs = self._syncs
        while syncs and syncs[-1][1] > rtt:
            syncs.pop()
        syncs.append((received_s, rtt, 0.5 * (sent_s + received_s) - remote_s))
        self._expire(received_s)
        self._estimate()

    def remote(self, local_s: float) -> float | None:
        """The autopilot's time at a local instant (None before anything was heard)."""
        return None if self.offset is None else local_s - self.offset


# Not frozen, on purpose: one is made for every message the autopilot sends (two a compass
# frame), and a frozen dataclass's __init__ (object.__setattr__ per field) costs four times
# plain slot stores. Read-only by contract: the track shares them between threads.
@dataclass(slots=True)
class AttitudeSample:
    """One autopilot attitude: its instant on the autopilot's clock (s), its unit down
    vector in the autopilot's body axes, and its body rates (rad/s: ATTITUDE's
    rollspeed, pitchspeed, yawspeed -- its gyros) when it sent them (read-only by contract)."""

    t: float
    down: Vec3
    rate: Vec3 | None = None


class AttitudeTrack:
    """The autopilot's recent attitudes on its own clock, taken at any instant.

    Immutable snapshots (a tuple swapped on each :meth:`add`), so one thread may
    add while another reads without a lock. :meth:`at` interpolates the down
    vector between the two samples around ``t``, or extrapolates past the newest
    (a frame newer than the autopilot's last word, by the link's latency) up to
    :attr:`max_extrapolate_s`: with the newest sample's gyro rates when it has them
    (``d' = d x w``), else by a line fitted to the last :attr:`fit_s` (the slope of
    two noisy samples 50 ms apart would amplify their noise).
    """

    fit_s = 0.3

    def __init__(self, size: int = 64, max_extrapolate_s: float = 0.25) -> None:
        self._size = size
        self.max_extrapolate_s = max_extrapolate_s
        self._samples: tuple[AttitudeSample, ...] = ()

    def add(self, sample: AttitudeSample) -> None:
        """Keep ``sample`` (a late one is put in its place; a duplicate instant dropped)."""
        s = self._samples
        if s and sample.t <= s[-1].t:
            if any(x.t == sample.t for x in s):
                return
            s = tuple(sorted((*s, sample), key=lambda x: x.t))
        else:
            s = (*s, sample)
        self._samples = s[-self._size :]

    def clear(self) -> None:
        """Forget every sample (the autopilot rebooted: its clock started again)."""
        self._samples = ()

    @property
    def newest(self) -> AttitudeSample | None:
        """The latest sample, or None."""
        s = self._samples
        return s[-1] if s else None

    def at(self, t: float) -> tuple[Vec3, float] | None:
        """(down, how far past the newest sample it was extrapolated, s) at ``t`` on the
        autopilot's clock; None when the track does not cover ``t``."""
        s = self._samples
        if not s or t > s[-1].t + self.max_extrapolate_s or t < s[0].t:
            return None
        if len(s) == 1 or t >= s[-1].t:
            return self._extrapolate(s, t), max(0.0, t - s[-1].t)
        i = len(s) - 1
        while i > 1 and s[i - 1].t > t:
            i -= 1
        a, b = s[i - 1], s[i]
        span = b.t - a.t
        f = min(1.0, max(0.0, (t - a.t) / span)) if span > 0.0 else 1.0
        da, db = a.down, b.down
        return (
            (
                da[0] + f * (db[0] - da[0]),
                da[1] + f * (db[1] - da[1]),
                da[2] + f * (db[2] - da[2]),
            ),
            0.0,
        )

    def _extrapolate(self, s: tuple[AttitudeSample, ...], t: float) -> Vec3:
        last = s[-1]
        if last.rate is not None:
            d, w, dt = last.down, last.rate, t - last.t
            return (
                d[0] + (d[1] * w[2] - d[2] * w[1]) * dt,
                d[1] + (d[2] * w[0] - d[0] * w[2]) * dt,
                d[2] + (d[0] * w[1] - d[1] * w[0]) * dt,
            )
        pts = [x for x in s if x.t >= last.t - self.fit_s]
        if len(pts) < 2:
            pts = list(s[-2:])
        n = len(pts)
        if n < 2:
            return last.down
        mt = sum(x.t for x in pts) / n
        stt = sum((x.t - mt) ** 2 for x in pts)
        if stt <= 0.0:
            return last.down
        out = []
        for k in range(3):
            m = sum(x.down[k] for x in pts) / n
            slope = sum((x.t - mt) * (x.down[k] - m) for x in pts) / stt
            out.append(m + slope * (t - mt))
        return (out[0], out[1], out[2])


class MountingResidual:
    """The rotation ``C`` taking the autopilot's axes to the compass's vehicle axes.

    ``down_compass = C @ down_autopilot``. Learnt from quasi-static frames (where
    the compass's accelerometer is right) as Wahba's problem on the pairs of down
    vectors: Davenport's q-method, the largest eigenvector of his K matrix in
    closed form (:func:`_largest_eigenvector`: QUEST's Newton step for the
    eigenvalue, then the adjugate; plain floats, no numpy on the per-frame path:
    about 20 us a solve, no slower than numpy's ``eigh`` on a 4x4). A prior of
    ``prior_weight`` pseudo-pairs of identity starts it at "no residual" and holds
    what the data cannot tell (the rotation about the vertical needs tilted
    samples). Pairs are forgotten over ``memory`` pairs, so a re-mounted unit is
    followed. :attr:`scatter_deg` is the RMS angle between the compass's down and
    the aligned autopilot's on those frames: the two errors together.
    """

    def __init__(self, prior_weight: float = 5.0, memory: float = 20000.0) -> None:
        self.prior_weight = prior_weight
        self.memory = memory
        self.reset()

    def reset(self) -> None:
        """Forget what was learnt (the mounting changed)."""
        self._B = [[0.0] * 3 for _ in range(3)]  # sum of w * a b^T (compass a, autopilot b)
        self._n = 0.0
        self._C: tuple[Vec3, Vec3, Vec3] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        self._q = (1.0, 0.0, 0.0, 0.0)
        self._since = 0
        self._scatter2 = 0.0
        self._scatter_n = 0

    @property
    def pairs(self) -> float:
        """The (forgetting-weighted) number of pairs learnt from."""
        return self._n

    @property
    def scatter_deg(self) -> float | None:
        """RMS angle between the two downs after alignment, degrees (None before 50 pairs)."""
        if self._scatter_n < 50:
            return None
        return math.degrees(math.sqrt(self._scatter2))

    def rotation_deg(self) -> float:
        """The size of the residual rotation now applied, degrees."""
        w = max(-1.0, min(1.0, abs(self._q[0])))
        return math.degrees(2.0 * math.acos(w))

    def add(self, compass_down: Vec3, autopilot_down: Vec3) -> None:
        """One quasi-static pair of unit down vectors (compass accelerometer, autopilot)."""
        a, b = compass_down, self.apply(autopilot_down)
        miss = (a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2
        self._scatter_n += 1
        if self._scatter_n > 50:
            # Winsorised: an acceleration nobody caught must not widen what judges the next.
            miss = min(miss, 9.0 * self._scatter2)
        self._scatter2 += max(0.002, 1.0 / self._scatter_n) * (miss - self._scatter2)
        k = 1.0 - 1.0 / self.memory
        # B = k B + a b^T, written out (the same arithmetic as a loop over i, j, without one)
        (a0, a1, a2), (b0, b1, b2) = compass_down, autopilot_down
        r0, r1, r2 = self._B
        r0[0], r0[1], r0[2] = k * r0[0] + a0 * b0, k * r0[1] + a0 * b1, k * r0[2] + a0 * b2
        r1[0], r1[1], r1[2] = k * r1[0] + a1 * b0, k * r1[1] + a1 * b1, k * r1[2] + a1 * b2
        r2[0], r2[1], r2[2] = k * r2[0] + a2 * b0, k * r2[1] + a2 * b1, k * r2[2] + a2 * b2
        self._n = k * self._n + 1.0
        self._since += 1
        if self._since >= 10:  # solved every tenth pair: the rotation moves slowly
            self._since = 0
            self._solve()

    def _solve(self) -> None:
        w = self.prior_weight
        (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = self._B
        b00, b11, b22 = b00 + w, b11 + w, b22 + w
        # Davenport's K = [[s, z^T], [z, S - s I]] with S = B + B^T, s = trace B.
        s = b00 + b11 + b22
        z0, z1, z2 = b12 - b21, b20 - b02, b01 - b10
        s00, s11, s22 = 2.0 * b00, 2.0 * b11, 2.0 * b22
        s01, s02, s12 = b01 + b10, b02 + b20, b12 + b21
        q = _largest_eigenvector(s, z0, z1, z2, s00, s11, s22, s01, s02, s12)
        if q is None:  # the best rotation is not unique (see _largest_eigenvector)
            q = self._power_iteration(s, (z0, z1, z2), (s00, s11, s22, s01, s02, s12))
        if q[0] < 0:
            q = [-v for v in q]
        q0, q1, q2, q3 = q
        self._q = (q0, q1, q2, q3)
        # Davenport's attitude matrix A(q) = (q0^2 - |v|^2) I + 2 v v^T - 2 q0 [v x]
        # maps the reference (autopilot) vectors onto the observed (compass) ones.
        self._C = (
            (
                q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3,
                2 * (q1 * q2 + q0 * q3),
                2 * (q1 * q3 - q0 * q2),
            ),
            (
                2 * (q1 * q2 - q0 * q3),
                q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3,
                2 * (q2 * q3 + q0 * q1),
            ),
            (
                2 * (q1 * q3 + q0 * q2),
                2 * (q2 * q3 - q0 * q1),
                q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3,
            ),
        )

    def _power_iteration(
        self, s: float, z: Vec3, S: tuple[float, float, float, float, float, float]
    ) -> list[float]:
        """K's largest eigenvector by power iteration from the last answer: only where the
        largest eigenvalue is (nearly) double, so any vector of its plane is as good and the
        one nearest the last answer is kept (the data cannot tell the rotation)."""
        s00, s11, s22, s01, s02, s12 = S
        K = (
            (s, z[0], z[1], z[2]),
            (z[0], s00 - s, s01, s02),
            (z[1], s01, s11 - s, s12),
            (z[2], s02, s12, s22 - s),
        )
        # Shifted so the largest eigenvalue is the largest in magnitude (K's lie within
        # +-(n + 3w)).
        c = self._n + 3.0 * self.prior_weight + 1.0
        q = list(self._q)
        for _ in range(60):
            nq = [sum(K[i][j] * q[j] for j in range(4)) + c * q[i] for i in range(4)]
            nn = math.sqrt(sum(v * v for v in nq))
            nq = [v / nn for v in nq]
            step = sum(abs(x - y) for x, y in zip(nq, q, strict=True))
            q = nq
            if step < 1e-13:
                break
        return q

    def apply(self, v: Vec3) -> Vec3:
        """An autopilot-axes vector in the compass's vehicle axes."""
        (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = self._C
        x, y, z = v  # (three dot products written out: every frame, the same arithmetic)
        return (
            c00 * x + c01 * y + c02 * z,
            c10 * x + c11 * y + c12 * z,
            c20 * x + c21 * y + c22 * z,
        )


def _det3(
    a: float, b: float, c: float, d: float, e: float, f: float, g: float, h: float, i: float
) -> float:
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def _largest_eigenvector(
    s: float,
    z0: float,
    z1: float,
    z2: float,
    s00: float,
    s11: float,
    s22: float,
    s01: float,
    s02: float,
    s12: float,
) -> list[float] | None:
    """The unit eigenvector of Davenport's ``K = [[s, z^T], [z, S - s I]]`` (``S``
    symmetric) for its largest eigenvalue, scalar first and ``q[0] >= 0``; None when
    that eigenvalue is (numerically) double and the vector not unique.

    QUEST's way (Shuster & Oh, 1981) to the eigenvalue: Newton on K's characteristic
    polynomial ``l^4 - (a + b) l^2 - c l + (a b + c s - d)`` from an upper bound (all
    its roots are real, so Newton from above falls monotonically onto the largest),
    a few steps. Then the vector without QUEST's singularity at half a turn:
    ``adj(l I - K)`` is ``p q q^T`` (``p`` the product of the other eigenvalues'
    distances), so its column with the largest diagonal is ``q`` times a number.
    Plain floats, no iteration on the vector: the answer is the converged
    eigenvector to rounding (about 1e-15 rad), where power iteration on
    ``K + c I`` converges by ``1 - gap / 2n`` a step (hundreds of steps when
    the rotation about the vertical is weakly seen).
    """
    zz = z0 * z0 + z1 * z1 + z2 * z2
    sz0 = s00 * z0 + s01 * z1 + s02 * z2
    sz1 = s01 * z0 + s11 * z1 + s12 * z2
    sz2 = s02 * z0 + s12 * z1 + s22 * z2
    kappa = s11 * s22 - s12 * s12 + s00 * s22 - s02 * s02 + s00 * s11 - s01 * s01
    delta = _det3(s00, s01, s02, s01, s11, s12, s02, s12, s22)
    a = s * s - kappa
    b = s * s + zz
    c = delta + z0 * sz0 + z1 * sz1 + z2 * sz2
    d = sz0 * sz0 + sz1 * sz1 + sz2 * sz2
    c2, c0 = -(a + b), a * b + c * s - d
    # Upper bounds on the largest eigenvalue: Gershgorin's rows; and, K's trace being
    # zero, l1^2 <= 3/4 of the sum of all eigenvalues squared (its Frobenius norm^2).
    m1, m2, m3 = s00 - s, s11 - s, s22 - s
    gersh = max(
        s + abs(z0) + abs(z1) + abs(z2),
        m1 + abs(z0) + abs(s01) + abs(s02),
        m2 + abs(z1) + abs(s01) + abs(s12),
        m3 + abs(z2) + abs(s02) + abs(s12),
    )
    frob2 = s * s + 2.0 * zz + m1 * m1 + m2 * m2 + m3 * m3 + 2.0 * (s01**2 + s02**2 + s12**2)
    lam = min(gersh, math.sqrt(0.75 * frob2))
    for _ in range(60):
        l2 = lam * lam
        slope = (4.0 * l2 + 2.0 * c2) * lam - c
        if slope <= 0.0:  # on the root (a double one) or rounding past it
            break
        step = ((l2 + c2) * l2 - c * lam + c0) / slope
        lam -= step
        if step <= 1e-15 * abs(lam):
            break
    # M = l I - K, symmetric: its rows 0..3.
    m = (
        (lam - s, -z0, -z1, -z2),
        (-z0, lam - m1, -s01, -s02),
        (-z1, -s01, lam - m2, -s12),
        (-z2, -s02, -s12, lam - m3),
    )
    # The diagonal of adj(M): p q_j^2. The largest picks the best-conditioned column.
    diag = [_cofactor(m, j, j) for j in range(4)]
    j = max(range(4), key=diag.__getitem__)
    # Below this, the eigenvalue's gap is under about 1e-10 of it: the vector's rounding
    # error (about 1e-16 over the relative gap) would pass 1e-6 rad, and it is not unique.
    scale = max(abs(lam), 1e-300)
    if not diag[j] > 1e-10 * scale * scale * scale:
        return None
    col = [_cofactor(m, i, j) for i in range(4)]
    nn = math.sqrt(col[0] ** 2 + col[1] ** 2 + col[2] ** 2 + col[3] ** 2)
    sign = 1.0 if col[0] >= 0.0 else -1.0
    return [sign * v / nn for v in col]


def _cofactor(m: tuple[tuple[float, ...], ...], r: int, c: int) -> float:
    """The (r, c) cofactor of the 4x4 ``m``."""
    (i, j, k), (u, v, w) = _OTHERS[r], _OTHERS[c]
    det = _det3(m[i][u], m[i][v], m[i][w], m[j][u], m[j][v], m[j][w], m[k][u], m[k][v], m[k][w])
    return -det if (r + c) % 2 else det


_OTHERS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # the rows (columns) left of a minor


# -- the compass frames' clock -----------------------------------------------------------

#: The output rates a ``$PGMRA`` compass runs at (``RATE,<hz>``), frames per second: the
#: datasheet's list, as the protocol module has it.
DEVICE_RATES_HZ = RATES_HZ
# Where the snap goes from one rate to the next: the geometric mean of the two (the
# rate nearest in ratio, |log(seen / r)| smallest), so a frame costs a few comparisons.
_RATE_EDGES = tuple((math.sqrt(a * b), a) for a, b in itertools.pairwise(DEVICE_RATES_HZ))


def _snap_rate(seen: float) -> int:
    """The device rate nearest in ratio to ``seen`` frames per second."""
    for edge, rate in _RATE_EDGES:
        if seen < edge:
            return rate
    return DEVICE_RATES_HZ[-1]


#: The frames per second each rate is snapped from, ``[low, high)`` (:func:`_snap_rate`'s edges).
_RATE_BANDS = dict(
    zip(
        DEVICE_RATES_HZ,
        itertools.pairwise((-math.inf, *(edge for edge, _rate in _RATE_EDGES), math.inf)),
        strict=True,
    )
)


class FrameClock:
    """When each compass frame was sampled, from its ``seq`` and its arrival.

    Arrivals are late by a delay that varies: a serial read delivers several
    frames at once, and a busy host reads them tens or hundreds of milliseconds
    late. Frames are sampled on the device's clock, one ``seq`` apart at its rate.
    So a frame's instant is ``a + n p``: ``n`` its unwrapped ``seq``, ``p`` the
    period of the device's rate (frames per second over the last
    :data:`RATE_WINDOW_S` of arrivals, snapped to :data:`DEVICE_RATES_HZ`: a burst
    does not move it to another rate), ``a`` the least-delayed frame's
    ``arrival - n p`` of the last :data:`ANCHOR_WINDOW_S`. Until the rate is known,
    and after ``seq`` goes back or jumps further than the time since allows (a
    device restart) or the rate changes, a frame's instant is its arrival. Pure;
    the caller owns it (one per compass link).
    """

    RATE_WINDOW_S = 4.0
    ANCHOR_WINDOW_S = 2.0
    MODULO = 65536

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the frames: the next is its arrival."""
        self._seq: int | None = None
        self._n = 0
        self._arrivals: deque[tuple[float, int]] = deque()  # (arrival, n), rate window
        self._period: float | None = None
        self._band = (math.nan, math.nan)  # the frames per second its rate is snapped from
        self._anchor: deque[tuple[float, int, float]] = deque()  # (arrival, n, a): rising a

    @property
    def rate_hz(self) -> float | None:
        """The device's rate as learnt (None before it is)."""
        return None if self._period is None else 1.0 / self._period

    def at(self, seq: int, arrival: float) -> float:
        """The instant frame ``seq``, which arrived at ``arrival``, was sampled."""
        if self._seq is not None:
            step = (seq - self._seq) % self.MODULO
            p, last = self._period, self._arrivals[-1][0]
            if (
                step == 0
                or step > self.MODULO // 2
                or (p is not None and step * p > arrival - last + 1.0)
            ):  # went back, or on further than the time allows: the device restarted
                self.reset()
            else:
                self._n += step
        self._seq = seq
        n = self._n
        arr = self._arrivals
        arr.append((arrival, n))
        while len(arr) > 2 and arr[1][0] <= arrival - self.RATE_WINDOW_S:
            arr.popleft()
        a0, n0 = arr[0]
        if arrival - a0 >= 0.5 * self.RATE_WINDOW_S and n > n0:
            seen = (n - n0) / (arrival - a0)
            lo, hi = self._band
            if not lo <= seen < hi:  # (inside: the rate it has; no snap to look up, every frame)
                rate = _snap_rate(seen)
                self._band = _RATE_BANDS[rate]
                if self._period is None or abs(rate * self._period - 1.0) > 1e-9:
                    self._period = 1.0 / rate
                    self._anchor.clear()
        p = self._period
        if p is None:
            return arrival
        # The sliding minimum of arrival - n p over the anchor window (a rising deque).
        a = arrival - n * p
        anchor = self._anchor
        while anchor and anchor[-1][2] >= a:
            anchor.pop()
        anchor.append((arrival, n, a))
        while anchor[0][0] <= arrival - self.ANCHOR_WINDOW_S:
            anchor.popleft()
        return anchor[0][2] + n * p
