"""Rotation helpers (NED world, FRD body), shared by the engine and the simulator.

Conventions, used everywhere in the package:

* ``R`` (a "DCM") rotates body-frame vectors into NED: ``v_ned = R @ v_body``.
* Euler angles are aerospace ZYX: yaw (psi) about down, then pitch (theta)
  about the new right axis, then roll (phi) about the new forward axis -- the
  angles MAVLink ATTITUDE carries, in radians unless a name says ``_deg``.
* Quaternions are ``(w, x, y, z)``, body to NED, as in ATTITUDE_QUATERNION.
* A sensor at attitude ``R`` in a field ``B_ned`` reads ``R.T @ B_ned``; its
  accelerometer (gravity vector, datasheet sign) reads ``R.T @ (0, 0, 1)`` g.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from bridge.core.vectors import norm
from bridge.types import FloatArray

GRAVITY_NED = np.array([0.0, 0.0, 1.0])  #: gravity direction in NED, in g


def euler_to_dcm(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Body-to-NED rotation matrix from ZYX Euler angles (radians)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    # (nine floats then reshaped: numpy reads a flat sequence faster than nested rows, and
    # the simulator and the tests build tens of thousands of these)
    return np.array(
        (
            cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy,
            cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy,
            -sp, sr * cp, cr * cp,
        )
    ).reshape(3, 3)  # fmt: skip


def euler_to_dcm_batch(roll: npt.ArrayLike, pitch: npt.ArrayLike, yaw: npt.ArrayLike) -> FloatArray:
    """Vectorised :func:`euler_to_dcm`: arrays of N angles to an (N, 3, 3) stack."""
    r = np.asarray(roll, dtype=np.float64)
    p = np.asarray(pitch, dtype=np.float64)
    y = np.asarray(yaw, dtype=np.float64)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    out = np.empty((*r.shape, 3, 3))
    out[..., 0, 0] = cp * cy
    out[..., 0, 1] = sr * sp * cy - cr * sy
    out[..., 0, 2] = cr * sp * cy + sr * sy
    out[..., 1, 0] = cp * sy
    out[..., 1, 1] = sr * sp * sy + cr * cy
    out[..., 1, 2] = cr * sp * sy - sr * cy
    out[..., 2, 0] = -sp
    out[..., 2, 1] = sr * cp
    out[..., 2, 2] = cr * cp
    return out


def dcm_to_euler(R: npt.ArrayLike) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in radians from a body-to-NED matrix.

    Yaw is returned in (-pi, pi]. At pitch = +-90 deg roll and yaw are not
    separable; this returns a finite pair (roll folded into yaw).
    """
    m = np.asarray(R, dtype=np.float64)
    pitch = -math.asin(max(-1.0, min(1.0, float(m[2, 0]))))
    roll = math.atan2(float(m[2, 1]), float(m[2, 2]))
    yaw = math.atan2(float(m[1, 0]), float(m[0, 0]))
    return roll, pitch, yaw


