"""Calibration by real hands: a shaken tumble's frame series fitted to the noise floor.

The unit, its shake and the attitudes it is held at are the simulator's
(``handheld_rig``); the bar is the benchmark's: held still at fresh
attitudes (tilt up to 60 deg, 0.5 s averages), heading RMS within 1.3x and
max within +0.15 deg of the unit's true parameters on the same frames.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
from handheld_rig import FIELD, Tumbled, collect, held, tumble

from bridge.calibration.fits.acceptance import DEFAULT_HEADING_MAX_DEG, Acceptance
from bridge.calibration.fits.handheld_models import _solve_joint
from bridge.calibration.fits.methods import BEST, CalibrationData, calibrate, fit, judge
from bridge.calibration.fits.series import hann_kernel, motion_rms_g, runs, window_means
from bridge.calibration.sessions.report import fit_report
from bridge.calibration.sessions.state import Mode
from bridge.core.calibration import AffineCalibration, CalibrationResult
from bridge.core.geometry import axis_angle_to_dcm
from bridge.sim.physics import UnitErrors
from bridge.tools.calreport import heading_error_estimate_deg, horizontal_field_G

H_G = horizontal_field_G(FIELD.total_G, FIELD.inclination_deg)


def _series_fit(
    rec: Tumbled, n: int | None = None, accel_calibration: AffineCalibration | None = None
) -> CalibrationResult:
    """The best method on the first ``n`` frames as a series (what a live calibration fits)."""
    n = len(rec.t) if n is None else n
    data = CalibrationData(
        rec.mag[:n],
        rec.acc[:n],
        rec.saturated[:n],
        reference=FIELD,
        t_s=rec.t[:n],
        accel_calibration=accel_calibration,
    )
    return calibrate(BEST, data)


def _live_and_old(rec: Tumbled) -> tuple[CalibrationResult, CalibrationResult]:
    """The live collection's fit now (its whole series) and before (its kept samples only)."""
    end, kept_mag, kept_acc = collect(rec)
    old = calibrate(BEST, CalibrationData(kept_mag, kept_acc, reference=FIELD))
    return _series_fit(rec, end), old


# The simulation and the fits are deterministic in their arguments, and no test changes a
# recording or a result: where two tests check different facts of the same tumble (or of
# the same fit of it), it is simulated (and fitted) once per module, not once per test.
_tumble = functools.cache(tumble)


@functools.cache
def _live_and_old_of(
    seed: int, shake: float
) -> tuple[Tumbled, CalibrationResult, CalibrationResult]:
    """A two-minute tumble and its live and old fits (see :func:`_live_and_old`)."""
    rec = _tumble(seed, shake, seconds=120.0)
    return (rec, *_live_and_old(rec))


def _announced(res: CalibrationResult) -> float:
    return heading_error_estimate_deg(res.report.fitness_mG, H_G)


# -- the frame series ----------------------------------------------------------------


def test_runs_split_at_saturation_gaps_and_time_going_back() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.9, 1.0, 1.1, 0.5, 0.6, 0.7])
    ok = np.ones(10, dtype=bool)
    ok[2] = False
    assert runs(t, ok) == [(0, 2), (3, 4), (4, 7), (7, 10)]
    with pytest.raises(ValueError):
        runs(t, ok[:5])


def test_window_means_never_straddle_a_run_and_keep_constants() -> None:
    f = np.column_stack([np.full(40, 3.0), np.arange(40.0)])
    w = window_means(f, [(0, 12), (12, 18), (20, 40)], hann_kernel(9), 2)
    assert np.allclose(w.rows[:, 0], 3.0)  # the kernel sums to 1
    # a linear feature's window mean is its value at the window's centre
    assert np.allclose(w.rows[:, 1], w.centre)
    assert set(w.centre.tolist()) == {4, 6, 24, 26, 28, 30, 32, 34}  # none from the 6-frame run


@pytest.mark.parametrize("shake", [0.0, 0.05, 0.1])
def test_motion_level_reads_the_shake(shake: float) -> None:
    rec = tumble(2, shake, seconds=30.0)
    level = motion_rms_g(rec.acc, 75)  # 1.5 s windows at 50 Hz
    # a 45 deg/s turn alone reads about 0.016 g; a shake reads 0.75-0.95 of its RMS on top
    assert math.hypot(0.016, 0.75 * shake) - 0.006 < level < math.hypot(0.017, 0.95 * shake) + 0.004


# -- the bar --------------------------------------------------------------------------


