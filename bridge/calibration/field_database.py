"""Method 7: attitude from the magnetometer alone, by matching against a recorded field database.

For bodies whose accelerometer is useless (spinning projectiles, bodies under
sustained acceleration) the seed work on magnetoresistive attitude records
pairs of (calibrated field vector in body axes, attitude) and then, in use,
looks the measured field up and interpolates the attitude of the nearest
entries.

What it can and cannot give -- read this before selecting it:

* A field vector has a fixed length, so it carries **two** degrees of freedom
  (its direction in body axes). A full attitude has three. The lookup is only
  meaningful when the body's motion is constrained to at most two degrees of
  freedom *and the database was recorded under the same constraint*: e.g. a
  body spinning about a known body axis whose direction in space is known
  (one DOF: roll within ~3 deg with a dense database), or a pan/tilt head with
  no roll (two DOF: 3-axis attitude within ~5 deg where the field-direction map
  is one-to-one).
* If the database holds several attitudes with the same field direction (an
  unconstrained body, or a constraint under which the map folds over), the
  neighbours disagree: the match is flagged (``ok=False``, large
  ``spread_deg``) rather than silently averaged.
* Sensitivity vanishes when the rotation axis is nearly parallel to the field
  (the field does not change as the body turns); the database cannot fix that.

Attitudes are body->NED matrices referenced to **magnetic** north (the engine
treats the resulting yaw as a magnetic heading); :meth:`FieldDatabase.add`
converts true-north attitudes when given the declination.

Matching uses field *direction* (the angle between unit vectors), so a
database recorded at one place stays usable where only |B| differs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.core.geometry import FloatArray, dcm_to_quaternion, quaternion_to_dcm


@dataclass(frozen=True, slots=True)
class FieldMatch:
    """How trustworthy one database lookup is.

    ``nearest_deg``: angle between the measured field direction and the closest
    entry; ``spread_deg``: largest rotation between the interpolated attitude and
    the entries whose field direction is about as close (large = ambiguous);
    ``ok`` when the match is close enough and unambiguous (see the database's limits).
    """

    ok: bool
    nearest_deg: float
    spread_deg: float
    neighbours: int
    reason: str = ""


def _rot_z(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class FieldDatabase:
    """Recorded (field direction, attitude) pairs with nearest-neighbour interpolation.

    ``k`` neighbours are blended. A match is good when the nearest entry is within
    ``max_match_deg`` and every entry about as close in field direction agrees
    with the result to within ``max_spread_deg + max_gain * (its field angle)``:
    ``max_gain`` is the largest attitude change per degree of field-direction
    change a one-to-one map may show (4 = the rotation axis at least ~15 deg
    from the field).
    """

    def __init__(
        self,
        *,
        k: int = 3,
        max_match_deg: float = 5.0,
        max_spread_deg: float = 10.0,
        max_gain: float = 4.0,
    ) -> None:
        if k < 1:
            raise ValueError("k must be >= 1")
        if not (max_match_deg > 0 and max_spread_deg > 0 and max_gain > 0):
            raise ValueError("limits must be positive")
        self.k = k
        self.max_match_deg = max_match_deg
        self.max_spread_deg = max_spread_deg
        self.max_gain = max_gain
        self._dirs = np.empty((0, 3))
        self._quats = np.empty((0, 4))
        self._pending_dirs: list[FloatArray] = []
        self._pending_quats: list[FloatArray] = []
        self.rejected = (
            0  #: entries refused by :meth:`add` (non-finite, zero field, not a rotation)
        )

    @classmethod
    def from_field_model(
        cls, field_ned_G: npt.ArrayLike, attitudes: npt.ArrayLike, **kwargs: float
    ) -> FieldDatabase:
        """A database computed rather than recorded: ``R.T @ B_ned`` for each attitude.

        Use it when the constraint is known analytically (e.g. all attitudes of a
        body spinning about a known axis) and the field is known (WMM). Field and
        attitudes share one NED frame; for the magnetic-north attitudes the engine
        expects, give the field in magnetic axes (north = horizontal field, east = 0).
        """
        R = np.asarray(attitudes, dtype=np.float64)
        if R.ndim != 3 or R.shape[1:] != (3, 3):
            raise ValueError(f"attitudes must be (N, 3, 3), got {R.shape}")
        B = np.asarray(field_ned_G, dtype=np.float64)
        db = cls(**kwargs)  # type: ignore[arg-type]
        db.add(np.swapaxes(R, 1, 2) @ B, R)
        return db

    def __len__(self) -> int:
        return int(self._dirs.shape[0]) + len(self._pending_dirs)

    def add(
        self, mag_G: npt.ArrayLike, attitude: npt.ArrayLike, *, declination_deg: float | None = None
    ) -> int:
        """Record one pair ((3,), (3, 3)) or a batch ((N, 3), (N, 3, 3)); returns how many were kept.

        ``mag_G`` is the *calibrated* field in body axes (what the engine reports as
        ``mag_G``). ``declination_deg`` given means the attitudes are referenced to
        true north and are turned to magnetic. Bad rows are dropped and counted in
        :attr:`rejected`; a shape mismatch raises ``ValueError``.
        """
        m = np.asarray(mag_G, dtype=np.float64)
        R = np.asarray(attitude, dtype=np.float64)
        if m.shape == (3,) and R.shape == (3, 3):
            m, R = m[np.newaxis], R[np.newaxis]
        if m.ndim != 2 or m.shape[1] != 3 or R.shape != (m.shape[0], 3, 3):
            raise ValueError(
                f"mag_G (N, 3) and attitude (N, 3, 3) expected, got {m.shape} and {R.shape}"
            )
        if declination_deg is not None:
            if not math.isfinite(declination_deg):
                raise ValueError("declination_deg must be finite")
            R = _rot_z(-math.radians(declination_deg)) @ R
        norms = np.linalg.norm(m, axis=1)
        good = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(R), axis=(1, 2)) & (norms > 0)
        orth = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) < 1e-6
        good &= orth & (np.linalg.det(np.where(np.isfinite(R), R, 0.0)) > 0)
        kept = 0
        for i in np.flatnonzero(good):
            self._pending_dirs.append(m[i] / norms[i])
            self._pending_quats.append(np.array(dcm_to_quaternion(R[i])))
            kept += 1
        self.rejected += int(m.shape[0] - kept)
        return kept

    def _consolidate(self) -> None:
        if self._pending_dirs:
            self._dirs = np.vstack([self._dirs, np.array(self._pending_dirs)])
            self._quats = np.vstack([self._quats, np.array(self._pending_quats)])
            self._pending_dirs.clear()
            self._pending_quats.clear()

    def attitude_from_field(self, mag_G: npt.ArrayLike) -> tuple[FloatArray, FieldMatch]:
        """Body->NED attitude (3, 3) for a calibrated body-axis field, and the match quality.

        Never returns NaN: an empty database, a zero or non-finite field give the
        identity with ``ok=False`` and the reason.
        """
        self._consolidate()
        m = np.asarray(mag_G, dtype=np.float64).reshape(3)
        n = float(np.linalg.norm(m))
        if self._dirs.shape[0] == 0:
            return np.eye(3), FieldMatch(False, math.inf, math.inf, 0, "empty database")
        if not (math.isfinite(n) and n > 0.0):
            return np.eye(3), FieldMatch(False, math.inf, math.inf, 0, "no field")
        u = m / n
        cosines = self._dirs @ u
        k = min(self.k, cosines.shape[0])
        idx = np.argpartition(-cosines, k - 1)[:k] if k < cosines.shape[0] else np.arange(k)
        idx = idx[np.argsort(-cosines[idx])]
        nearest_deg = math.degrees(math.acos(max(-1.0, min(1.0, float(cosines[idx[0]])))))
        w = self._weights(self._dirs[idx], u)
        q = self._quats[idx].copy()
        q[np.sum(q * q[0], axis=1) < 0] *= -1.0  # one hemisphere before averaging
        qm = w @ q
        qm /= np.linalg.norm(qm)
        # Ambiguity: every entry whose field direction is about as close as the
        # neighbours' must also have about the same attitude. A smooth one-to-one
        # map moves the attitude at most max_gain times the field direction; a fold
        # (two attitudes, one field direction) breaks that.
        cap = math.cos(math.radians(min(180.0, nearest_deg + self.max_match_deg)))
        cand = np.flatnonzero(cosines >= cap)
        if cand.size > 512:  # bounded work per frame
            cand = cand[np.argsort(-cosines[cand])[:512]]
        field_deg = np.degrees(np.arccos(np.clip(cosines[cand], -1.0, 1.0)))
        rot_deg = np.degrees(2.0 * np.arccos(np.clip(np.abs(self._quats[cand] @ qm), 0.0, 1.0)))
        excess = rot_deg - self.max_gain * field_deg
        spread_deg = float(rot_deg.max())
        reason = ""
        if nearest_deg > self.max_match_deg:
            reason = f"nearest entry {nearest_deg:.1f} deg away: database too sparse here"
        elif float(excess.max()) > self.max_spread_deg:
            reason = (
                f"entries with this field direction disagree by {spread_deg:.1f} deg: ambiguous"
            )
        return quaternion_to_dcm(qm), FieldMatch(
            not reason, nearest_deg, spread_deg, int(k), reason
        )

    @staticmethod
    def _weights(dirs: FloatArray, u: FloatArray) -> FloatArray:
        """Blend weights (sum 1, >= 0) that best reproduce ``u`` from the neighbours' directions.

        An affine least-squares fit handles a neighbour curve (1 DOF) or patch
        (2 DOF) alike; a small pull towards inverse-distance weights settles the
        directions the neighbours do not span.
        """
        k = dirs.shape[0]
        if k == 1:
            return np.ones(1)
        d = np.linalg.norm(dirs - u, axis=1)
        # An exact hit takes all the weight (and avoids dividing by zero).
        w0 = (d < 1e-12).astype(np.float64) if float(d.min()) < 1e-12 else 1.0 / d
        w0 /= w0.sum()
        A = dirs.T  # (3, k)
        mu = 1e-6 + 1e-3 * float(np.mean(d)) ** 2
        # minimise |A w - u|^2 + mu |w - w0|^2 subject to sum(w) = 1 (KKT system)
        H = A.T @ A + mu * np.eye(k)
        rhs = A.T @ u + mu * w0
        K = np.zeros((k + 1, k + 1))
        K[:k, :k] = 2.0 * H
        K[:k, k] = 1.0
        K[k, :k] = 1.0
        b = np.concatenate([2.0 * rhs, [1.0]])
        try:
            w = np.linalg.solve(K, b)[:k]
        except np.linalg.LinAlgError:
            return w0
        w = np.clip(w, 0.0, None)
        s = float(w.sum())
        return w / s if s > 0 and math.isfinite(s) else w0
