"""How the accuracy benchmarks score a calibration: heading (and tilt) error against the truth.

Shared by ``bench accuracy`` (:mod:`benchmarks.accuracy`), its hand-held
conditions (:mod:`benchmarks.handheld`) and its end-to-end mode
(:mod:`benchmarks.e2e`). The truth is the simulator's: the attitude each
frame was sampled at. Every calibration scored in one call sees the very same
frames, so the *floor* -- the unit's true parameters, what noise and
quantisation alone leave -- is comparable with each method.

* the attitudes: ``bridge.calibration.fits.handheld.tilted_attitudes`` (random heading,
  tilt uniform over a cap; the hand-held fit predicts its errors over the same);
* :func:`heading_errors` -- single frames;
* :func:`score_held` -- the unit held still at each attitude for a number of
  frames: the error of the averaged reading (what a person checks against a
  reference), of single frames, and the worst roll/pitch error.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.core.attitude import tilt_compensated_heading
from bridge.core.calibration import Calibration
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.sim.physics import SensorModel
from bridge.types import BoolArray, FloatArray


def magnetic_heading_deg(R: FloatArray, declination_deg: float) -> FloatArray:
    """True magnetic heading of body->NED matrices: yaw minus declination, in degrees."""
    return np.degrees(np.arctan2(R[:, 1, 0], R[:, 0, 0])) - declination_deg


def wrap180(a: FloatArray) -> FloatArray:
    """Angles (degrees) into [-180, 180)."""
    return np.asarray((a + 180.0) % 360.0 - 180.0, dtype=np.float64)


def heading_errors(
    cal: Calibration, mag_G: FloatArray, acc_g: FloatArray, truth_deg: FloatArray
) -> FloatArray:
    """Heading error (deg) of ``cal`` on raw nominal frames whose true heading is ``truth_deg``."""
    _, _, h = tilt_compensated_heading(cal.mag.apply(mag_G), cal.accel.apply(acc_g))
    return wrap180(h - truth_deg)


def still_means(
    model: SensorModel, R: FloatArray, per_stop: int, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Mean nominal mag/acc of ``per_stop`` frames at each attitude; False where all saturated."""
    s = model.sample(np.repeat(R, per_stop, axis=0), rng)
    mag = mag_counts_to_gauss(s.mag_counts).reshape(-1, per_stop, 3)
    acc = acc_counts_to_g(s.acc_counts).reshape(-1, per_stop, 3)
    good = ~s.saturated.reshape(-1, per_stop)
    n = good.sum(axis=1)
    w = good[:, :, None] / np.maximum(n, 1)[:, None, None]
    return (mag * w).sum(axis=1), (acc * w).sum(axis=1), n > 0


@dataclass(frozen=True, slots=True)
class HeldScore:
    """Errors of one calibration at held attitudes (degrees).

    ``rms_deg``/``max_deg``: heading of the averaged reading of each hold;
    ``frame_rms_deg``: heading of single frames; ``tilt_max_deg``: the worst
    roll or pitch error of the averaged readings.
    """

    rms_deg: float
    max_deg: float
    frame_rms_deg: float
    tilt_max_deg: float
    n: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "rms_deg": self.rms_deg,
            "max_deg": self.max_deg,
            "frame_rms_deg": self.frame_rms_deg,
            "tilt_max_deg": self.tilt_max_deg,
            "n": self.n,
        }


def _rms(e: FloatArray) -> float:
    return float(np.sqrt(np.mean(e * e))) if e.size else math.nan


