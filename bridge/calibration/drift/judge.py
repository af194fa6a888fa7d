"""Successive drift fits in, verdicts out: detected, cleared, learn a step (pure).

The judge of :mod:`bridge.calibration.drift.estimator`: no I/O, no clock (times are the
fits' own), one owner.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from bridge.calibration.drift.estimator import (
    DriftEstimate,
    DriftSettings,
    known_part,
    minus,
    norm,
    plus,
)
from bridge.types import Vec3


@dataclass(frozen=True, slots=True)
class Verdict:
    """What one pair of fits means.

    ``state`` is "collecting" (nothing known yet), "ok" or "drift"; ``drift_G`` the
    change left in the calibration in use (body axes; None without a fit);
    ``detected`` / ``cleared`` say the state changed now. ``cut_before``: the change
    began before this time -- the long window must forget the samples before it.
    ``step_G`` is a learning step to apply now, ``learned`` says learning has just
    ended (what is left is below ``learn_done_mG``), ``refused`` why a step was
    not taken (a change too large to be learned).
    """

    state: str
    drift_G: Vec3 | None = None  #: left in the calibration in use (before ``step_G``)
    detected: bool = False
    cleared: bool = False
    cut_before: float | None = None
    step_G: Vec3 | None = None
    learned: bool = False
    refused: str = ""


@dataclass(slots=True)
class _Memory:
    above: int = 0
    below: int = 0
    recent: deque[Vec3] = field(default_factory=lambda: deque(maxlen=3))
    last_step_t: float = -math.inf
    #: The offset applied when the learning under way began (None: none under way).
    #: Detection measures from there, so a change being learned is still announced.
    base: Vec3 | None = None
    refused: bool = False


class DriftJudge:
    """Successive fits in, :class:`Verdict` out (not thread-safe: one owner).

    Two fits of the same samples: ``recent`` (the last ``window_s``) judges
    *whether* the calibration drifted, ``long`` (up to ``long_window_s``) *by how
    much*, for learning. Only the part of a change a fit knows counts
    (:meth:`DriftEstimate.known`), and only fits that are ``consistent``.

    Drift is declared when the change left in the calibration in use is at least
    ``detect_mG`` (``detect_vertical_mG`` straight up or down; between the two
    on an ellipsoid), known to ``detect_sigma_mG`` and clear of the noise, in
    ``detect_evaluations`` recent fits in a row; it clears after as many below
    ``clear_mG``. When the recent fit disagrees with the long one, the change
    happened in the recent window: the long window is cut (``cut_before``), so
    its fit holds only what came after.

    Learning (``learn=True``), once drift is declared: a step -- what is
    left, at most ``learn_step_mG`` -- when the long fit, over at least
    ``window_s``, knows it to ``learn_sigma_mG`` (or to a fifth of it: bulk steps
    first, the finish once it is known well), it is at least ``learn_min_mG``
    (``learn_done_mG`` while learning) and 2.5 sigma, the last three long fits
    agree with each other and with the recent one, no disturbance is recent
    (``quiet``) and the last step is ``learn_interval_s`` old. Learning has ended
    (``learned``) when less than that is left in every direction the drive shows.
    """

    def __init__(self, settings: DriftSettings | None = None) -> None:
        self.settings = settings if settings is not None else DriftSettings()
        self.state = "collecting"
        self._m = _Memory()

    def reset(self) -> None:
        """Start over (a new calibration: nothing is known about it yet)."""
        self.state = "collecting"
        self._m = _Memory()

    @property
    def learning(self) -> bool:
        """Steps have been returned and learning has not ended yet."""
        return self._m.base is not None

    def judge(
        self,
        recent: DriftEstimate | None,
        long: DriftEstimate | None,
        applied_G: Vec3,
        *,
        learn: bool,
        quiet: bool,
    ) -> Verdict:
        """The fits of one evaluation, with the offset already applied (``applied_G``, in
        the samples' terms) since the calibration the samples are given in; ``learn``
        allows steps, ``quiet`` says no disturbance is recent.

        Only what a fit knows counts (:meth:`DriftEstimate.known`): detection looks at
        the part of the change known to ``detect_sigma_mG``.
        """
        s = self.settings
        m = self._m
        detected = cleared = False
        cut: float | None = None
        left: Vec3 | None = None
        if recent is not None:
            full = minus(recent.offset_G, m.base if m.base is not None else applied_G)
            left, sig = recent.known(full, s.detect_sigma_mG / 1000.0)
            if math.isinf(sig):
                left = None
            cut = self._change_began(recent, long)
        if recent is not None and left is not None and recent.consistent:
            k = s.detect_mG / s.detect_vertical_mG  # a vertical change counts for less
            size = 1000.0 * math.sqrt(left[0] ** 2 + left[1] ** 2 + (k * left[2]) ** 2)
            sigma = 1000.0 * sig
            if size >= s.detect_mG and size - 2.0 * sigma >= 0.5 * s.detect_mG:
                m.above, m.below = m.above + 1, 0
            elif size < s.clear_mG:
                m.above, m.below = 0, m.below + 1
            else:
                m.above = m.below = 0
            if self.state != "drift" and m.above >= s.detect_evaluations:
                self.state, detected = "drift", True
            elif self.state == "drift" and m.below >= s.detect_evaluations:
                self.state, cleared = "ok", True
            elif self.state == "collecting":
                self.state = "ok"
        step: Vec3 | None = None
        learned = False
        refused = ""
        if learn and long is not None:
            step, learned, refused = self._learn(long, recent, applied_G, quiet)
        if recent is not None and left is not None and m.base is not None:
            # what is left in the calibration in use (detection measured from the base)
            left = recent.known(minus(recent.offset_G, applied_G), s.detect_sigma_mG / 1000.0)[0]
        return Verdict(self.state, left, detected, cleared, cut, step, learned, refused)

    def _change_began(self, recent: DriftEstimate, long: DriftEstimate | None) -> float | None:
        """When the recent fit disagrees with the long one (by ``detect_mG``, three sigma;
        or the long one is garbled) the offset changed within the
        recent window -- and, a robust fit following the majority of its samples, in
        its older half: the long window must forget what came before its middle."""
        s = self.settings
        if long is None or not recent.consistent:
            return None
        if not long.consistent:  # the long window holds two offsets, the recent one one
            return recent.t - 0.5 * s.window_s
        apart, sigma = known_part(
            recent.cov + long.cov,
            minus(recent.offset_G, long.offset_G),
            3.0 * s.detect_sigma_mG / 1000.0,
        )
        size = 1000.0 * norm(apart)
        if size < max(s.detect_mG, 3000.0 * sigma):
            return None
        return recent.t - 0.5 * s.window_s

    def _learn(
        self,
        est: DriftEstimate,
        recent: DriftEstimate | None,
        applied_G: Vec3,
        quiet: bool,
    ) -> tuple[Vec3 | None, bool, str]:
        s = self.settings
        m = self._m
        if m.base is None and self.state != "drift":
            return None, False, ""  # learning follows a detection: a good calibration stays
        if not est.consistent or (recent is not None and not recent.consistent):
            return None, False, ""
        m.recent.append(est.offset_G)
        full = minus(est.offset_G, applied_G)
        # bulk steps where a fifth of the change is known, the finish to learn_sigma_mG
        rough = max(s.learn_sigma_mG, 0.2 * 1000.0 * norm(full)) / 1000.0
        left, sig = est.known(full, rough)
        size, sigma = 1000.0 * norm(left), 1000.0 * sig
        if len(m.recent) < 3 or math.isinf(sigma) or est.span_s < s.window_s:
            return None, False, ""
        pts = [est.known(p, rough)[0] for p in m.recent]
        spread = max(1000.0 * norm(minus(p, q)) for p in pts for q in pts)
        if spread > max(s.learn_stable_mG, 0.1 * size):
            return None, False, ""
        if recent is not None:
            # The long fit must not hold a change the recent one has not seen (or the
            # other way round): a window across a change is a mixture of two offsets.
            apart, both = known_part(
                est.cov + recent.cov, minus(est.offset_G, recent.offset_G), 3.0 * rough
            )
            if not math.isinf(both) and 1000.0 * norm(apart) > max(
                2.0 * s.learn_stable_mG, 3000.0 * both
            ):
                return None, False, ""
        floor = s.learn_done_mG if m.base is not None else s.learn_min_mG
        if size < max(floor, 2.5 * sigma):
            # Learning ends when little is left in every direction the drive can show:
            # all of them, or what a full long window knows (a level drive: x and y).
            if m.base is None or (
                est.sigma_G > s.learn_sigma_mG / 1000.0 and est.span_s < 0.9 * s.long_window_s
            ):
                return None, False, ""
            m.base = None
            return None, True, ""
        if not quiet or est.t - m.last_step_t < s.learn_interval_s:
            return None, False, ""
        k = min(1.0, s.learn_step_mG / size)
        step = (k * left[0], k * left[1], k * left[2])
        if 1000.0 * norm(plus(applied_G, step)) > s.learn_total_mG:
            if m.refused:
                return None, False, ""
            m.refused = True
            return None, False, f"over {s.learn_total_mG:.0f} mG: recalibrate"
        m.last_step_t = est.t
        if m.base is None:
            m.base = applied_G
        return step, False, ""
