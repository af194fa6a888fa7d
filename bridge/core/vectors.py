"""Plain-float 3-vector helpers for the per-frame tilt path (pure).

numpy costs more than the arithmetic on 3-vectors at 100 frames a second, so
the tilt estimate (:mod:`bridge.core.tilt`) and the autopilot's attitude
(:mod:`bridge.core.aligned`) work on tuples. "Down" is the unit gravity vector in
body axes (x forward, y right, z down), the datasheet's sign: level = (0, 0, 1).
"""

from __future__ import annotations

import math

from bridge.types import Vec3


def dot(a: Vec3, b: Vec3) -> float:
    """a . b"""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a: Vec3, b: Vec3) -> Vec3:
    """a x b"""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def norm(a: Vec3) -> float:
    """|a|"""
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def unit(a: Vec3) -> Vec3:
    """a / |a| (level down for a zero vector)."""
    x, y, z = a
    n = math.sqrt(x * x + y * y + z * z)
    return (x / n, y / n, z / n) if n > 0.0 else (0.0, 0.0, 1.0)


def down_from_euler(roll: float, pitch: float) -> Vec3:
    """The unit gravity vector in body axes for ZYX roll and pitch (radians)."""
    cp = math.cos(pitch)
    return (-math.sin(pitch), math.sin(roll) * cp, math.cos(roll) * cp)


def down_from_quaternion(w: float, x: float, y: float, z: float) -> Vec3:
    """The unit gravity vector in body axes for a body->NED quaternion (ATTITUDE_QUATERNION):
    the third row of its rotation matrix."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n <= 0.0:
        return (0.0, 0.0, 1.0)
    w, x, y, z = w / n, x / n, y / n, z / n
    return (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


def euler_from_down(d: Vec3) -> tuple[float, float]:
    """(roll, pitch) in radians of a down vector (the datasheet's formulas)."""
    n = norm(d)
    if n <= 0.0:
        return 0.0, 0.0
    return math.atan2(d[1], d[2]), math.asin(max(-1.0, min(1.0, -d[0] / n)))


def angle_deg(a: Vec3, b: Vec3) -> float:
    """The angle between two vectors, degrees (0 for a zero vector: atan2(0, 0))."""
    ax, ay, az = a
    bx, by, bz = b
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.degrees(
        math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)
    )
