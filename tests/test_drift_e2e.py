"""End to end: the daemon on the simulated compass, a hard-iron change mid-drive, STATUSTEXT.

The simulated compass drives (:class:`~bridge.sim.drive.Drive`) on a fast
clock (simulated seconds run ``SPEED`` times faster than real ones); the
daemon starts with the unit's true calibration in its state directory; the
unit's hard iron changes 20 simulated seconds in. A ground station on a real
UDP socket must receive a STATUSTEXT at severity WARNING saying "drift".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_mavlink_rig import DEADLINE_S, FastClock, M, connect_gcs, free_port, make_config

from bridge.app.calibration.store import CalibrationStore
from bridge.daemon import build_daemon
from bridge.link.transport import SimTransport
from bridge.mavlink import MavlinkOutput, MavlinkSettings
from bridge.protocol.device import LinkState
from bridge.sim.drive import Drive
from bridge.sim.firmware import make_firmware
from bridge.sim.physics import DEFAULT_LOCATION, UnitErrors
from bridge.storage import StateStore

pytestmark = pytest.mark.integration

SPEED = 20.0  #: simulated seconds per real second (as the other fast rigs: a loaded
#: machine that starves the reader for 2 simulated seconds loses frames)
SEED = 4

pytestmark = pytest.mark.integration  # a real UDP ground station, the daemon's threads


def test_a_hard_iron_change_mid_drive_reaches_the_ground_station(tmp_path: Path) -> None:
    udp = free_port()
    # The compass runs SPEED times faster than the link's clock: every frame as it comes.
    cfg = make_config(
        tmp_path,
        mavlink={"endpoints": [f"udpin:127.0.0.1:{udp}"]},
        device={"read_bursts": False},
    )
    good = UnitErrors.draw(np.random.default_rng(SEED)).true_calibration()  # make_firmware's unit
    CalibrationStore(StateStore(cfg.storage.dir)).save(good, source="mag", accepted_unix=1.0)
    fw = make_firmware(
        SEED,
        motion=Drive(SEED),
        location=DEFAULT_LOCATION,
        hard_iron_change=((0.02, -0.025, 0.015), 20.0),  # 36 mG, 20 s into the drive
    )
    fc = FastClock(SPEED)
    daemon = build_daemon(cfg, transport=SimTransport(fw, clock=fc, sleep=fc.sleep), clock=fc)
    out = MavlinkOutput(MavlinkSettings.from_config(cfg), daemon.bridge.services)
    daemon.bridge.pipeline.set_outputs([out])
    assert daemon.bridge.engine.calibration == good
    daemon.start()
    gcs = None
    try:
        assert daemon.link.wait_state(LinkState.STREAMING, DEADLINE_S)
        gcs = connect_gcs(f"udpout:127.0.0.1:{udp}")
        gcs.wait("HEARTBEAT")
        msg = gcs.wait(
            "STATUSTEXT",
            lambda m: "drift" in m.text.lower(),
            timeout=DEADLINE_S,
        )
        assert msg.severity == M.MAV_SEVERITY_WARNING
        assert fc() - (fw.motion_epoch or 0.0) > 20.0  # after the change (timing: the bench)
        status = daemon.bridge.services.drift.status()
        assert status.state == "drift" and status.change_mG is not None
        # what the fit knows of the change by then: all of it, or its horizontal part
        truth = 1000.0 * good.mag.matrix_array @ (0.02, -0.025, 0.015)
        assert 0.9 * np.hypot(*truth[:2]) < status.change_mG < np.linalg.norm(truth) + 6.0
    finally:
        if gcs is not None:
            gcs.close()
        daemon.stop()
