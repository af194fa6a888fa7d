"""The calibration watched while the vehicle works: drift detection and offset learning.

:class:`DriftMonitor` owns the running bridge's side of
:mod:`bridge.calibration.drift.estimator`. The pipeline hands it every sample
(:meth:`DriftMonitor.observe`, in the compass link's reader thread) with the
instant its frame was sampled (the pipeline's frame clock: frames the link reads
in a burst share an arrival, not an instant): one comparison per frame, and
every ``sample_period_s`` of those instants a row appended to the current
block -- a few microseconds. Every ``block_s`` the block goes to the monitor's
own thread (or, when that thread is not started -- tests, benches
-- is processed at once), which fits the windows, judges, emits the events
and applies learned offsets. Nothing here blocks the reader.

Modes (``[calibration] learn``, the MAVLink parameter ``BRG_CAL_LEARN``):

* ``off`` (0) -- nothing is watched;
* ``detect`` (1, the default) -- a hard-iron change of ``detect_mG`` or more is
  announced: ``calibration.drift`` at WARNING (a STATUSTEXT whose text says
  "drift", the change and the heading error it causes), and shown in
  :meth:`DriftMonitor.status` (the Zenoh status document, ``compass-bridge monitor``);
* ``learn`` (2) -- besides, once drift is declared, the offsets are
  re-estimated and applied in bounded steps when known well and stable, never
  while a calibration runs nor within ``quiet_s`` of a disturbed sample -- one
  whose field is not the Earth's as the fit corrects it (the pipeline's own
  flag compares with the calibration in use, which a large drift itself
  upsets). A learned calibration is applied and stored like any other, with
  source ``"learned"``; only its offsets differ from the calibration learning
  started from.

An uncalibrated unit (the identity in use) is not watched: every offset would be
"drift", and offsets alone on raw soft iron make no calibration.

Samples are kept in the terms of the *base* calibration (the one in use when
watching began): a learned step only moves the offset, so the rows of the
later calibrations are brought back by adding what was applied, and the
windows survive the steps. Any other change of the calibration or of the
mounting starts over.

Undo (:meth:`DriftMonitor.undo`; Zenoh ``cmd/calibration/undo``, MAVLink
``BRG_CAL_UNDO = 1``): back to the calibration learning started from -- the
copy the calibration store kept when the first learned step replaced it
(:meth:`~bridge.app.calibration.store.CalibrationStore.replaced`), or, without a
state directory, the one in memory. It applies only while a learned
calibration is in use, so a repeated request does nothing, and it turns
``learn`` down to ``detect`` so the offsets are not learned straight back.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from bridge.app.calibration.store import LEARNED_SOURCE, CalibrationStore
from bridge.app.settings import EngineSettings
from bridge.calibration.drift.estimator import (
    ZERO,
    DriftEstimate,
    DriftEstimator,
    DriftSettings,
    Reference,
    heading_error_deg,
    minus,
    norm,
    with_offset_change,
)
from bridge.calibration.drift.judge import DriftJudge, Verdict
from bridge.core.attitude import AttitudeSolution
from bridge.core.calibration import Calibration
from bridge.core.mounting import Mounting
from bridge.events import Event, EventBus, Severity
from bridge.types import LEARN_MODES, Vec3

log = logging.getLogger(__name__)

#: ``source`` of a learned calibration.
LEARNED = LEARNED_SOURCE
_IDENTITY = Calibration()

#: Every event kind the monitor emits.
EVENT_KINDS: tuple[str, ...] = (
    "calibration.drift",
    "calibration.drift_cleared",
    "calibration.learn_step",
    "calibration.learned",
    "calibration.learn_refused",
    "calibration.undo",
)

#: Applies a calibration: ``(calibration, source, report, view) -> problem`` ("" when applied).
ApplyCalibration = Callable[
    [Calibration, str, Mapping[str, Any] | None, Mapping[str, float] | None], str
]


@dataclass(frozen=True, slots=True)
class DriftStatus:
    """The monitor's state for status displays (read-only snapshot).

    ``state``: "off", "uncalibrated" (the identity is in use: nothing to drift
    from), "collecting" (no verdict yet), "ok", "drift" (a change is detected and
    not learned), "learning" (steps applied, not finished).
    ``change_mG`` / ``offset_change_mG`` the change left in the calibration in use
    (body axes), ``heading_error_deg`` the worst heading error it gives a level
    vehicle, ``sigma_mG`` how well the last fit knows it; ``learned_mG`` the
    offset learned since the base calibration, in ``steps`` steps.
    """

    mode: str
    state: str
    change_mG: float | None = None
    offset_change_mG: tuple[float, float, float] | None = None
    heading_error_deg: float | None = None
    sigma_mG: float | None = None
    learned_mG: float = 0.0
    steps: int = 0

    @property
    def drift(self) -> bool:
        """A change is detected and not (yet) learned away."""
        return self.state in ("drift", "learning")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        off = self.offset_change_mG
        return {
            "mode": self.mode,
            "state": self.state,
            "detected": self.drift,
            "change_mG": _round(self.change_mG, 1),
            "offset_change_mG": None if off is None else [round(v, 1) for v in off],
            "heading_error_deg": _round(self.heading_error_deg, 1),
            "sigma_mG": _round(self.sigma_mG, 2),
            "learned_mG": round(self.learned_mG, 1),
            "steps": self.steps,
        }


def _checked(mode: str) -> str:
    if mode not in LEARN_MODES:
        raise ValueError(f"mode must be one of {', '.join(LEARN_MODES)}, got {mode!r}")
    return mode


def _round(v: float | None, digits: int) -> float | None:
    return None if v is None or not math.isfinite(v) else round(v, digits)


class _Block:
    """Rows gathered under one calibration and mounting (reader thread until handed over)."""

    __slots__ = ("cal", "mount", "rows", "t0")

    def __init__(self, cal: Calibration, mount: Mounting, t0: float) -> None:
        self.cal = cal
        self.mount = mount
        self.t0 = t0
        self.rows: list[tuple[float, float, float, float, float, float, float]] = []


class DriftMonitor:
    """Watches the calibration for hard-iron drift; learns it away (see the module docstring).

    ``apply`` applies and stores a calibration (the calibration controller's
    ``apply_calibration``); ``calibrating`` says whether a calibration runs;
    ``store`` is where the replaced calibration is found for :meth:`undo`;
    ``on_mode`` is told when the monitor lowers its own mode (an undo).
    Blocks are processed by the monitor's thread once :meth:`start` ran, at
    once in the reader's thread before -- or, ``deferred``, when :meth:`drain`
    is called (benchmarks timing the reader's side alone).
    """

    def __init__(
        self,
        settings: EngineSettings,
        events: EventBus,
        *,
        apply: ApplyCalibration,
        calibrating: Callable[[], bool],
        store: CalibrationStore | None = None,
        mode: str = "detect",
        config: DriftSettings | None = None,
        on_mode: Callable[[str], None] | None = None,
        deferred: bool = False,
    ) -> None:
        self.config = config if config is not None else DriftSettings()
        self._settings = settings
        self._engine = settings.engine
        self._events = events
        self._apply_calibration = apply
        self._calibrating = calibrating
        self._store = store
        self._on_mode = on_mode
        self._mode = _checked(mode)
        self._on = mode != "off"
        # reader thread
        # A frame up to 15 ms early still counts (a 10 Hz compass's jitter; a test's fast
        # simulated clock multiplies it). The frames' instants are the compass's own (the
        # pipeline's frame clock), one period apart to the ulp: at 0.9 the ninth frame at
        # 100 Hz sat on the gate, and rounding kept it or the tenth. At 0.85 no device rate
        # puts a frame within 5 ms of it (100 Hz: every ninth frame; 50, 20, 10 Hz: 0.1 s).
        self._period = 0.85 * self.config.sample_period_s
        self._block_s = self.config.block_s
        self._due = -math.inf
        self._block: _Block | None = None
        # worker
        self._queue: queue.SimpleQueue[_Block | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._deferred = deferred
        self._lock = threading.RLock()  # the estimator state, steps and undo
        self._recent = DriftEstimator(self.config)
        self._long = DriftEstimator(self.config, self.config.long_window_s)
        self._judge = DriftJudge(self.config)
        self._base: Calibration | None = None
        self._mount: Mounting | None = None
        self._current: Calibration | None = None  # what the monitor last saw or applied
        self._learned: dict[int, tuple[Calibration, Vec3]] = {}
        self._applied: Vec3 = ZERO
        self._steps = 0
        self.errors = 0  #: blocks whose processing failed (logged once)
        self._status = DriftStatus(mode, "off" if mode == "off" else "collecting")

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> None:
        """Process blocks in the monitor's own thread from now on."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="drift-monitor", daemon=True)
            self._thread.start()

    def close(self, timeout: float) -> None:
        """Stop the thread within about ``timeout`` seconds (blocks still queued are dropped)."""
        t, self._thread = self._thread, None
        if t is not None:
            self._queue.put(None)
            t.join(timeout)
            if t.is_alive():
                log.error("drift monitor did not stop within %.1f s", timeout)

    # -- mode and status -----------------------------------------------------------------

    @property
    def mode(self) -> str:
        """``off``, ``detect`` or ``learn``."""
        return self._mode

    def set_mode(self, mode: str) -> None:
        """Change the mode (BRG_CAL_LEARN); ``off`` forgets what was gathered."""
        _checked(mode)
        with self._lock:
            if mode == self._mode:
                return
            self._mode = mode
            self._on = mode != "off"
            if mode == "off":
                self._block = None
                self._forget(None, None)
            self._status = self._make_status(None, None)

    def status(self) -> DriftStatus:
        """The latest state (cheap, any thread)."""
        return self._status

    # -- the per-frame hook (reader thread) ----------------------------------------------

    def observe(self, a: AttitudeSolution, t: float, saturated: bool = False) -> None:
        """One sample from the pipeline (the link's reader thread; a comparison per frame)."""
        if t < self._due or not self._on:  # (off: not even the sample times are kept)
            return
        self._due = t + self._period
        if saturated or a.degraded or self._calibrating():
            self._block = None  # a calibration's tumble (or a gap) is nothing to fit
            return
        engine = self._engine
        cal, mount = engine.calibration, engine.mounting
        b = self._block
        if b is None or b.cal is not cal or b.mount is not mount:
            b = self._block = _Block(cal, mount, t)
        h, g = a.mag_G, a.accel_g
        b.rows.append((t, h[0], h[1], h[2], g[0], g[1], g[2]))
        if t - b.t0 >= self._block_s:
            self._block = None
            if self._deferred or self._thread is not None:
                self._queue.put(b)
            else:
                self._process(b)

    # -- the worker --------------------------------------------------------------------

    def drain(self) -> int:
        """Process the blocks waiting now, in the caller's thread; how many there were."""
        n = 0
        while True:
            try:
                b = self._queue.get_nowait()
            except queue.Empty:
                return n
            if b is not None:
                self._process(b)
                n += 1

    def _run(self) -> None:
        while True:
            b = self._queue.get()
            if b is None:
                return
            self._process(b)

    def _process(self, b: _Block) -> None:
        try:
            with self._lock:
                if self._on:
                    self._evaluate(b)
        except Exception:
            self.errors += 1
            if self.errors == 1:
                log.exception("drift monitor: a block failed (further failures counted)")

    def _evaluate(self, b: _Block) -> None:
        applied = self._applied_for(b.cal, b.mount)
        if applied is None:  # a calibration or mounting the monitor did not make: start over
            self._forget(b.cal, b.mount)
            applied = ZERO
        if b.cal == _IDENTITY:
            # Never calibrated: every offset is "drift", and learning offsets alone on raw
            # soft iron and gains would make no calibration. A calibration comes first.
            self._status = DriftStatus(self._mode, "uncalibrated")
            return
        rows = np.asarray(b.rows, dtype=np.float64)
        rows[:, 1:4] += applied  # back to the base calibration's terms
        self._recent.add(rows)
        self._long.add(rows)
        ref = self._settings.reference
        reference = (
            Reference.from_total_dip(ref.total_G, ref.dip_deg) if ref is not None else Reference()
        )
        recent = self._recent.estimate(reference)
        long = self._long.estimate(reference)
        outlier = (
            max(e.outlier_t for e in (recent, long) if e is not None)
            if (recent or long)
            else -math.inf
        )
        quiet = float(rows[-1, 0]) - outlier >= self.config.quiet_s
        learn = self._mode == "learn" and not self._calibrating()
        v = self._judge.judge(recent, long, self._applied, learn=learn, quiet=quiet)
        if v.cut_before is not None:
            self._long.cut(v.cut_before)
        # the status first: whoever hears an event and asks finds it already told
        self._status = self._make_status(v, recent, stepped=False)
        self._announce(v, recent, long)
        if v.step_G is not None and long is not None and self._step(v.step_G, long):
            self._status = self._make_status(v, recent, stepped=True)

    def _applied_for(self, cal: Calibration, mount: Mounting) -> Vec3 | None:
        if mount is not self._mount or self._base is None:
            return None
        if cal is self._base:
            return ZERO
        known = self._learned.get(id(cal))
        return known[1] if known is not None and known[0] is cal else None

    def _forget(self, base: Calibration | None, mount: Mounting | None) -> None:
        self._recent.reset()
        self._long.reset()
        self._judge.reset()
        self._base = self._current = base
        self._mount = mount
        self._learned.clear()
        self._applied = ZERO
        self._steps = 0

    # -- verdicts -------------------------------------------------------------------------

    def _announce(
        self, v: Verdict, recent: DriftEstimate | None, long: DriftEstimate | None
    ) -> None:
        if v.detected and v.drift_G is not None and recent is not None:
            size = 1000.0 * norm(v.drift_G)
            err = heading_error_deg(v.drift_G, recent.horizontal_G)
            self._emit(
                "calibration.drift",
                f"Compass drift {size:.0f}mG, heading err {err:.0f}deg",
                Severity.WARNING,
                offset_change_mG=[round(1000.0 * x, 1) for x in v.drift_G],
                change_mG=round(size, 1),
                heading_error_deg=round(err, 1),
                sigma_mG=round(1000.0 * recent.sigma_G, 2),
                mode=self._mode,
            )
        elif v.cleared and not v.learned:
            self._emit("calibration.drift_cleared", "Compass drift cleared", Severity.NOTICE)
        if v.refused:
            self._emit(
                "calibration.learn_refused",
                f"Drift too large to learn: {v.refused}"[:50],
                Severity.WARNING,
                reason=v.refused,
            )
        if v.learned:
            total = 1000.0 * norm(self._applied)
            self._emit(
                "calibration.learned",
                f"Drift learned: offsets moved {total:.0f}mG",
                Severity.NOTICE,
                learned_mG=round(total, 1),
                steps=self._steps,
                residual_mG=None if long is None else round(1000.0 * long.sigma_G, 2),
            )

    def _step(self, step_G: Vec3, est: DriftEstimate) -> bool:
        """Apply one learned step (worker thread, lock held); whether it was applied."""
        base, current = self._base, self._current
        if base is None or self._settings.calibration is not current:
            return False  # changed meanwhile by someone else: the next block starts over
        total = (
            self._applied[0] + step_G[0],
            self._applied[1] + step_G[1],
            self._applied[2] + step_G[2],
        )
        cal = with_offset_change(base, self._mount.matrix() if self._mount else np.eye(3), total)
        self._learned[id(cal)] = (cal, total)
        report = {
            "method": LEARNED,
            "offset_change_mG": [round(1000.0 * x, 2) for x in total],
            "step_mG": round(1000.0 * norm(step_G), 2),
            "sigma_mG": round(1000.0 * est.sigma_G, 2),
            "steps": self._steps + 1,
        }
        problem = self._apply_calibration(cal, LEARNED, report, None)
        if problem:
            del self._learned[id(cal)]
            log.warning("drift: learned offsets not applied: %s", problem)
            return False
        self._applied, self._current = total, cal
        self._steps += 1
        self._emit(
            "calibration.learn_step",
            f"Drift: offsets moved {1000.0 * norm(step_G):.0f}mG",
            Severity.INFO,
            step_mG=[round(1000.0 * x, 2) for x in step_G],
            learned_mG=round(1000.0 * norm(total), 1),
        )
        return True

    def _make_status(
        self, v: Verdict | None, est: DriftEstimate | None, *, stepped: bool = False
    ) -> DriftStatus:
        if self._mode == "off":
            return DriftStatus("off", "off")
        state = self._judge.state
        if state != "collecting" and self._mode == "learn" and self._judge.learning:
            state = "learning"
        learned = 1000.0 * norm(self._applied)
        if v is None or v.drift_G is None or est is None:
            old = self._status
            return DriftStatus(
                self._mode,
                state,
                old.change_mG,
                old.offset_change_mG,
                old.heading_error_deg,
                old.sigma_mG,
                learned,
                self._steps,
            )
        left = minus(v.drift_G, v.step_G) if stepped and v.step_G is not None else v.drift_G
        return DriftStatus(
            self._mode,
            state,
            1000.0 * norm(left),
            (1000.0 * left[0], 1000.0 * left[1], 1000.0 * left[2]),
            heading_error_deg(left, est.horizontal_G),
            1000.0 * est.sigma_G,
            learned,
            self._steps,
        )

    def _emit(self, kind: str, text: str, severity: Severity, **data: Any) -> None:
        self._events.emit(Event(kind, text, severity, data))

    # -- undo ------------------------------------------------------------------------------

    def undo(self) -> tuple[bool, str]:
        """Back to the calibration learning started from; ``(done, what happened)``.

        Only while a learned calibration is in use (a repeated request finds none and
        does nothing). ``learn`` is turned down to ``detect`` (and ``on_mode`` told).
        """
        with self._lock:
            target = self._undo_target()
            if target is None:
                text = "Nothing learned to undo"
                self._emit("calibration.undo", text, Severity.NOTICE, done=False)
                return False, text
            cal, source, report, view = target
            problem = self._apply_calibration(cal, source, report, view)
            if problem:
                self._emit(
                    "calibration.undo", "Undo failed", Severity.WARNING, done=False, error=problem
                )
                return False, f"undo failed: {problem}"
            lowered = self._mode == "learn"
            if lowered:
                self.set_mode("detect")
            self._emit(
                "calibration.undo",
                "Learned offsets undone",
                Severity.NOTICE,
                done=True,
                source=source,
                mode=self._mode,
            )
        if lowered and self._on_mode is not None:
            self._on_mode("detect")
        return True, f"back to the {source} calibration; learning set to detect"

    def _undo_target(
        self,
    ) -> tuple[Calibration, str, Mapping[str, Any] | None, Mapping[str, float] | None] | None:
        in_use = self._settings.calibration
        if self._store is not None and self._store.documents is not None:
            stored = self._store.load()
            prev = self._store.replaced()
            if stored.source == LEARNED and stored.calibration == in_use and prev is not None:
                return prev.calibration, prev.source, prev.report, prev.view
        base = self._base
        if base is not None and self._steps > 0 and in_use is self._current:
            return base, "restored", None, None
        return None
