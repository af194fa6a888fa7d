"""A host for the simulated firmware in simulated time, for the firmware's tests.

The firmware is sans-I/O: :class:`Host` steps time, polls, decodes what arrives with the
*host* decoder and records when each sentence appeared; :func:`firmware` builds a unit
(ideal by default) in :data:`FIELD`. Every wait is bounded in simulated time.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from bridge.protocol.gmr import AttitudeFrame, CommandFrame, GmrDecoder, GmrFrame, encode
from bridge.sim.firmware import Firmware
from bridge.sim.flash import Flash
from bridge.sim.motion import Motion, Still
from bridge.sim.physics import SensorModel, UnitErrors

FIELD = np.array([0.2152, 0.0138, 0.4333])  # NED gauss, about Zurich
DECL_DEG = math.degrees(math.atan2(FIELD[1], FIELD[0]))
FACTORY_FIELDS = "2458.0,2458.0,2458.0,1.0000,1.0000,1.0000,2458.0,2458.0,2949.5"


class Host:
    """Drives a firmware in simulated time and records ``(time, frame)`` as decoded."""

    def __init__(self, fw: Firmware, t0: float = 0.0, step: float = 0.001) -> None:
        self.fw = fw
        self.t = t0
        self.step = step
        self.dec = GmrDecoder("host")
        self.log: list[tuple[float, GmrFrame]] = []
        self.raw = bytearray()

    def send(self, cmd: CommandFrame | bytes) -> float:
        data = cmd if isinstance(cmd, bytes) else encode(cmd)
        self.fw.receive(data, self.t)
        return self.t

    def run(self, dt: float, step: float | None = None) -> list[tuple[float, GmrFrame]]:
        """Advance ``dt`` seconds; return what arrived meanwhile."""
        step = step or self.step
        start = len(self.log)
        end = self.t + dt
        while self.t < end - 1e-12:
            self.t = min(end, self.t + step)
            self._poll()
        return self.log[start:]

    def _poll(self) -> None:
        data = self.fw.poll(self.t)
        if not data:  # most polls (every ms, frames at 10 Hz): nothing came, nothing to decode
            return
        self.raw += data
        for f in self.dec.feed(data):
            self.log.append((self.t, f))

    def wait_for(self, pred: Callable[[GmrFrame], bool], timeout: float) -> tuple[float, GmrFrame]:
        """Run until a frame matching ``pred`` arrives (simulated deadline ``timeout``)."""
        start = len(self.log)
        end = self.t + timeout
        while self.t < end:
            self.t = min(end, self.t + self.step)
            self._poll()
            for t, f in self.log[start:]:
                if pred(f):
                    return t, f
            start = len(self.log)
        raise AssertionError(f"nothing matched within {timeout} s")

    def command(self, cmd: CommandFrame, timeout: float = 2.0) -> tuple[float, GmrFrame]:
        """Send ``cmd``; return (latency, answer)."""
        t0 = self.send(cmd)
        t, f = self.wait_for(cmd.is_answer, timeout)
        return t - t0, f

    def frames(self, since: float = -math.inf) -> list[tuple[float, AttitudeFrame]]:
        return [(t, f) for t, f in self.log if isinstance(f, AttitudeFrame) and t >= since]


def firmware(
    motion: Motion | None = None,
    errors: UnitErrors | None = None,
    flash: Flash | None = None,
    seed: int = 0,
) -> Firmware:
    sensor = SensorModel(errors or UnitErrors.ideal(), FIELD)
    return Firmware(
        sensor,
        motion or Still(),
        flash or Flash(),
        np.random.default_rng(seed),
        power_on_at=0.0,
    )


def failing_flash_host(step: float) -> Host:
    """The host of an ideal unit 50 ms after power-up, polling every ``step`` s; the
    unit's next flash write will fail."""
    fw = firmware()
    h = Host(fw, step=step)
    h.run(0.05)
    fw.flash.fail_next_write()
    return h


def angle_err(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)
