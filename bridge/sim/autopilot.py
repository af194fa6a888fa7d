"""A stand-in autopilot's attitude stream: what a companion compass hears over MAVLink.

The autopilot's ATTITUDE carries its estimator's roll and pitch of the vehicle
body, stamped with its boot clock (``time_boot_ms``), and reaches the companion
some tens of milliseconds later. :class:`AutopilotAttitude` simulates exactly
that for a motion script (the *compass's* attitude, as the simulator moves it):

* the vehicle's attitude is the compass's turned back by the mounting between
  the two (``mounting``: the compass's axes in the autopilot's, a small residual
  rotation -- two boards are never bolted exactly parallel -- times the compass's
  ``AHRS_ORIENTATION`` if it has one);
* the roll and pitch are off by the estimator's error: white noise
  (``noise_deg``) plus a slowly wandering part (``wander_deg``, first-order
  Gauss-Markov with ``wander_s``): an EKF's attitude error is correlated, not white;
* its body rates (rollspeed, pitchspeed, yawspeed) are the true ones with
  ``gyro_noise_dps`` of white noise;
* each message is stamped ``time_boot_ms`` on the autopilot's clock (booted
  ``boot_s`` before the simulation's zero) and arrives ``latency_s`` plus an
  exponential jitter (``jitter_s``) later, in order (a serial link does not
  reorder); TIMESYNC answers travel the same link both ways.

Pure and seeded: :meth:`messages` lists what arrives, :meth:`timesync` answers a
request. The UDP stand-in of the integration tests sends these very values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.core.geometry import (
    dcm_to_euler,
    dcm_to_euler_batch,
    dcm_to_rotvec,
    dcm_to_rotvec_batch,
    euler_to_dcm,
)
from bridge.sim.motion import Motion
from bridge.types import FloatArray


# Not frozen, on purpose: a drive's stream is made of thousands (8 500 in the tilt bench's
# 420 s drive), and a frozen dataclass's __init__ (object.__setattr__ per field) costs five
# times plain slot stores -- as bridge.core.aligned.AttitudeSample. Read-only by contract.
@dataclass(slots=True)
class AttitudeMessage:
    """One ATTITUDE as the companion receives it (read-only by contract)."""

    arrival_s: float  #: when it arrives (the simulation's clock)
    time_boot_ms: int  #: its stamp, on the autopilot's clock
    roll: float  #: radians
    pitch: float
    yaw: float
    truth_s: float  #: the instant it describes (the simulation's clock)
    rates: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: body rates, rad/s (its gyros)


class AutopilotAttitude:
    """The attitude stream of an autopilot on the vehicle a compass is mounted in.

    ``mounting`` maps the compass's axes into the autopilot's (``v_ap = M @
    v_compass``); :meth:`random_residual` draws a realistic one.
    """

    def __init__(
        self,
        motion: Motion,
        *,
        seed: int = 0,
        rate_hz: float = 20.0,
        noise_deg: float = 0.1,
        wander_deg: float = 0.2,
        wander_s: float = 20.0,
        latency_s: float = 0.04,
        jitter_s: float = 0.01,
        boot_s: float = 123.456,
        mounting: npt.ArrayLike | None = None,
        gyro_noise_dps: float = 0.1,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        for name, v in (
            ("noise_deg", noise_deg),
            ("wander_deg", wander_deg),
            ("latency_s", latency_s),
            ("jitter_s", jitter_s),
        ):
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        self.motion = motion
        self.seed = seed
        self.rate_hz = float(rate_hz)
        self.noise_deg = float(noise_deg)
        self.wander_deg = float(wander_deg)
        self.wander_s = float(wander_s)
        self.latency_s = float(latency_s)
        self.jitter_s = float(jitter_s)
        self.boot_s = float(boot_s)
        self.gyro_noise_dps = float(gyro_noise_dps)
        self.mounting = np.eye(3) if mounting is None else np.asarray(mounting, dtype=np.float64)
        self._rng = np.random.default_rng([seed, 0xA7])
        self._link = np.random.default_rng([seed, 0x11A])
        self._wander = np.zeros(2)
        self._last_arrival = -math.inf

    @staticmethod
    def random_residual(seed: int, max_deg: float = 2.0) -> FloatArray:
        """A small random rotation (up to ``max_deg`` about a random axis): two boards'
        misalignment."""
        rng = np.random.default_rng([seed, 0x2E5])
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = math.radians(float(rng.uniform(0.5, 1.0)) * max_deg)
        from bridge.core.geometry import axis_angle_to_dcm

        return axis_angle_to_dcm(axis, angle)

    def boot_ms(self, t: float) -> int:
        """The autopilot's ``time_boot_ms`` at simulation time ``t``."""
        return int((t + self.boot_s) * 1000.0)

    def body_rates(self, t: float, h: float = 0.005) -> tuple[float, float, float]:
        """The vehicle's true body rates at ``t`` (rad/s), by a central difference."""
        Ra = np.asarray(self.motion.attitude(t - h)) @ self.mounting.T
        Rb = np.asarray(self.motion.attitude(t + h)) @ self.mounting.T
        w = dcm_to_rotvec(Ra.T @ Rb) / (2.0 * h)
        return float(w[0]), float(w[1]), float(w[2])

    def true_euler(self, t: float) -> tuple[float, float, float]:
        """The vehicle's (autopilot's body) true roll, pitch, yaw at ``t``."""
        R = np.asarray(self.motion.attitude(t)) @ self.mounting.T
        return dcm_to_euler(R)

    def _delay(self) -> float:
        return self.latency_s + (
            float(self._link.exponential(self.jitter_s)) if self.jitter_s else 0.0
        )

    def message(self, t: float) -> AttitudeMessage:
        """The ATTITUDE describing instant ``t`` (call in increasing ``t``)."""
        return self._stream(np.array([float(t)]))[0]

    def messages(self, t0: float, t1: float) -> list[AttitudeMessage]:
        """Every ATTITUDE describing an instant in ``[t0, t1)``, at the stream's rate."""
        n = math.ceil((t1 - t0) * self.rate_hz)
        return self._stream(t0 + np.arange(max(0, n)) / self.rate_hz)

    def _stream(self, ts: FloatArray, h: float = 0.005) -> list[AttitudeMessage]:
        """The messages describing the instants ``ts`` (increasing, after any before),
        all at once: each draws, in order, its wander step, its noise, its link delay and
        its gyros' noise; its body rates are a central difference (as :meth:`body_rates`)."""
        n = ts.size
        if n == 0:
            return []
        MT = self.mounting.T
        roll, pitch, yaw = dcm_to_euler_batch(self.motion.attitudes(ts) @ MT)
        Ra = self.motion.attitudes(ts - h) @ MT
        Rb = self.motion.attitudes(ts + h) @ MT
        gyro = dcm_to_rotvec_batch(np.swapaxes(Ra, 1, 2) @ Rb) / (2.0 * h)
        # Per message: wander step (2), noise (2), gyro noise (3) from one generator, in
        # that order, as one message at a time would draw them.
        k_w = 2 if self.wander_deg > 0.0 else 0
        k_n = 2 if self.noise_deg else 0
        z = self._rng.standard_normal((n, k_w + k_n + 3))
        dt = 1.0 / self.rate_hz
        err = np.zeros((n, 2))
        if k_w:
            phi = math.exp(-dt / self.wander_s)
            step = self.wander_deg * math.sqrt(1.0 - phi * phi) * z[:, :2]
            # The recursion in plain floats (the same products and sums as on the arrays,
            # without a numpy call per message: thousands a drive).
            w0, w1 = float(self._wander[0]), float(self._wander[1])
            walk = []
            for s0, s1 in step.tolist():
                w0 = phi * w0 + s0
                w1 = phi * w1 + s1
                walk.append((w0, w1))
            err = np.array(walk)
            self._wander = err[-1].copy()
        if k_n:
            err = err + self.noise_deg * z[:, k_w : k_w + 2]
        err = np.radians(err)
        delay = self.latency_s + (
            self._link.exponential(self.jitter_s, size=n) if self.jitter_s else np.zeros(n)
        )
        # In order: a message never overtakes the one before it.
        arrival = np.maximum.accumulate(np.maximum(ts + delay, self._last_arrival))
        self._last_arrival = float(arrival[-1])
        rates = gyro + math.radians(self.gyro_noise_dps) * z[:, k_w + k_n :]
        boot_ms = ((ts + self.boot_s) * 1000.0).astype(np.int64)
        r, p = (roll + err[:, 0]).tolist(), (pitch + err[:, 1]).tolist()
        return [
            AttitudeMessage(a, b, ro, pi, y, t, (g[0], g[1], g[2]))
            for a, b, ro, pi, y, t, g in zip(
                arrival.tolist(), boot_ms.tolist(), r, p, yaw.tolist(), ts.tolist(),
                rates.tolist(), strict=True,
            )
        ]  # fmt: skip

    def timesync(self, sent_s: float) -> tuple[float, int]:
        """A TIMESYNC request sent at ``sent_s``: (when the answer arrives, its ``tc1`` in
        nanoseconds on the autopilot's clock)."""
        at_autopilot = sent_s + self._delay()
        return at_autopilot + self._delay(), int((at_autopilot + self.boot_s) * 1e9)


def compass_attitude(
    vehicle_roll: float, vehicle_pitch: float, vehicle_yaw: float, mounting: npt.ArrayLike
) -> FloatArray:
    """The compass's body->NED matrix for a vehicle attitude and a mounting (``v_ap = M v_c``)."""
    return euler_to_dcm(vehicle_roll, vehicle_pitch, vehicle_yaw) @ np.asarray(mounting)
