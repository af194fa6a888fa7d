"""The companion's tilt source from the real ArduPilot: its ATTITUDE and TIMESYNC answers.

ArduPilot Rover SITL from ``../shared/autopilots/ardupilot`` (README there) stands level
at its home; its SERIAL1 (MAVLink 2, ``MAV2_EXTRA1`` = 20: ATTITUDE at 20 Hz -- the
stream group is ``MAVn_`` for MAVLink channel n in 4.7, ``SRn_`` before) talks to the
bridge's ``udpin``. The bridge runs in the companion role on a simulated compass that
rides the same level vehicle, whose accelerometer feels 0.25 g sideways from the start
and for good: its own tilt is 14 deg off, and with no quiet frame to hold on to, the
bridge alone would believe it (a steady accelerometer is a re-oriented unit) until the
autopilot is heard.

What must hold: the bridge hears ArduPilot's ATTITUDE (system 1, component 1) at the
rate asked for, lines up its ``time_boot_ms`` with ArduPilot's own TIMESYNC answers
(``GCS_MAVLINK::handle_timesync``), and while the accelerometer lies its ATTITUDE keeps
roll and pitch near ArduPilot's (level) and the heading near the truth, each sample with
TILT_SRC 1 (autopilot). A test of the real interface, not of accuracy: the compass is
ideal and SITL's rover at rest is exactly level (the accuracy figures are
``python -m benchmarks tilt``'s, with an autopilot's noise, latency and misalignment).
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from autopilots import ARDUPILOT_INSTANCES, AUTOPILOTS, ardupilot_ports, claim_instance
from test_mavlink_rig import Rig, connect_gcs, wait_until

from bridge.core.geometry import euler_to_dcm
from bridge.core.wmm import earth_field
from bridge.sim.motion import MotionBase
from bridge.sim.physics import DEFAULT_LOCATION

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ARDUPILOT = AUTOPILOTS / "ardupilot"
PARAMS = {"SERIAL1_PROTOCOL": 2, "MAV2_EXTRA1": 20, "ARMING_CHECK": 0}
YAW_DEG = 75.0  #: the compass's vehicle heading (ArduPilot's own yaw plays no part)
PUSH_G = 0.25
DECLINATION = earth_field(*DEFAULT_LOCATION).declination_deg


class PushedSideways(MotionBase):
    """Level at a fixed heading, 0.25 g towards the vehicle's right all along (eased in over
    the first 2 s): an accelerometer whose down is 14 deg off."""

    def __init__(self) -> None:
        self._R = euler_to_dcm(0.0, 0.0, math.radians(YAW_DEG))
        right = self._R @ np.array([0.0, 1.0, 0.0])
        self._right = right

    def attitude(self, t: float) -> np.ndarray:
        return self._R

    def linear_acc_ned_g(self, t: float) -> np.ndarray:
        s = min(1.0, max(0.0, t / 2.0))
        return np.asarray(PUSH_G * s * s * (3.0 - 2.0 * s) * self._right, dtype=np.float64)


@contextlib.contextmanager
def ardupilot(workdir: Path, companion_port: int) -> Iterator[subprocess.Popen[bytes]]:
    """ArduPilot Rover SITL, SERIAL1 to ``companion_port``, the rest off. Its instance (-I)
    is claimed with the same lock files the other autopilot tests use."""
    if not (ARDUPILOT / "ardurover").is_file():
        pytest.fail(f"the real ArduPilot is missing: expected it in {ARDUPILOT}")
    workdir.mkdir(parents=True, exist_ok=True)
    extra = workdir / "extra.parm"
    extra.write_text("".join(f"{k} {v:g}\n" for k, v in PARAMS.items()))
    claim = claim_instance("ardupilot", ARDUPILOT_INSTANCES, ardupilot_ports)
    n = claim.n
    console = open(workdir / "ardupilot.console", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [
            str(ARDUPILOT / "ardurover"),
            "-w",
            "-I",
            str(n),
            "--model",
            "rover",
            "--speedup",
            "1",
            "--defaults",
            f"{ARDUPILOT / 'rover.parm'},{extra}",
            "--home",
            "-35.363261,149.165230,584,120",
            "--serial0",
            "none",
            "--serial1",
            f"udpclient:127.0.0.1:{companion_port}",
            *[a for k in (2, 5, 6, 7, 8) for a in (f"--serial{k}", "none")],
        ],
        cwd=workdir,
        stdin=subprocess.DEVNULL,
        stdout=console,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5.0)
        console.close()
        claim.release()


def test_the_companion_takes_ardupilots_attitude_while_the_accelerometer_lies(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, motion=PushedSideways(), ideal=True, mavlink={"role": "companion"})
    tilt = rig.daemon.bridge.services.tilt
    assert tilt is not None
    # Alone, with no quiet frame before the push, the bridge takes the accelerometer's 14 deg.
    if rig.motion_time() < 4.0:
        rig.wait_motion_time(4.0)
    down = tilt.filter.down
    assert down is not None
    before = math.degrees(math.atan2(down[1], down[2]))
    with ardupilot(tmp_path / "ap", rig.udp_port):
        # ArduPilot heard, and its clock lined up by its TIMESYNC answers.
        assert wait_until(lambda: tilt.status()["autopilot"]["clock"] == "timesync", 30.0), (
            f"no TIMESYNC alignment with ArduPilot: {tilt.status()['autopilot']}"
        )
        start = rig.motion_time() + 3.0
        rig.wait_motion_time(start)
        g = connect_gcs(f"udpout:127.0.0.1:{rig.udp_port}")
        rig.gcss.append(g)
        ours = (rig.out.identity.system_id, rig.out.identity.component_id)
        epoch = rig.fw.motion_epoch
        assert epoch is not None
        atts: list[Any] = []
        srcs: list[int] = []
        t_end = time.monotonic() + 10.0
        while time.monotonic() < t_end:
            for m in g.collect(0.5):
                if (m.get_srcSystem(), m.get_srcComponent()) != ours:
                    continue
                kind = m.get_type()
                if kind not in ("ATTITUDE", "NAMED_VALUE_INT"):
                    continue
                if rig.out._t0 + m.time_boot_ms / 1000.0 - epoch < start:
                    continue  # a frame from before ArduPilot had its say
                if kind == "ATTITUDE":
                    atts.append(m)
                elif m.name == "TILT_SRC":
                    srcs.append(int(m.value))
        st = tilt.status()["autopilot"]
    print(f"ArduPilot: {st}")
    assert st["heard"] and st["rate_hz"] >= 15.0, st  # MAV2_EXTRA1 = 20
    assert abs(before) > 10.0, f"roll {before:.1f} deg before ArduPilot was heard"
    # TILT_SRC beside an ATTITUDE on a change and once a second: 1 (autopilot) all along
    assert len(atts) >= 50 and len(srcs) >= 5 and set(srcs) == {1}, srcs
    roll = [math.degrees(a.roll) for a in atts]
    pitch = [math.degrees(a.pitch) for a in atts]
    yaw_err = [
        (math.degrees(a.yaw) - (YAW_DEG - DECLINATION) + 180.0) % 360.0 - 180.0 for a in atts
    ]
    rms = float(np.sqrt(np.mean(np.square(yaw_err))))
    print(
        f"roll {np.mean(roll):.2f} pitch {np.mean(pitch):.2f} deg; heading {rms:.2f} deg RMS "
        f"(before ArduPilot was heard: {before:.1f} deg of roll)"
    )
    # The accelerometer alone says 14 deg of roll; ArduPilot's level vehicle says none.
    assert max(abs(r) for r in roll) < 1.5 and max(abs(p) for p in pitch) < 1.5
    assert rms < 1.0
