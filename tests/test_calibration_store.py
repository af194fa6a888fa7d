"""The calibration store keeps the calibration each change replaced (the undo of learning)."""

from __future__ import annotations

import json
from pathlib import Path

from bridge.app.calibration.store import LEARNED_SOURCE, CalibrationStore
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.storage import StateStore


def _cal(x: float) -> Calibration:
    return Calibration(mag=AffineCalibration((x, 0.01, -0.02)))


def test_each_change_keeps_what_it_replaced_and_learned_steps_share_one(tmp_path: Path) -> None:
    store = CalibrationStore(StateStore(tmp_path))
    assert store.replaced() is None  # nothing stored yet
    store.save(_cal(0.1), source="mag", accepted_unix=1.0, report={"fitness": 3.0})
    assert store.replaced() is None  # it replaced nothing stored
    store.save(_cal(0.2), source="parameters", accepted_unix=2.0, view={"COMPASS_OFS_X": -200.0})
    prev = store.replaced()
    assert prev is not None and prev.calibration == _cal(0.1) and prev.source == "mag"
    assert prev.report == {"fitness": 3.0} and prev.accepted_unix == 1.0
    # learning in three steps: the undo goes back to before the first one
    for k, x in enumerate((0.21, 0.22, 0.23)):
        store.save(_cal(x), source=LEARNED_SOURCE, accepted_unix=3.0 + k)
        prev = store.replaced()
        assert prev is not None and prev.calibration == _cal(0.2)
        assert prev.source == "parameters" and prev.view == {"COMPASS_OFS_X": -200.0}
    assert store.load().calibration == _cal(0.23) and store.load().source == LEARNED_SOURCE
    # a calibration after learning replaces the learned one (never nested)
    store.save(_cal(0.3), source="mag", accepted_unix=9.0)
    prev = store.replaced()
    assert prev is not None and prev.calibration == _cal(0.23) and prev.source == LEARNED_SOURCE
    doc = json.loads((tmp_path / "calibration.json").read_text())["payload"]
    assert "replaced" not in doc["replaced"]


def test_a_damaged_replaced_copy_is_ignored_and_the_calibration_still_loads(
    tmp_path: Path,
) -> None:
    docs = StateStore(tmp_path)
    docs.save(
        "calibration",
        {
            "calibration": _cal(0.4).to_dict(),
            "source": "mag",
            "replaced": {"calibration": {"mag": "nonsense"}, "source": "mag"},
        },
    )
    store = CalibrationStore(docs)
    assert store.load().calibration == _cal(0.4)
    assert store.replaced() is None
    # an older file: the bare calibration, no envelope
    docs.save("calibration", _cal(0.5).to_dict())
    assert store.load().calibration == _cal(0.5) and store.replaced() is None
    assert CalibrationStore(None).replaced() is None
