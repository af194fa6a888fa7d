"""``python -m benchmarks drift``: hard-iron drift detection and online learning, in figures.

Each simulated unit (its errors drawn from a seed) drives
(:class:`~bridge.sim.drive.Drive`: turns, +-15 deg roll and pitch, the
centripetal and along-track acceleration of a vehicle) with its true
calibration in use. The frames go through the attitude engine to the drift
monitor (:class:`~bridge.app.calibration.drift.DriftMonitor`, processing each block at
once) exactly as in the daemon; its learned steps are applied to the engine.

* **change**: the hard iron changes by ``size`` mG (a random direction, sensor
  axes) ``warmup_s`` into the drive. Reported: when ``calibration.drift``
  came with ``learn = "detect"`` (seconds after the change; the bar is 90 s for
  20 mG and more), and on the same frames with ``learn = "learn"`` the
  learning steps and the heading error on held attitudes (random heading,
  tilt up to 60 deg) of the old calibration, of the calibration in use
  ``learn_s`` (3 min) after the change, and of the changed unit's true
  calibration -- the *floor* -- on the very same frames.
* **false alarms**: ``fa_minutes`` of driving per unit with a good
  calibration (the true one, the best fit of a simulated tumble, and a rough
  one -- soft iron off by 0.5 %, offsets by 1.5 mG): drift events per hour,
  and the learning steps taken.
* **magnets**: a magnet going by (peaks of 0.1-1 G at 1 m, 1 m/s) once a
  minute: a disturbance, not drift.
* **cost**: the per-frame cost of the pipeline's hook (:meth:`DriftMonitor.observe`)
  and the worker's cost per block.
"""

from __future__ import annotations

import argparse
import logging
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from benchmarks.figures import finish, result_options
from benchmarks.scoring import HeldScore, positive_int, score_held, target
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.pipeline import Pipeline
from bridge.app.settings import EngineSettings
from bridge.calibration.drift.estimator import DriftSettings
from bridge.calibration.fits.handheld import tilted_attitudes
from bridge.calibration.fits.methods import BEST, CalibrationData, calibrate
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.core.wmm import EarthField, earth_field
from bridge.events import Event, EventBus
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.sim.drive import Drive
from bridge.sim.motion import Tumble
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors, magnet_pass
from bridge.types import FloatArray

DETECT_BAR_S = 90.0  #: a change of DETECT_BAR_MG or more is announced within this
DETECT_BAR_MG = 20.0
LEARN_BAR_MG = 40.0  #: after this change and LEARN_S of driving ...
LEARN_RMS_DEG = 0.3  #: ... the heading is back to this RMS
LEARN_MAX_DEG = 0.8  #: ... and this worst case, tilt up to 60 deg


@dataclass(frozen=True, slots=True)
class DriftBenchConfig:
    """What the benchmark runs."""

    units: int = 4
    seed: int = 1
    sizes_mG: tuple[float, ...] = (10.0, 20.0, 40.0, 80.0)
    rate_hz: float = 10.0
    warmup_s: float = 120.0
    learn_s: float = 180.0
    fa_minutes: float = 30.0
    fa_units: int = 2
    magnet_minutes: float = 10.0
    holds: int = 200
    hold_frames: int = 20
    max_tilt_deg: float = 60.0


@dataclass(slots=True)
class Drive1:
    """One drive of one unit through the monitor: what happened, in drive time."""

    events: list[tuple[float, Event]] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)
    calibrations: list[tuple[float, Calibration]] = field(default_factory=list)

    def first(self, kind: str, after: float = -math.inf) -> float | None:
        """Time of the first event of ``kind`` at or after ``after``."""
        return next((t for t, e in self.events if e.kind == kind and t >= after), None)

    def count(self, kind: str) -> int:
        """Events of ``kind``."""
        return sum(1 for _, e in self.events if e.kind == kind)

    def in_use_at(self, t: float, start: Calibration) -> Calibration:
        """The calibration in use at drive time ``t``."""
        cal = start
        for tc, c in self.calibrations:
            if tc <= t:
                cal = c
        return cal


