"""Small helpers shared by test modules (``from helpers import ...``)."""

from __future__ import annotations

from pathlib import Path

from bridge.app.calibration.store import CalibrationStore
from bridge.calibration.model import Calibration
from bridge.storage import StateStore


def load_calibration(directory: str | Path) -> tuple[Calibration, str]:
    """The calibration the daemon would start with from ``directory``, and how the status
    line names it ("stored", "stored (previous copy)", "none (identity)")."""
    stored = CalibrationStore(StateStore(directory)).load()
    return stored.calibration, stored.description