def dcm_to_euler_batch(R: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Vectorised :func:`dcm_to_euler`: an (N, 3, 3) stack to arrays of N roll, pitch, yaw."""
    m = np.asarray(R, dtype=np.float64)
    pitch = -np.arcsin(np.clip(m[:, 2, 0], -1.0, 1.0))
    roll = np.arctan2(m[:, 2, 1], m[:, 2, 2])
    yaw = np.arctan2(m[:, 1, 0], m[:, 0, 0])
    return roll, pitch, yaw


def dcm_to_quaternion(R: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) with w >= 0 from a rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        w = 0.25 * s
        x = (m[2, 1] - m[1, 2]) / s
        y = (m[0, 2] - m[2, 0]) / s
        z = (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        w = (m[2, 1] - m[1, 2]) / s
        x = 0.25 * s
        y = (m[0, 1] + m[1, 0]) / s
        z = (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        w = (m[0, 2] - m[2, 0]) / s
        x = (m[0, 1] + m[1, 0]) / s
        y = 0.25 * s
        z = (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        w = (m[1, 0] - m[0, 1]) / s
        x = (m[0, 2] + m[2, 0]) / s
        y = (m[1, 2] + m[2, 1]) / s
        z = 0.25 * s
    q = np.array([w, x, y, z], dtype=np.float64)
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def quaternion_to_dcm(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrix from a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = (np.asarray(q, dtype=np.float64) / np.linalg.norm(q)).tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def euler_to_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z), body->NED, w >= 0, from ZYX Euler angles (radians).

    The one conversion of the package: the attitude engine, MAVLink
    ATTITUDE_QUATERNION and Zenoh's ``attitude`` all give this quaternion for the
    same angles. The closed form of the half angles (plain floats, no matrix).
    """
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    return (w, x, y, z) if w >= 0.0 else (-w, -x, -y, -z)


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def _rodrigues(x: float, y: float, z: float, n: float, angle: float) -> FloatArray:
    """Rotation by ``angle`` about (x, y, z), whose length is ``n``.

    The length is :func:`~bridge.core.vectors.norm`'s plain floats: the same number as
    ``np.linalg.norm`` (the square root of BLAS's dot, which adds the three squares in
    order: checked on 160 022 vectors), without its Python layers -- the rotations run once
    per step of every Gauss-Newton fit and once per frame of the simulator.
    """
    if n == 0.0:
        return np.eye(3)
    kx, ky, kz = x / n, y / n, z / n
    K = np.array((0.0, -kz, ky, kz, 0.0, -kx, -ky, kx, 0.0)).reshape(3, 3)
    return _EYE3 + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def axis_angle_to_dcm(axis: npt.ArrayLike, angle: float) -> FloatArray:
    """Rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    x, y, z = np.asarray(axis, dtype=np.float64).tolist()
    return _rodrigues(x, y, z, norm((x, y, z)), angle)


def rotvec_to_dcm(rotvec: npt.ArrayLike) -> FloatArray:
    """Rotation matrix from a rotation vector (axis * angle, radians)."""
    x, y, z = np.asarray(rotvec, dtype=np.float64).tolist()
    n = norm((x, y, z))
    return _rodrigues(x, y, z, n, n)


def dcm_to_rotvec(R: npt.ArrayLike) -> FloatArray:
    """Rotation vector (axis * angle, radians) of a rotation matrix."""
    m = np.asarray(R, dtype=np.float64)
    # 2 sin(angle) * axis is the skew part; cos(angle) the trace's. atan2 of the two keeps
    # small angles that acos(cos) rounds to zero (below ~1e-8 rad).
    v = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    s = 0.5 * float(np.linalg.norm(v))
    c = (float(np.trace(m)) - 1.0) / 2.0
    angle = math.atan2(s, c)
    if angle < 1e-6:
        return 0.5 * v  # angle / sin(angle) = 1 to 2e-13
    if math.pi - angle < 1e-6:
        # near 180 deg: axis from the symmetric part
        S = (m + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(S), 0.0, None))
        i = int(np.argmax(axis))
        axis = S[:, i] / math.sqrt(max(S[i, i], 1e-300))
        return axis / np.linalg.norm(axis) * angle
    return v * (angle / (2.0 * math.sin(angle)))


def dcm_to_rotvec_batch(R: npt.ArrayLike) -> FloatArray:
    """Vectorised :func:`dcm_to_rotvec`: an (N, 3, 3) stack to (N, 3) rotation vectors
    (rotations within 1e-6 rad of 180 deg go through :func:`dcm_to_rotvec` one by one)."""
    m = np.asarray(R, dtype=np.float64)
    v = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], 1)
    s = 0.5 * np.linalg.norm(v, axis=1)
    c = (np.trace(m, axis1=1, axis2=2) - 1.0) / 2.0
    angle = np.arctan2(s, c)
    small = angle < 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(small, 0.5, angle / (2.0 * np.sin(angle)))
    out = v * factor[:, None]
    for k in np.flatnonzero(math.pi - angle < 1e-6):
        out[k] = dcm_to_rotvec(m[k])
    return out


def random_rotations(rng: np.random.Generator, n: int) -> FloatArray:
    """``n`` rotation matrices uniformly distributed over SO(3), as an (n, 3, 3) stack."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out = np.empty((n, 3, 3))
    out[:, 0, 0] = 1 - 2 * (y * y + z * z)
    out[:, 0, 1] = 2 * (x * y - w * z)
    out[:, 0, 2] = 2 * (x * z + w * y)
    out[:, 1, 0] = 2 * (x * y + w * z)
    out[:, 1, 1] = 1 - 2 * (x * x + z * z)
    out[:, 1, 2] = 2 * (y * z - w * x)
    out[:, 2, 0] = 2 * (x * z - w * y)
    out[:, 2, 1] = 2 * (y * z + w * x)
    out[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def wrap_degrees_360(angle_deg: float) -> float:
    """Fold an angle into [0, 360) -- the one fold of the package (headings, declination).

    ``0.0`` where rounding would give 360.0 (``-1e-15 + 360.0 == 360.0``).
    """
    a = math.fmod(angle_deg, 360.0)
    if a < 0.0:
        a += 360.0
    return 0.0 if a >= 360.0 else a


def wrap_radians_pi(angle_rad: float) -> float:
    """Fold an angle into (-pi, pi] radians (a yaw as MAVLink ATTITUDE carries it).

    Angles already in range come back unchanged, bit for bit.
    """
    if -math.pi < angle_rad <= math.pi:
        return angle_rad
    a = math.fmod(angle_rad, 2.0 * math.pi)  # exact; in (-2 pi, 2 pi)
    if a > math.pi:
        a -= 2.0 * math.pi
    elif a <= -math.pi:
        a += 2.0 * math.pi
    return a


def wrap_degrees_180(angle_deg: float) -> float:
    """Fold an angle into [-180, 180)."""
    return wrap_degrees_360(angle_deg + 180.0) - 180.0


def angle_diff_deg(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Signed smallest difference a - b in degrees, in [-180, 180), element-wise."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return (d + 180.0) % 360.0 - 180.0
