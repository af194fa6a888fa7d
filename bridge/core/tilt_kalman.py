"""The tilt filter's small formulas (:mod:`bridge.core.tilt`; pure, plain floats).

The plane normal to the down and its axes, the field's rotation about the down,
whether a move of the down came with the field's, and the two scalar Kalman updates
on the 2-axis tilt correction: functions of their arguments, called once to a few
times a frame.
"""

from __future__ import annotations

import math

from bridge.core.vectors import Vec3, angle_deg

#: A basis of the plane normal to a down: its two axes' components, flat (:func:`basis`).
Axes = tuple[float, float, float, float, float, float]


def basis(d: Vec3) -> Axes:
    """Two unit vectors spanning the plane normal to ``d``: forward-ish, right-ish (their
    six components, flat: one to three bases a frame)."""
    # dot, unit and cross written out: the same arithmetic. (x . d with x = (1, 0, 0) or
    # (0, 1, 0) is d's component: for a finite d the terms times 0 only change the sign
    # of a zero k, which 0.0 - k * d and 1.0 - k * d do not see.)
    dx, dy, dz = d
    if abs(dx) < 0.9:
        k = dx
        ux, uy, uz = 1.0 - k * dx, 0.0 - k * dy, 0.0 - k * dz
    else:
        k = dy
        ux, uy, uz = 0.0 - k * dx, 1.0 - k * dy, 0.0 - k * dz
    n = math.sqrt(ux * ux + uy * uy + uz * uz)
    if n > 0.0:
        ux, uy, uz = ux / n, uy / n, uz / n
    else:
        ux, uy, uz = 0.0, 0.0, 1.0
    return ux, uy, uz, dy * uz - dz * uy, dz * ux - dx * uz, dx * uy - dy * ux


def rotation_about(m0: Vec3, m1: Vec3, d: Vec3) -> float:
    """The angle from ``m0`` to ``m1`` about ``d``, both projected onto its normal plane
    (dot and cross written out: once or twice a frame)."""
    ax, ay, az = m0
    bx, by, bz = m1
    dx, dy, dz = d
    k0 = ax * dx + ay * dy + az * dz
    k1 = bx * dx + by * dy + bz * dz
    p0x, p0y, p0z = ax - k0 * dx, ay - k0 * dy, az - k0 * dz
    p1x, p1y, p1z = bx - k1 * dx, by - k1 * dy, bz - k1 * dz
    cx, cy, cz = p0y * p1z - p0z * p1y, p0z * p1x - p0x * p1z, p0x * p1y - p0y * p1x
    return math.atan2(cx * dx + cy * dy + cz * dz, p0x * p1x + p0y * p1y + p0z * p1z)


def turned(d0: Vec3, d1: Vec3, m0: Vec3, m1: Vec3) -> bool:
    """Whether the down's move from ``d0`` to ``d1`` came with the field's own: the
    unit turned. Any tilt turns the field (dipping at I) in the unit's axes by at
    least ``sin(I)`` times as much; an acceleration moves the down alone."""
    if m0 == (0.0, 0.0, 0.0) or m1 == (0.0, 0.0, 0.0):
        return False
    return angle_deg(m0, m1) > 0.5 * angle_deg(d0, d1)


def match(y: float, h0: float, h1: float, R: float, x: list[float], P: list[float]) -> list[float]:
    """The dip: a scalar measurement that moves the estimate only along what it
    observes (``h``, the field's east axis) -- the minimal correction. The optimal
    gain would also move it across, through the covariance's cross term: with a
    dip a few tenths off (the learnt one is a mean over frames), every frame
    would push the held, unobserved axis a little further. Joseph form: the
    covariance stays positive whatever the gain."""
    hn2 = h0 * h0 + h1 * h1
    if hn2 <= 1e-12:
        return P
    pxx, pxy, pyy = P
    ph0 = pxx * h0 + pxy * h1
    ph1 = pxy * h0 + pyy * h1
    S = h0 * ph0 + h1 * ph1 + R
    if S <= 0.0:
        return P
    # The optimal gain projected onto h's direction.
    a = (h0 * ph0 + h1 * ph1) / (S * hn2)
    k0, k1 = a * h0, a * h1
    r = y - (h0 * x[0] + h1 * x[1])
    x[0] += k0 * r
    x[1] += k1 * r
    # P' = (I - k h^T) P (I - k h^T)^T + R k k^T
    i00, i01, i10, i11 = 1.0 - k0 * h0, -k0 * h1, -k1 * h0, 1.0 - k1 * h1
    a00 = i00 * pxx + i01 * pxy
    a01 = i00 * pxy + i01 * pyy
    a10 = i10 * pxx + i11 * pxy
    a11 = i10 * pxy + i11 * pyy
    return [
        a00 * i00 + a01 * i01 + R * k0 * k0,
        a00 * i10 + a01 * i11 + R * k0 * k1,
        a10 * i10 + a11 * i11 + R * k1 * k1,
    ]


def measure(
    y: float, axis: int, R: float, x0: float, x1: float, pxx: float, pxy: float, pyy: float
) -> tuple[float, float, float, float, float]:
    """One scalar measurement ``y = x[axis] + noise(R)`` on the correction ``(x0, x1)`` with
    covariance ``(pxx, pxy, pyy)``: the Kalman update, their new values.

    (``h`` is a unit axis, so ``h . x`` and ``P h`` are written as what they are: a term
    times 1.0 is the term; for finite values a term times 0.0 adds only a zero's sign,
    and never to a -0.0 -- the correction starts at +0.0 and is only added to, the
    variances are positive and the covariance's +0.0 stays one. The same bits as the
    general form.)"""
    if axis == 0:
        ph0, ph1, S, r = pxx, pxy, pxx + R, y - x0
    else:
        ph0, ph1, S, r = pxy, pyy, pyy + R, y - x1
    if S <= 0.0:
        return x0, x1, pxx, pxy, pyy
    k0, k1 = ph0 / S, ph1 / S
    return x0 + k0 * r, x1 + k1 * r, pxx - k0 * ph0, pxy - k0 * ph1, pyy - k1 * ph1
