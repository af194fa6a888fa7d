"""``bench accuracy --e2e``: the daemon itself, calibrated through the MAVLink ArduPilot flow.

For each shake level a real ``compass-bridge run`` is started as a subprocess
on its built-in simulated compass (``device.port = "sim"``, ``sim.motion =
"tumble"``, ``sim.shake_g``, frames at ``rate_hz``), with a MAVLink
``udpin`` endpoint on 127.0.0.1 and a temporary state directory. A pymavlink
ground station (:func:`bridge.tools.calibrate.run_mavlink`, what
``compass-bridge calibrate --mavlink`` runs) sends ``DO_START_MAG_CAL``,
follows MAG_CAL_PROGRESS and STATUSTEXT (counting the "slower / steadier"
warnings), takes the MAG_CAL_REPORT and sends ``DO_ACCEPT_MAG_CAL``; the
daemon saves the calibration it accepted.

That calibration is then scored held still at random attitudes on the very
same simulated unit (``make_firmware(seed)``, the unit the daemon's ``sim``
port draws) beside the floor -- the unit's true parameters -- on the same
frames, with the heading error the calibrate tool announced from the
report's fitness. Real time: about a minute per shake level.
"""

from __future__ import annotations

import math
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.handheld import TARGET_SHAKE_G
from benchmarks.procstat import free_port, wait_until
from benchmarks.scoring import (
    bar_targets,
    estimate_target,
    ratio_apart,
    score_held,
    target,
)
from bridge.calibration.fits.handheld import tilted_attitudes
from bridge.sim.physics import DEFAULT_LOCATION

FLOOR = "floor"
BRIDGE = "bridge"


@dataclass(frozen=True, slots=True)
class E2eConfig:
    """Shake levels and the daemon's set-up."""

    shakes_g: tuple[float, ...] = (0.0, 0.05, 0.1)
    seed: int = 1
    rate_hz: float = 50.0
    holds: int = 60  #: held attitudes (the target's figure)
    hold_s: float = 0.5
    max_tilt_deg: float = 60.0
    location: tuple[float, float, float] = DEFAULT_LOCATION
    timeout_s: float = 240.0  #: one calibration, start to report


