"""Small helpers shared by test modules (``from helpers import ...``)."""

from __future__ import annotations

import math
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import settings

from bridge.app.calibration.store import CalibrationStore
from bridge.core.attitude import tilt_compensated_heading
from bridge.core.calibration import Calibration
from bridge.core.geometry import axis_angle_to_dcm, euler_to_dcm
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.core.wmm import EarthField
from bridge.sim.firmware import Firmware
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


def random_attitudes(rng: np.random.Generator, n: int, max_tilt_deg: float) -> np.ndarray:
    """Random heading, tilt uniform over the cap up to ``max_tilt_deg`` (as the benchmark)."""
    out = np.empty((n, 3, 3))
    cos_lo = math.cos(math.radians(max_tilt_deg))
    for i in range(n):
        yaw, az = rng.uniform(0.0, 2.0 * math.pi, 2)
        tilt = math.acos(rng.uniform(cos_lo, 1.0))
        axis = (math.cos(az), math.sin(az), 0.0)
        out[i] = axis_angle_to_dcm(axis, tilt) @ euler_to_dcm(0.0, 0.0, yaw)
    return out


def heading_errors(
    fw: Firmware, cal: Calibration, R: np.ndarray, seed: int, field: EarthField
) -> np.ndarray:
    """Heading error (deg) of ``cal`` on fresh physics samples of ``fw``'s unit at attitudes
    R, in ``field`` (its declination turns the true heading into the magnetic one)."""
    s = fw.sensor.sample(R, np.random.default_rng(seed))
    ok = ~s.saturated
    truth = np.degrees(np.arctan2(R[ok, 1, 0], R[ok, 0, 0])) - field.declination_deg
    mag = cal.mag.apply(mag_counts_to_gauss(s.mag_counts[ok]))
    acc = cal.accel.apply(acc_counts_to_g(s.acc_counts[ok]))
    _, _, h = tilt_compensated_heading(mag, acc)
    return np.asarray((h - truth + 180.0) % 360.0 - 180.0)


def cli_env(tmp_path: Path) -> dict[str, str]:
    """The environment a ``compass-bridge`` child runs in: this one's, its state under
    ``tmp_path`` -- never the machine's (STATE_DIRECTORY) nor the user's (XDG_STATE_HOME,
    ``run --simulate``'s) -- and its log on stderr, not the journal's stream."""
    env = dict(os.environ)
    env["STATE_DIRECTORY"] = str(tmp_path / "state")
    env["XDG_STATE_HOME"] = str(tmp_path / "xdg")
    env.pop("JOURNAL_STREAM", None)
    return env


def run_cli(tmp_path: Path, *args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    """``python -m bridge ARGS`` in ``tmp_path`` (:func:`cli_env`), run to its end within
    ``timeout`` s: its exit code, stdout and stderr."""
    return subprocess.run(
        [sys.executable, "-m", "bridge", *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=cli_env(tmp_path),
        timeout=timeout,
    )


def png_size(path: Path) -> tuple[int, int]:
    """A PNG file's (width, height) from its IHDR chunk; fails on anything else."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    assert data[12:16] == b"IHDR"
    w, h = struct.unpack(">II", data[16:24])
    return w, h