def score_held(
    model: SensorModel,
    cals: dict[str, Calibration],
    R: FloatArray,
    per_hold: int,
    rng: np.random.Generator,
    declination_deg: float,
) -> dict[str, HeldScore]:
    """Hold the unit still at each attitude ``R`` for ``per_hold`` frames; score every calibration.

    The same frames for every entry of ``cals`` (put the floor among them).
    Saturated frames are left out of the averages and of the frame scores.
    """
    s = model.sample(np.repeat(R, per_hold, axis=0), rng)
    mag = mag_counts_to_gauss(s.mag_counts)
    acc = acc_counts_to_g(s.acc_counts)
    ok = ~s.saturated
    good = ok.reshape(-1, per_hold)
    keep = good.any(axis=1)
    w = good[:, :, None] / np.maximum(good.sum(axis=1), 1)[:, None, None]
    mag_m = (mag.reshape(-1, per_hold, 3) * w).sum(axis=1)[keep]
    acc_m = (acc.reshape(-1, per_hold, 3) * w).sum(axis=1)[keep]
    Rk = R[keep]
    truth = magnetic_heading_deg(Rk, declination_deg)
    truth_frames = np.repeat(magnetic_heading_deg(R, declination_deg), per_hold)[ok]
    g_true = Rk[:, 2, :]  # R^T (0, 0, 1): the body's gravity vector
    roll_t = np.arctan2(g_true[:, 1], g_true[:, 2])
    pitch_t = -np.arcsin(np.clip(g_true[:, 0], -1.0, 1.0))
    out: dict[str, HeldScore] = {}
    for name, cal in cals.items():
        roll, pitch, h = tilt_compensated_heading(cal.mag.apply(mag_m), cal.accel.apply(acc_m))
        e = wrap180(h - truth)
        droll = np.abs(wrap180(np.degrees(roll - roll_t)))
        dpitch = np.degrees(np.abs(pitch - pitch_t))
        ef = heading_errors(cal, mag[ok], acc[ok], truth_frames)
        out[name] = HeldScore(
            rms_deg=_rms(e),
            max_deg=float(np.max(np.abs(e))) if e.size else math.nan,
            frame_rms_deg=_rms(ef),
            tilt_max_deg=float(np.max(np.maximum(droll, dpitch))) if e.size else math.nan,
            n=int(e.size),
        )
    return out


#: The accuracy bar: heading RMS within this factor of the floor on the same frames ...
RATIO_LIMIT = 1.3
#: ... and the worst heading within this many degrees of the floor's worst.
MAX_MARGIN_DEG = 0.15
#: A reported heading error is within this factor of the measured one.
ESTIMATE_FACTOR = 2.0


def positive_int(text: str) -> int:
    """An argparse type: an integer of at least 1 (unit, sample and hold counts)."""
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def target(name: str, value: float, limit: float, passed: bool) -> dict[str, Any]:
    """One PASS/FAIL line of a benchmark's targets."""
    return {"name": name, "value": value, "limit": limit, "pass": bool(passed)}


def bar_targets(label: str, floor: dict[str, Any], got: dict[str, Any]) -> list[dict[str, Any]]:
    """Heading RMS within 1.3x and max within +0.15 deg of the floor (held-score dicts)."""
    rms_limit = RATIO_LIMIT * floor["rms_deg"]
    max_limit = floor["max_deg"] + MAX_MARGIN_DEG
    return [
        target(f"{label}: heading RMS <= {RATIO_LIMIT}x floor", got["rms_deg"], rms_limit,
               got["rms_deg"] <= rms_limit),
        target(f"{label}: heading max <= floor + {MAX_MARGIN_DEG} deg", got["max_deg"], max_limit,
               got["max_deg"] <= max_limit),
    ]  # fmt: skip


def ratio_apart(a: float, b: float) -> float:
    """How many times apart two positive figures are (>= 1; inf if either is not positive)."""
    return max(a, b) / min(a, b) if a > 0.0 and b > 0.0 else math.inf


def estimate_target(label: str, ratio: float, of: str = "") -> dict[str, Any]:
    """A reported heading error within 2x of the measured one (``of``: e.g. "worst unit")."""
    what = f"{of}, ratio" if of else "ratio"
    return target(
        f"{label}: announced heading error within {ESTIMATE_FACTOR:g}x of the measured ({what})",
        ratio,
        ESTIMATE_FACTOR,
        ratio <= ESTIMATE_FACTOR,
    )