class Unit:
    """A simulated unit on a drive, frames on demand (vectorised physics, seeded)."""

    def __init__(self, seed: int, rate_hz: float, field: EarthField) -> None:
        self.seed = seed
        self.rate_hz = rate_hz
        self.field = field
        self.errors = UnitErrors.draw(np.random.default_rng(seed))
        self.model = SensorModel(self.errors, field.ned_G)
        self.drive = Drive(seed)
        self._rng = np.random.default_rng([seed, 0xD71F])

    def frames(
        self,
        t0: float,
        t1: float,
        model: SensorModel | None = None,
        extra_ned_G: FloatArray | None = None,
    ) -> tuple[FloatArray, Any]:
        """Drive times in [t0, t1) and the physics' sample at each (counts, saturation)."""
        ts = np.arange(t0, t1, 1.0 / self.rate_hz)
        R = self.drive.attitudes(ts)
        acc = self.drive.linear_accs_ned_g(ts)
        m = model if model is not None else self.model
        return ts, m.sample(R, self._rng, acc, extra_ned_G)

    def fitted_calibration(self) -> Calibration:
        """The best method's fit of a 90 s tumble: a good calibration, not a perfect one."""
        rng = np.random.default_rng([self.seed, 0xF17])
        tumble = Tumble(self.seed, reference_ned=self.field.ned_G)
        ts = np.arange(0.0, 90.0, 1.0 / self.rate_hz)
        s = self.model.sample(tumble.attitudes(ts), rng)
        data = CalibrationData(
            mag_counts_to_gauss(s.mag_counts),
            acc_counts_to_g(s.acc_counts),
            s.saturated,
            reference=self.field,
            accel_calibration=self.errors.true_calibration().accel,
        )
        return calibrate(BEST, data).calibration

    def rough_calibration(self) -> Calibration:
        """The true calibration spoiled as a hurried hand-held fit would be: soft iron off by
        up to 0.5 % per element, offsets by up to 1.5 mG (heading errors of a few tenths)."""
        rng = np.random.default_rng([self.seed, 0x2B6])
        true = self.errors.true_calibration()
        e = rng.uniform(-0.005, 0.005, size=(3, 3))
        m = (np.eye(3) + (e + e.T) / 2.0) @ true.mag.matrix_array
        off = true.mag.offset_array + rng.uniform(-0.0015, 0.0015, size=3)
        return Calibration(mag=AffineCalibration.from_arrays(off, m), accel=true.accel)


class Rig:
    """The engine, its settings' writer and a drift monitor, fed frame by frame."""

    def __init__(
        self,
        cal: Calibration,
        field: EarthField,
        mode: str = "learn",
        config: DriftSettings | None = None,
    ) -> None:
        self.engine = AttitudeEngine(cal)
        self.settings = EngineSettings(self.engine, field=field)
        self.events = EventBus(history=1)
        self.now = 0.0
        self.log = Drive1()
        self.events.subscribe(lambda e: self.log.events.append((self.now, e)))
        self.monitor = DriftMonitor(
            self.settings,
            self.events,
            apply=self._apply,
            calibrating=lambda: False,
            mode=mode,
            config=config,
        )

    def _apply(self, cal: Calibration, source: str, report: Any, view: Any) -> str:
        self.settings.update_calibration(cal, source)
        self.log.steps.append(self.now)
        self.log.calibrations.append((self.now, cal))
        return ""

    def feed(self, ts: FloatArray, s: Any) -> None:
        """Frames through the engine to the monitor, as the pipeline does."""
        solve, observe = self.engine.solve_counts, self.monitor.observe
        mc, ac, sat = s.mag_counts.tolist(), s.acc_counts.tolist(), s.saturated.tolist()
        for i, t in enumerate(ts.tolist()):
            self.now = t
            m, a = mc[i], ac[i]
            observe(solve(m[0], m[1], m[2], a[0], a[1], a[2]), t, sat[i])


# -- the runs --------------------------------------------------------------------------


def _random_change(seed: int, size_mG: float) -> FloatArray:
    v = np.random.default_rng([seed, 0xC4A]).normal(size=3)
    return np.asarray(v / np.linalg.norm(v) * size_mG / 1000.0, dtype=np.float64)