def test_shaken_tumble_calibrates_to_the_floor_where_single_samples_cannot() -> None:
    rec, res, bag = _live_and_old_of(3, 0.05)
    assert res.report.ok, res.report.notes
    # the old way: ArduPilot's kept samples as a bag (the shake taken as signal)
    s = held(rec, {"series": res.calibration, "bag": bag.calibration})
    floor, got, old = s["floor"], s["series"], s["bag"]
    assert got.rms_deg <= 1.3 * floor.rms_deg, (got, floor)
    assert got.max_deg <= floor.max_deg + 0.15, (got, floor)
    assert old.rms_deg > 5.0 * floor.rms_deg  # what the fix is for: ~1 deg RMS
    # roll and pitch: as the true accelerometer calibration gives, not the shake's
    assert got.tilt_max_deg <= floor.tilt_max_deg + 0.05
    assert old.tilt_max_deg > 0.5
    # what it says of itself: the shake it saw, the window it used, a fitness near the residual
    rep = res.report
    assert 0.03 < rep.motion_g < 0.06 and rep.window_s > 0.0
    assert rep.residual_mG <= rep.fitness_mG < 1.5 * rep.residual_mG
    assert "accelerometer: fit of the tumble (hand-held)" in rep.notes


def test_still_tumble_stays_at_the_floor() -> None:
    rec = tumble(5, 0.0, seconds=120.0)
    res, _ = _live_and_old(rec)
    s = held(rec, {"series": res.calibration})
    assert s["series"].rms_deg <= 1.3 * s["floor"].rms_deg
    assert s["series"].max_deg <= s["floor"].max_deg + 0.15
    assert s["series"].tilt_max_deg <= s["floor"].tilt_max_deg + 0.05
    assert res.report.motion_g < 0.025  # a smooth turn, no shake


def test_roll_and_pitch_are_never_made_worse() -> None:
    rec = _tumble(3, 0.05, seconds=70.0)
    # a known accelerometer calibration (six faces, the one in use) is kept as it is
    given = rec.truth.accel
    res = _series_fit(rec, accel_calibration=given)
    assert res.calibration.accel == given
    assert "accelerometer: given" in res.report.notes
    # a unit whose accelerometer needs no calibration keeps the nominal transfer:
    # fitting it from a tumble would only add the fit's noise
    perfect = UnitErrors(
        mag_noise_G=0.0005, acc_noise_g=0.001, hard_iron_G=np.array([0.05, -0.03, 0.08])
    )
    rec2 = tumble(8, 0.05, seconds=70.0, errors=perfect)
    res2 = _series_fit(rec2)
    assert res2.calibration.accel == AffineCalibration()
    assert "accelerometer: nominal" in res2.report.notes
    s = held(rec2, {"series": res2.calibration})
    assert s["series"].tilt_max_deg <= s["floor"].tilt_max_deg + 1e-9


# -- telling the truth ---------------------------------------------------------------


@pytest.mark.parametrize(("seed", "shake"), [(3, 0.05), (4, 0.1)])
def test_announced_heading_error_is_within_2x_of_the_measured(seed: int, shake: float) -> None:
    rec, res, bag = _live_and_old_of(seed, shake)
    s = held(rec, {"series": res.calibration, "bag": bag.calibration})
    measured = s["series"].frame_rms_deg  # frame by frame, as the bridge publishes
    assert 0.5 * measured <= _announced(res) <= 2.0 * measured
    # the bag's fitness looks as good while its heading is many times worse: the old lie
    assert _announced(bag) < 0.5 * s["bag"].frame_rms_deg
    report = fit_report(Mode.MAG, res.calibration.mag, res.report).to_dict()
    assert report["fitness"] == pytest.approx(res.report.fitness_mG)
    assert report["heading_error_deg"] == pytest.approx(res.report.heading_error_deg)


@pytest.mark.parametrize(
    ("seed", "dps", "shake"),
    [(4, 120.0, 0.3), (1, 120.0, 0.3), (4, 45.0, 0.5), (1, 90.0, 0.5), (1, 180.0, 0.5)],
)
def test_motion_too_violent_fails_instead_of_succeeding_worse(
    seed: int, dps: float, shake: float
) -> None:
    # far beyond a hand's usual shake: the fit either still holds within the operator's
    # target (DEFAULT_HEADING_MAX_DEG, 1 deg) and within what it predicts, or fails saying
    # why -- it never succeeds quietly worse
    rec = tumble(seed, shake, seconds=70.0, dps=dps)
    data = CalibrationData(rec.mag, rec.acc, rec.saturated, reference=FIELD, t_s=rec.t)
    fitted = fit(BEST, data)  # judged twice below: the default target, and a stricter one
    res = judge(fitted, data)
    s = held(rec, {"series": res.calibration})
    excess = math.sqrt(max(0.0, s["series"].rms_deg ** 2 - s["floor"].rms_deg ** 2))
    rep = res.report  # the best method is judged by the acceptance rule
    assert rep.heading_limit_deg == DEFAULT_HEADING_MAX_DEG
    if rep.ok:
        assert excess <= rep.heading_limit_deg and excess <= rep.predicted_heading_deg
    else:
        assert rep.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
        assert rep.notes[0] == rep.reason
        assert rep.reason.startswith(("heading error ~", "fitness "))
        assert rep.reason.endswith("turn slower / steadier")
    if (seed, dps) == (1, 180.0):  # spoilt beyond the target, and says so
        assert excess > DEFAULT_HEADING_MAX_DEG and not rep.ok
    if (seed, dps) == (4, 120.0):
        # leaves ~0.4 deg RMS beyond the floor: within the 1 deg target (and within the
        # ~0.7 deg it predicts) -- but an operator who asks for 0.25 deg is told no, and why
        assert rep.ok and excess > 0.25
        strict = judge(fitted, data, Acceptance(heading_max_deg=0.25))
        assert not strict.report.ok
        assert strict.report.reason.endswith("> 0.25: turn slower / steadier")