def _config_text(state: Path, port: int, shake_g: float, cfg: E2eConfig) -> str:
    lat, lon, alt = cfg.location
    return (
        f'[device]\nport = "sim"\nrate_hz = {int(cfg.rate_hz)}\n'
        f'[mavlink]\nendpoints = ["udpin:127.0.0.1:{port}"]\n'
        "[zenoh]\nenabled = false\n"
        f'[storage]\ndir = "{state}"\n'
        f"[calibration]\ntimeout_s = {cfg.timeout_s}\n"
        f"[location]\nlatitude = {lat}\nlongitude = {lon}\naltitude_m = {alt}\n"
        f'[sim]\nseed = {cfg.seed}\nmotion = "tumble"\nshake_g = {shake_g}\n'
    )


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def run_condition(
    shake_g: float, cfg: E2eConfig, progress: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """One daemon, one calibration through MAVLink at ``shake_g``; the accepted one scored."""
    from bridge.app.calibration.store import CalibrationStore
    from bridge.sim.firmware import make_firmware
    from bridge.storage import StateStore
    from bridge.tools.calibrate import run_mavlink
    from bridge.tools.calreport import is_motion_warning

    out: dict[str, Any] = {"shake_g": shake_g}
    with tempfile.TemporaryDirectory(prefix="cb-e2e-") as tmp:
        state = Path(tmp) / "state"
        conf = Path(tmp) / "bridge.toml"
        port = free_port(socket.SOCK_DGRAM)
        conf.write_text(_config_text(state, port, shake_g, cfg))
        cmd = [sys.executable, "-m", "bridge", "run", "--config", str(conf)]
        texts: list[str] = []
        last: list[float] = [0.0]

        def on_progress(pct: float, missing: frozenset[int]) -> None:
            if progress is not None and pct >= last[0] + 10.0:
                last[0] = pct
                progress(f"e2e {shake_g:g} g: {pct:.0f}%")

        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            outcome = run_mavlink(
                f"udpout:127.0.0.1:{port}",
                target_system=1,
                target_component=1,
                timeout_s=cfg.timeout_s,
                accept=lambda report, samples: True,
                on_progress=on_progress,
                on_text=texts.append,
            )
            saved = outcome.accepted and wait_until((state / "calibration.json").exists, 10.0, 0.1)
        finally:
            _stop(proc)
            err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
        out["message"] = outcome.message
        out["accepted"] = bool(saved)
        out["motion_warnings"] = sum(1 for t in texts if is_motion_warning(t))
        out["report"] = outcome.report
        if not saved:
            out["daemon_log_tail"] = err[-2000:]
            return out
        calibration = CalibrationStore(StateStore(state)).load().calibration
    fw = make_firmware(cfg.seed, location=cfg.location)
    model = fw.sensor
    field = _site_field(cfg.location)
    rng = np.random.default_rng([cfg.seed, 31337, round(1000 * shake_g)])
    R = tilted_attitudes(rng, cfg.holds, cfg.max_tilt_deg)
    per_hold = max(1, round(cfg.hold_s * cfg.rate_hz))
    cals = {FLOOR: model.errors.true_calibration(), BRIDGE: calibration}
    scores = score_held(model, cals, R, per_hold, rng, field.declination_deg)
    out["held"] = {k: v.to_dict() for k, v in scores.items()}
    report = outcome.report or {}
    fitness = report.get("fitness")
    out["fitness_mG"] = float(fitness) if isinstance(fitness, int | float) else math.nan
    out["announced_deg"] = _announced(out["fitness_mG"], field)
    return out


def _site_field(location: tuple[float, float, float]) -> Any:
    from bridge.core.wmm import earth_field

    return earth_field(*location)


def _announced(fitness_mG: float, field: Any) -> float:
    from bridge.tools.calreport import heading_error_estimate_deg, horizontal_field_G

    return heading_error_estimate_deg(
        fitness_mG, horizontal_field_G(field.total_G, field.inclination_deg)
    )


def run_e2e(cfg: E2eConfig, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Every shake level of ``cfg``; JSON-ready."""
    conditions = [run_condition(s, cfg, progress) for s in cfg.shakes_g]
    return {
        "seed": cfg.seed,
        "rate_hz": cfg.rate_hz,
        "holds": cfg.holds,
        "hold_s": cfg.hold_s,
        "conditions": conditions,
    }


def check_e2e_targets(result: dict[str, Any]) -> list[dict[str, Any]]:
    """PASS/FAIL of the daemon's calibrations (as :func:`benchmarks.handheld.check_handheld_targets`)."""
    out: list[dict[str, Any]] = []
    for c in result["conditions"]:
        label = f"e2e {c['shake_g']:g} g"
        held = c.get("held")
        if held is None:  # failing beyond the bar's shake is allowed (and said)
            ok = c["shake_g"] > TARGET_SHAKE_G
            out.append(target(f"{label}: calibration accepted and saved", 0.0, 1.0, ok))
            continue
        if c["shake_g"] <= TARGET_SHAKE_G + 1e-9:
            out += bar_targets(label, held[FLOOR], held[BRIDGE])
        out.append(
            estimate_target(label, ratio_apart(c["announced_deg"], held[BRIDGE]["frame_rms_deg"]))
        )
    return out


def format_e2e(result: dict[str, Any]) -> list[str]:
    """The end-to-end table: the daemon's calibration beside the floor on the same frames."""
    lines = [
        "",
        f"end to end: `compass-bridge run` on its simulated compass (seed {result['seed']}, "
        f"{result['rate_hz']:g} Hz), ArduPilot flow over MAVLink, held still at "
        f"{result['holds']} attitudes ({result['hold_s']:g} s averages): heading RMS / max, "
        "worst roll-pitch, single-frame RMS",
        f"{'shake':>6}  {'':<8}{'RMS':>8}{'max':>7}{'x floor':>9}{'r/p max':>9}{'frame':>8}"
        f"{'fitness':>9}{'announced':>11}{'warnings':>10}",
    ]
    for c in result["conditions"]:
        held = c.get("held")
        if held is None:
            lines.append(f"{c['shake_g']:>5.2f}g  not calibrated: {c.get('message', '?')}")
            continue
        floor = held[FLOOR]
        for name in (FLOOR, BRIDGE):
            h = held[name]
            extra = ""
            if name == BRIDGE:
                extra = f"{c['fitness_mG']:>7.2f}mG{c['announced_deg']:>11.3f}{c['motion_warnings']:>10}"
            lines.append(
                f"{c['shake_g']:>5.2f}g  {name:<8}{h['rms_deg']:>8.3f}{h['max_deg']:>7.2f}"
                f"{h['rms_deg'] / floor['rms_deg']:>8.2f}x{h['tilt_max_deg']:>9.3f}"
                f"{h['frame_rms_deg']:>8.3f}{extra}"
            )
    return lines