def _score(
    cfg: DriftBenchConfig, unit: Unit, model: SensorModel, cals: dict[str, Calibration]
) -> dict[str, HeldScore]:
    rng = np.random.default_rng([unit.seed, 0x5C0])
    R = tilted_attitudes(rng, cfg.holds, cfg.max_tilt_deg)
    return score_held(model, cals, R, cfg.hold_frames, rng, unit.field.declination_deg)


def run_change(
    cfg: DriftBenchConfig, seed: int, size_mG: float, field: EarthField
) -> dict[str, Any]:
    """One unit, one change: detection time (``detect``), learning and the heading errors
    before and after it (``learn``), both on the very same frames."""
    unit = Unit(seed, cfg.rate_hz, field)
    start = unit.errors.true_calibration()
    changed = unit.model.with_hard_iron_change(_random_change(seed, size_mG))
    t_change = cfg.warmup_s
    t_end = t_change + cfg.learn_s
    frames = [unit.frames(0.0, t_change), unit.frames(t_change, t_end, changed)]
    watch, rig = Rig(start, field, mode="detect"), Rig(start, field, mode="learn")
    for part in frames:
        watch.feed(*part)
        rig.feed(*part)
    detected = watch.log.first("calibration.drift", t_change)
    log = rig.log
    learned = log.first("calibration.learned", t_change)
    cals = {
        "floor": changed.errors.true_calibration(),
        "before": start,
        "learned": log.in_use_at(t_end, start),
    }
    scores = _score(cfg, unit, changed, cals)
    early = [t for t, e in watch.log.events + log.events if e.kind == "calibration.drift"]
    return {
        "seed": seed,
        "size_mG": size_mG,
        "detected_s": None if detected is None else detected - t_change,
        "false_before": sum(1 for t in early if t < t_change),
        "steps": len([t for t in log.steps if t >= t_change]),
        "learned_s": None if learned is None else learned - t_change,
        "scores": {k: v.to_dict() for k, v in scores.items()},
    }


#: The good calibrations of the false-alarm runs.
GOOD_CALIBRATIONS = ("true", "fitted", "rough")


def run_false_alarms(
    cfg: DriftBenchConfig, seed: int, field: EarthField, kind: str
) -> dict[str, Any]:
    """A long drive with a good calibration (``kind``: the unit's true one, the best fit of a
    tumble, or a rough one): drift events, and learning steps."""
    unit = Unit(seed, cfg.rate_hz, field)
    cal = {
        "true": unit.errors.true_calibration,
        "fitted": unit.fitted_calibration,
        "rough": unit.rough_calibration,
    }[kind]()
    rig = Rig(cal, field)
    total = 60.0 * cfg.fa_minutes
    chunk = 300.0
    t = 0.0
    while t < total:
        rig.feed(*unit.frames(t, min(total, t + chunk)))
        t += chunk
    learned = rig.log.in_use_at(total, cal)
    moved = 1000.0 * float(np.linalg.norm(learned.mag.offset_array - cal.mag.offset_array))
    cals = {"floor": unit.errors.true_calibration(), "before": cal, "learned": learned}
    scores = _score(cfg, unit, unit.model, cals)
    return {
        "seed": seed,
        "calibration": kind,
        "hours": total / 3600.0,
        "alarms": rig.log.count("calibration.drift"),
        "steps": len(rig.log.steps),
        "learned_mG": moved,
        "scores": {k: v.to_dict() for k, v in scores.items()},
    }


def run_magnets(cfg: DriftBenchConfig, seed: int, field: EarthField) -> dict[str, Any]:
    """A drive with a magnet going by once a minute (peaks 0.1, 0.3, 1 G): no drift."""
    unit = Unit(seed, cfg.rate_hz, field)
    cal = unit.errors.true_calibration()
    rig = Rig(cal, field)
    total = 60.0 * cfg.magnet_minutes
    ts = np.arange(0.0, total, 1.0 / cfg.rate_hz)
    extra = np.zeros((len(ts), 3))
    rng = np.random.default_rng([seed, 0x3A6])
    peaks = (0.1, 0.3, 1.0)
    passes = 0
    for k, at in enumerate(np.arange(90.0, total - 30.0, 60.0)):
        d = rng.normal(size=3)
        extra += magnet_pass(ts, float(at), peaks[k % len(peaks)], d)
        passes += 1
    rig.feed(*unit.frames(0.0, total, extra_ned_G=extra))
    return {
        "seed": seed,
        "passes": passes,
        "alarms": rig.log.count("calibration.drift"),
        "steps": len(rig.log.steps),
    }