@pytest.mark.parametrize(("seed", "dps", "shake"), [(5, 90.0, 2.0), (4, 45.0, 2.0)])
def test_a_shake_that_hides_gravity_is_told_as_motion_not_as_a_wrong_orientation(
    seed: int, dps: float, shake: float
) -> None:
    # 2 g of shake: the frames do not give gravity, and the mag-to-accel rotation fitted from
    # them is tens of degrees of noise (43 and 72 deg here, the unit's own ~2): unknown, not
    # wrong. The operator is told to turn steadier -- not to check COMPASS_ORIENT, which
    # they would change for nothing.
    rec = tumble(seed, shake, seconds=70.0, dps=dps)
    data = CalibrationData(rec.mag, rec.acc, rec.saturated, reference=FIELD, t_s=rec.t)
    rep = calibrate(BEST, data).report
    assert not rep.ok and rep.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    assert rep.reason.endswith("turn slower / steadier") and rep.notes[0] == rep.reason
    assert not any("COMPASS_ORIENT" in n for n in rep.notes)
    assert not rep.heading_error_deg <= 10.0  # what made the rotation unknown


@pytest.mark.parametrize(("seed", "shake", "yaw_deg"), [(5, 0.3, 45.0), (4, 0.05, 90.0)])
def test_a_compass_mounted_turned_fails_its_orientation_under_a_hands_shake(
    seed: int, shake: float, yaw_deg: float
) -> None:
    # ... while a magnetometer really turned against the accelerometer (a wrong
    # COMPASS_ORIENT: 45 deg and more) is determined to a tenth of a degree by a hand's
    # tumble, and told as what it is.
    e = UnitErrors.draw(np.random.default_rng(seed))
    turned = axis_angle_to_dcm([0.0, 0.0, 1.0], math.radians(yaw_deg)) @ e.mag_rotation
    rec = tumble(seed, shake, seconds=70.0, dps=45.0, errors=replace(e, mag_rotation=turned))
    data = CalibrationData(rec.mag, rec.acc, rec.saturated, reference=FIELD, t_s=rec.t)
    rep = calibrate(BEST, data).report
    assert rep.status == "MAG_CAL_FAILED_ORIENTATION"
    assert "check COMPASS_ORIENT" in rep.reason and f"{yaw_deg:.0f}." in rep.reason
    assert rep.heading_error_deg < 1.0


def test_a_good_fit_passes_the_accuracy_judge_and_a_tighter_target_fails_it() -> None:
    rec = _tumble(3, 0.05, seconds=70.0)
    data = CalibrationData(rec.mag, rec.acc, rec.saturated, reference=FIELD, t_s=rec.t)
    fitted = fit(BEST, data)
    good = judge(fitted, data)
    assert good.report.ok and good.report.predicted_heading_deg < 0.25
    tight = judge(fitted, data, Acceptance(heading_max_deg=1e-3))
    assert tight.report.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    assert tight.report.reason.endswith(": turn slower / steadier")


def test_a_short_series_falls_back_to_single_samples_and_bad_times_are_refused() -> None:
    rec = tumble(3, 0.0, seconds=3.0)
    res = _series_fit(rec)
    assert any("single samples used" in n for n in res.report.notes)
    with pytest.raises(ValueError, match="t_s"):
        CalibrationData(rec.mag, rec.acc, t_s=rec.t[:-1])


def _garbage_rows(trials: int) -> list[np.ndarray]:
    """Window features no unit could give (random, at scales from 1e-3 to 1e3): the
    same draws, in the same order, as the search that found the ones that diverge."""
    rng = np.random.default_rng(1)
    out = []
    for _ in range(trials):
        n = int(rng.integers(15, 60))
        scale = 10.0 ** rng.uniform(-3, 3)
        rows = rng.normal(size=(n, 21)) * scale + rng.normal(size=21) * scale * rng.uniform(0, 5)
        out.append(rows)
    return out


def test_a_joint_fit_that_diverges_gives_no_candidate_and_no_numpy_warning() -> None:
    """Gauss-Newton sent to infinity by windows that do not pin the model is no candidate,
    and says nothing on stderr (numpy's overflow warnings reached CI's output, and would
    reach the daemon's journal during a calibration)."""
    sets = _garbage_rows(1861)
    for rows in (sets[895], sets[1860]):  # two of 3000 that overflow
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert _solve_joint(rows) is None
