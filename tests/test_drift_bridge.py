"""Drift detection and learning in the application: parameters, store, status, undo.

A daemon is built on a state directory but not started: the test hands the
pipeline a simulated drive's frames itself (drive time as frame time), so
minutes of driving take a fraction of a second and nothing waits.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.drift import Unit
from bridge.app.calibration.drift import LEARNED
from bridge.app.calibration.store import CalibrationStore
from bridge.config import config_from_mapping
from bridge.core.wmm import earth_field
from bridge.daemon import Daemon, build_daemon
from bridge.events import Event
from bridge.link.transport import SimTransport
from bridge.protocol.device import Received
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.sim.firmware import make_firmware
from bridge.sim.physics import DEFAULT_LOCATION
from bridge.storage import StateStore
from bridge.zenoh import schema
from bridge.zenoh.monitor import FleetView
from bridge.zenoh.services import calibration_key, calibration_state, run_calibration_command

FIELD = earth_field(*DEFAULT_LOCATION)
SEED = 5
CHANGE_G = (-0.02, 0.03, 0.015)


def daemon(state: Path) -> tuple[Daemon, list[Event]]:
    lat, lon, alt = DEFAULT_LOCATION
    cfg = config_from_mapping(
        {
            "device": {"port": "sim"},
            "storage": {"dir": str(state)},
            "location": {"latitude": lat, "longitude": lon, "altitude_m": alt},
            "zenoh": {"enabled": False},
            "mavlink": {"endpoints": []},
        },
        env={},
        hostname="t",
    )
    d = build_daemon(cfg, transport=SimTransport(make_firmware(SEED, location=DEFAULT_LOCATION)))
    log: list[Event] = []  # the calibration's events (a turn's acceleration "disturbs" too)
    d.bridge.events.subscribe(
        lambda e: log.append(e) if e.kind.startswith("calibration.") else None
    )
    return d, log


class Drive:
    """The unit's frames, through the pipeline, continuing in time across calls."""

    def __init__(self) -> None:
        self.unit = Unit(SEED, 10.0, FIELD)
        self.changed = self.unit.model.with_hard_iron_change(CHANGE_G)
        self.t = 0.0
        self.seq = 0

    def __call__(self, d: Daemon, seconds: float, changed: bool = True) -> None:
        ts, s = self.unit.frames(self.t, self.t + seconds, self.changed if changed else None)
        for t, (mx, my, mz), (ax, ay, az) in zip(
            ts, s.mag_counts.tolist(), s.acc_counts.tolist(), strict=True
        ):
            f = AttitudeFrame(self.seq % 65536, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, Flags(0))
            d.bridge.pipeline.on_frame(Received(f, float(t)))
            self.seq += 1
        self.t += seconds


def status_doc(d: Daemon) -> dict[str, object]:
    cal = calibration_state(d.bridge.services)
    # the output's cheap change key names the same state and source (a learned one too)
    assert calibration_key(d.bridge.services) == (cal["state"], cal["source"])
    doc = schema.status_doc(
        d.bridge.status(),
        frame_rate_hz=10.0,
        calibration=cal,
        publisher={},
        t_unix=0.0,
        uptime_s=1.0,
    )
    return json.loads(schema.dumps(doc))  # as a subscriber receives it