def measure_cost(field: EarthField, seconds: float = 60.0, repeats: int = 5) -> dict[str, float]:
    """What the drift monitor costs at 100 Hz: the pipeline's per-frame time with and without
    its hook (the best of ``repeats`` runs each, the same frames), the hook alone, and the
    worker's time per block."""
    unit = Unit(7, 100.0, field)
    ts, s = unit.frames(0.0, seconds)
    mc, ac = s.mag_counts.tolist(), s.acc_counts.tolist()
    frames = [AttitudeFrame(i % 65536, 0.0, 0.0, 0.0, m[0], m[1], m[2], a[0], a[1], a[2], Flags(0))
              for i, (m, a) in enumerate(zip(mc, ac, strict=True))]  # fmt: skip
    times = ts.tolist()
    best = {False: math.inf, True: math.inf}
    hook = math.inf
    blocks, worker = 0, 0.0
    for _ in range(repeats):
        for hooked in (False, True):
            engine = AttitudeEngine(unit.errors.true_calibration())
            events = EventBus()
            # deferred: the blocks wait on the queue, as they do for the daemon's worker
            mon = DriftMonitor(EngineSettings(engine, field=field), events,
                               apply=lambda *a: "", calibrating=lambda: False, deferred=True)  # fmt: skip
            pipe = Pipeline(engine, events, feed=lambda f, t: None, calibrating=lambda: False,
                            observe=mon.observe if hooked else None)  # fmt: skip
            t0 = time.perf_counter()
            for f, t in zip(frames, times, strict=True):
                pipe.process(f, t)
            best[hooked] = min(best[hooked], (time.perf_counter() - t0) / len(frames) * 1e6)
            if hooked:
                t1 = time.perf_counter()
                blocks = mon.drain()
                worker = (time.perf_counter() - t1) / max(1, blocks) * 1e3
        sols = [engine.solve_counts(*m, *a) for m, a in zip(mc, ac, strict=True)]
        mon = DriftMonitor(EngineSettings(engine, field=field), EventBus(),
                           apply=lambda *a: "", calibrating=lambda: False, deferred=True)  # fmt: skip
        observe = mon.observe
        t0 = time.perf_counter()
        for a, t in zip(sols, times, strict=True):
            observe(a, t, False)
        hook = min(hook, (time.perf_counter() - t0) / len(sols) * 1e6)
    return {
        "frames": float(len(frames)),
        "pipeline_us_per_frame": best[False],
        "pipeline_hooked_us_per_frame": best[True],
        "observe_us_per_frame": hook,
        "worker_ms_per_block": worker,
        "worker_cpu_pct": 100.0 * worker / 1e3 / DriftSettings().block_s,
    }


def run(
    cfg: DriftBenchConfig, progress: Callable[[float, str], None] | None = None
) -> dict[str, Any]:
    """Every part of the benchmark; a JSON-ready result with its targets."""
    field = earth_field(*DEFAULT_LOCATION)
    seeds = [cfg.seed + k for k in range(cfg.units)]
    jobs = len(cfg.sizes_mG) * len(seeds) + 3 * cfg.fa_units + cfg.units + 1
    done = 0

    def tick(note: str) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done / jobs, note)

    changes = []
    for size in cfg.sizes_mG:
        for seed in seeds:
            changes.append(run_change(cfg, seed, size, field))
            tick(f"{size:g} mG, unit {seed}")
    alarms = []
    for kind in GOOD_CALIBRATIONS:
        for seed in seeds[: cfg.fa_units]:
            alarms.append(run_false_alarms(cfg, seed, field, kind))
            tick(f"false alarms, {kind} calibration, unit {seed}")
    magnets = []
    for seed in seeds:
        magnets.append(run_magnets(cfg, seed, field))
        tick(f"magnets, unit {seed}")
    cost = measure_cost(field)
    tick("cost")
    result: dict[str, Any] = {
        "config": _config_dict(cfg),
        "changes": changes,
        "false_alarms": alarms,
        "magnets": magnets,
        "cost": cost,
    }
    result["targets"] = targets(result)
    return result


