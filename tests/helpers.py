"""Small helpers shared by test modules (``from helpers import ...``)."""

from __future__ import annotations

import os
from pathlib import Path

from hypothesis import settings

from bridge.app.calibration.store import CalibrationStore
from bridge.calibration.model import Calibration
from bridge.storage import StateStore


def load_calibration(directory: str | Path) -> tuple[Calibration, str]:
    """The calibration the daemon would start with from ``directory``, and how the status
    line names it ("stored", "stored (previous copy)", "none (identity)")."""
    stored = CalibrationStore(StateStore(directory)).load()
    return stored.calibration, stored.description


#: Property tests run the example counts written on them when this is set (or ``CI`` is, as
#: ``.ci/run`` sets it); otherwise a third of them, so the in-memory tier stays a quick
#: loop (``README.md``). Failing examples are kept in Hypothesis's database
#: (``.hypothesis/``) and replayed first on the next run, whatever the count.
THOROUGH = bool(os.environ.get("COMPASS_BRIDGE_THOROUGH") or os.environ.get("CI"))
EVERYDAY_SHARE = 3


def examples(thorough: int) -> settings:
    """Hypothesis settings for a property test: ``thorough`` examples in CI (or with
    ``COMPASS_BRIDGE_THOROUGH=1``), a third of them in an everyday run. The explicit
    ``@example`` cases and the boundary-token tests run in full either way."""
    n = thorough if THOROUGH else max(1, thorough // EVERYDAY_SHARE)
    return settings(max_examples=n, deadline=None)