def test_drift_is_shown_learned_stored_kept_across_a_restart_and_undone(tmp_path: Path) -> None:
    state = tmp_path / "state"
    drive = Drive()
    good = drive.unit.errors.true_calibration()
    CalibrationStore(StateStore(state)).save(good, source="mag", accepted_unix=1.0)
    d, log = daemon(state)
    assert d.bridge.engine.calibration == good
    assert d.bridge.params.get("BRG_CAL_LEARN") == 1 and d.bridge.drift.mode == "detect"

    # detect (the default): the warning, the status document, the monitor's flag
    drive(d, 120.0, changed=False)
    assert not schema.drift_detected(status_doc(d))
    drive(d, 90.0)
    assert [e.kind for e in log] == ["calibration.drift"]
    doc = status_doc(d)
    schema.validate(doc, schema.STATUS)
    calibration = doc["calibration"]
    assert isinstance(calibration, dict)
    drift = calibration["drift"]
    assert drift["state"] == "drift" and drift["mode"] == "detect"
    assert abs(drift["change_mG"] - 1000.0 * np.linalg.norm(good.mag.matrix_array @ CHANGE_G)) < 3
    assert schema.drift_detected(doc)
    view = FleetView()
    assert view.update("fleet/boat/compass/status", schema.dumps(doc), 0.0)
    assert "DRIFT" in view.rows(0.0)[0].flags

    # learn, switched on over MAVLink (BRG_CAL_LEARN = 2): stored as "learned"
    assert d.bridge.params.set("BRG_CAL_LEARN", 2).accepted and d.bridge.drift.mode == "learn"
    drive(d, 180.0)
    kinds = [e.kind for e in log]
    assert "calibration.learn_step" in kinds and "calibration.learned" in kinds
    assert "calibration.accepted" in kinds  # the controller applied and saved each step
    learned = d.bridge.engine.calibration
    true_now = drive.changed.errors.true_calibration()
    left = (
        1000.0 * learned.mag.matrix_array @ (true_now.mag.offset_array - learned.mag.offset_array)
    )
    assert np.linalg.norm(left) < 2.0
    stored = d.bridge.calibrations.load()
    assert stored.source == LEARNED and stored.calibration == learned
    assert d.bridge.status().calibration_source == LEARNED
    assert d.bridge.params.get("COMPASS_OFS_X") == np.float32(-1000.0 * learned.mag.offset[0])
    assert not schema.drift_detected(status_doc(d))

    # a restart keeps the learned calibration and the learning mode (a user's setting);
    # the first bridge stops first (its parameter writes are coalesced: they land by then)
    d.bridge.params.close()
    d2, log2 = daemon(state)
    assert d2.bridge.engine.calibration == learned
    assert d2.bridge.calibrations.load().source == LEARNED
    assert d2.bridge.drift.mode == "learn"

    # undo over MAVLink: BRG_CAL_UNDO = 1 goes back to the calibration before learning,
    # turns learning down to detect and reads back 1 (the echo a ground station checks)
    out = d2.bridge.params.set("BRG_CAL_UNDO", 1)
    assert out.accepted
    assert d2.bridge.engine.calibration == good
    assert d2.bridge.params.get("BRG_CAL_UNDO") == 1 and d2.bridge.params.get("BRG_CAL_LEARN") == 1
    assert d2.bridge.drift.mode == "detect"
    assert d2.bridge.calibrations.load().source == "mag"
    undo = [e for e in log2 if e.kind == "calibration.undo"]
    assert len(undo) == 1 and undo[0].data["done"] is True
    # ... and over Zenoh (cmd/calibration/undo): nothing learned is left to undo
    res = run_calibration_command(d2.bridge.calibrator, "undo", {}, undo=d2.bridge.drift.undo)
    assert not res.ok and "Nothing learned" in res.message
    # the undone calibration is what a third start finds
    d2.bridge.params.close()
    d3, _ = daemon(state)
    assert d3.bridge.engine.calibration == good and d3.bridge.params.get("BRG_CAL_LEARN") == 1


def test_a_bridge_without_drift_monitoring_says_so(tmp_path: Path) -> None:
    d, log = daemon(tmp_path / "state")
    assert d.bridge.params.set("BRG_CAL_LEARN", 0).accepted and d.bridge.drift.mode == "off"
    Drive()(d, 60.0)
    assert log == []
    assert calibration_state(d.bridge.services)["drift"]["state"] == "off"
    res = run_calibration_command(d.bridge.calibrator, "undo", {}, undo=None)
    assert not res.ok