def _config_dict(cfg: DriftBenchConfig) -> dict[str, Any]:
    return {name: getattr(cfg, name) for name in cfg.__dataclass_fields__}


def targets(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The targets, PASS/FAIL."""
    out = []
    big = [c for c in result["changes"] if c["size_mG"] >= DETECT_BAR_MG]
    worst = max(
        (c["detected_s"] if c["detected_s"] is not None else math.inf for c in big),
        default=math.nan,
    )
    out.append(
        target(
            f"changes >= {DETECT_BAR_MG:g} mG detected within {DETECT_BAR_S:g} s (worst, s)",
            worst,
            DETECT_BAR_S,
            worst <= DETECT_BAR_S,
        )
    )
    n = sum(a["alarms"] for a in result["false_alarms"]) + sum(
        c["false_before"] for c in result["changes"]
    )
    out.append(target("false alarms with a good calibration (count)", n, 0, n == 0))
    mags = sum(m["alarms"] for m in result["magnets"])
    out.append(target("drift alarms for passing magnets (count)", mags, 0, mags == 0))
    learn = [c for c in result["changes"] if c["size_mG"] == LEARN_BAR_MG]
    if learn:
        rms = max(c["scores"]["learned"]["rms_deg"] for c in learn)
        mx = max(c["scores"]["learned"]["max_deg"] for c in learn)
        out.append(
            target(f"{LEARN_BAR_MG:g} mG learned: heading RMS (worst unit, deg)", rms,
                   LEARN_RMS_DEG, rms <= LEARN_RMS_DEG)
        )  # fmt: skip
        out.append(
            target(f"{LEARN_BAR_MG:g} mG learned: heading max (worst unit, deg)", mx,
                   LEARN_MAX_DEG, mx <= LEARN_MAX_DEG)
        )  # fmt: skip
    cost = result["cost"]
    # The hook alone is the work the pipeline adds; the two pipeline runs bound it from
    # the outside, within their timing noise (a few tenths of a microsecond).
    added = max(
        cost["observe_us_per_frame"],
        cost["pipeline_hooked_us_per_frame"] - cost["pipeline_us_per_frame"],
    )
    out.append(
        target("pipeline time the drift monitor adds (us per frame, 100 Hz)", added, 5.0,
               added <= 5.0)
    )  # fmt: skip
    return out


# -- the report --------------------------------------------------------------------------


def _fmt(v: float | None, spec: str = ".1f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def format_report(result: dict[str, Any]) -> str:
    """The tables, as text."""
    cfg = result["config"]
    lines = [
        f"bench drift: {cfg['units']} units driving (turns, +-15 deg roll/pitch, "
        f"{cfg['rate_hz']:g} Hz); change {cfg['warmup_s']:g} s in, scored "
        f"{cfg['learn_s']:g} s after it on held attitudes up to {cfg['max_tilt_deg']:g} deg tilt",
        "",
        "change  detected after s        learned after s   heading error RMS/max deg",
        "  mG    median   worst  missed  median  steps     before        learned      floor",
    ]
    for size in cfg["sizes_mG"]:
        rows = [c for c in result["changes"] if c["size_mG"] == size]
        det = [c["detected_s"] for c in rows if c["detected_s"] is not None]
        lrn = [c["learned_s"] for c in rows if c["learned_s"] is not None]
        missed = sum(1 for c in rows if c["detected_s"] is None)

        def agg(name: str, rows: list[dict[str, Any]] = rows) -> str:
            rms = statistics.fmean(c["scores"][name]["rms_deg"] for c in rows)
            mx = max(c["scores"][name]["max_deg"] for c in rows)
            return f"{rms:5.2f}/{mx:5.2f}"

        lines.append(
            f"{size:5.0f}  {_fmt(statistics.median(det) if det else None):>7} "
            f"{_fmt(max(det) if det else None):>7} {missed:5d}/{len(rows)}  "
            f"{_fmt(statistics.median(lrn) if lrn else None):>6} "
            f"{statistics.fmean(c['steps'] for c in rows):6.1f}   "
            f"{agg('before')}  {agg('learned')}  {agg('floor')}"
        )
    lines.append(
        "  (RMS: mean over units; max: worst unit. floor = the changed unit's true calibration)"
    )
    lines.append("")
    for cal in GOOD_CALIBRATIONS:
        rows = [a for a in result["false_alarms"] if a["calibration"] == cal]
        if not rows:
            continue
        hours = sum(a["hours"] for a in rows)
        alarms = sum(a["alarms"] for a in rows)

        def worst(name: str, rows: list[dict[str, Any]] = rows) -> str:
            rms = max(a["scores"][name]["rms_deg"] for a in rows)
            return f"{rms:.2f}/{max(a['scores'][name]['max_deg'] for a in rows):.2f}"

        lines.append(
            f"false alarms, {cal} calibration: {alarms} in {hours:.1f} h of driving "
            f"({alarms / hours:.2f}/h); learning: {sum(a['steps'] for a in rows)} steps, "
            f"offsets moved up to {max(a['learned_mG'] for a in rows):.1f} mG, heading "
            f"{worst('before')} -> {worst('learned')} deg (floor {worst('floor')})"
        )
    mags = result["magnets"]
    lines.append(
        f"magnets going by: {sum(m['passes'] for m in mags)} passes (0.1-1 G), "
        f"{sum(m['alarms'] for m in mags)} drift alarms, {sum(m['steps'] for m in mags)} learning steps"
    )
    c = result["cost"]
    lines.append(
        f"cost at 100 Hz: pipeline {c['pipeline_us_per_frame']:.2f} us/frame without the "
        f"hook, {c['pipeline_hooked_us_per_frame']:.2f} with it; the hook alone "
        f"{c['observe_us_per_frame']:.2f} us/frame; worker {c['worker_ms_per_block']:.1f} ms "
        f"per {DriftSettings().block_s:g} s block ({c['worker_cpu_pct']:.2f} % of a core)"
    )
    lines.append("")
    lines.append("targets:")
    for t in result["targets"]:
        v = t["value"]
        lines.append(
            f"  {'PASS' if t['pass'] else 'FAIL'}  {t['name']}: {_fmt(float(v), '.2f')} "
            f"(limit {t['limit']:g})"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: prints the tables, optionally JSON; exit 1 if a target fails."""
    d = DriftBenchConfig()
    p = argparse.ArgumentParser(
        prog="python -m benchmarks drift",
        description="Hard-iron drift: detection time, false alarms, heading before/after learning.",
    )
    p.add_argument("--units", type=positive_int, default=d.units, help="simulated units")
    p.add_argument("--seed", type=int, default=d.seed, help="first unit seed")
    p.add_argument(
        "--sizes", type=float, nargs="+", default=list(d.sizes_mG), metavar="MG",
        help="hard-iron changes, mG (default 10 20 40 80)",
    )  # fmt: skip
    p.add_argument(
        "--fa-minutes", type=float, default=d.fa_minutes, help="driving per false-alarm unit"
    )
    p.add_argument("--fa-units", type=int, default=d.fa_units, help="units for false alarms")
    result_options(p, "progress bar")
    args = p.parse_args(list(argv) if argv is not None else None)
    cfg = DriftBenchConfig(
        units=args.units,
        seed=args.seed,
        sizes_mG=tuple(args.sizes),
        fa_minutes=args.fa_minutes,
        fa_units=max(0, args.fa_units),
    )
    from bridge.tools.progress import Progress

    # the events are the figures (and a turn's acceleration "disturbs" the pipeline's flag)
    logging.getLogger("bridge.events").setLevel(logging.ERROR)

    with Progress("drift", 1.0, enabled=args.progress, tick=True) as bar:
        result = run(cfg, lambda frac, note: bar.update(frac, note=note))
    return finish(format_report(result), result, args.json)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
