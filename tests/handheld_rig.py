"""A simulated hand-held tumble for the tests: the frames a live calibration records, and the truth.

One unit (``UnitErrors.draw`` from the seed, at PX4 SITL's Zurich, WMM 2026)
tumbled at 45 deg/s by a hand shaking ``shake_g`` RMS per axis
(``HandShake``), sampled at ``rate_hz`` as the firmware would (noise, 12-bit
ADC). Truth comes from the simulator, never from the code under test; the
scores are the benchmark's (held still, the floor on the same frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from benchmarks.scoring import HeldScore, score_held
from bridge.calibration.fits.handheld import tilted_attitudes
from bridge.calibration.sessions.collect import MagCollector, sphere_step
from bridge.core.calibration import Calibration
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.core.wmm import EarthField, earth_field
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.sim.motion import HandShake, Tumble
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors
from bridge.types import FloatArray

FIELD: EarthField = earth_field(*DEFAULT_LOCATION, 2026.0)


@dataclass(frozen=True)
class Tumbled:
    """``seconds`` of frames: times, raw counts, nominal vectors, saturation; the unit's model."""

    t: FloatArray
    mag_counts: npt.NDArray[np.int64]
    acc_counts: npt.NDArray[np.int64]
    saturated: npt.NDArray[np.bool_]
    model: SensorModel

    @property
    def mag(self) -> FloatArray:
        return mag_counts_to_gauss(self.mag_counts)

    @property
    def acc(self) -> FloatArray:
        return acc_counts_to_g(self.acc_counts)

    @property
    def truth(self) -> Calibration:
        return self.model.errors.true_calibration()

    def frames(self) -> list[AttitudeFrame]:
        """The frames, as the decoder gives them: the counts and flags as plain ints (the
        frame's constructor then takes its fast path; the frames are the same)."""
        sat = int(Flags.SAT)
        return [
            AttitudeFrame(i % 65536, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, sat if s else 0)
            for i, ((mx, my, mz), (ax, ay, az), s) in enumerate(
                zip(
                    self.mag_counts.tolist(),
                    self.acc_counts.tolist(),
                    self.saturated.tolist(),
                    strict=True,
                )
            )
        ]


def tumble(
    seed: int,
    shake_g: float,
    *,
    seconds: float = 120.0,
    rate_hz: float = 50.0,
    dps: float = 45.0,
    errors: UnitErrors | None = None,
) -> Tumbled:
    """A (shaken) tumble of the unit drawn from ``seed`` (or of ``errors``)."""
    errs = errors if errors is not None else UnitErrors.draw(np.random.default_rng(seed))
    model = SensorModel(errs, FIELD.ned_G)
    base = Tumble(seed, dps, reference_ned=FIELD.ned_G)
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    lin = HandShake(base, shake_g, seed).shake_g(t) if shake_g > 0.0 else None
    s = model.sample(base.attitudes(t), np.random.default_rng([seed, 1]), lin)
    return Tumbled(t, s.mag_counts, s.acc_counts, s.saturated, model)


def held(
    rec: Tumbled, cals: dict[str, Calibration], *, holds: int = 200, seed: int = 7
) -> dict[str, HeldScore]:
    """Every calibration (and the floor, as ``"floor"``) held still at the same fresh attitudes."""
    rng = np.random.default_rng([seed, 99])
    R = tilted_attitudes(rng, holds, 60.0)
    all_cals = {"floor": rec.truth, **cals}
    return score_held(rec.model, all_cals, R, 25, rng, FIELD.declination_deg)


def collect(rec: Tumbled, capacity: int = 300) -> tuple[int, FloatArray, FloatArray]:
    """ArduPilot's two-step collection over the frames, as a live calibration runs it.

    Returns how many frames it took to complete and its kept samples (mag, acc):
    what the bridge used to fit before it kept the whole series.
    """
    col = MagCollector(capacity, seed=1)
    mag, acc = rec.mag, rec.acc
    end = len(rec.t)
    for i in range(len(rec.t)):
        m, a = mag[i], acc[i]
        mag_G = (float(m[0]), float(m[1]), float(m[2]))
        col.offer(mag_G, (float(a[0]), float(a[1]), float(a[2])), bool(rec.saturated[i]))
        if col.full:
            if col.step == 2:
                end = i + 1
                break
            sph = sphere_step(col.acceptor.samples)
            assert sph is not None
            col.begin_step_two(*sph)
    kept_mag, kept_acc = col.data()
    return end, kept_mag, kept_acc
