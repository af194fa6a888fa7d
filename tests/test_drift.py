"""The drift estimator and judge (bridge.calibration.drift.estimator): samples in, verdicts out.

The samples are a simulated unit driving (turns, +-15 deg roll and pitch, a
vehicle's accelerations), calibrated with its true calibration, in memory: no
clock, no threads, a few minutes of driving in well under a second.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest

from bridge.calibration.drift.estimator import (
    ZERO,
    DriftEstimate,
    DriftEstimator,
    DriftSettings,
    Reference,
    _median,
    heading_error_deg,
    with_offset_change,
)
from bridge.calibration.drift.judge import DriftJudge
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.core.wmm import earth_field
from bridge.sim.drive import Drive
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors, magnet_pass

FIELD = earth_field(*DEFAULT_LOCATION)
REF = Reference.from_total_dip(FIELD.total_G, FIELD.inclination_deg)


def drive_rows(
    seed: int,
    seconds: float,
    *,
    change_G: tuple[float, float, float] | None = None,
    scale: float = 1.0,
    level: bool = False,
    extra: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rows (t, h, g) of a unit driving, calibrated with its true calibration (times
    scaled by ``scale``: a calibration reading another field), and the change in body axes."""
    errors = UnitErrors.draw(np.random.default_rng(seed))
    model = SensorModel(errors, FIELD.ned_G)
    cal = errors.true_calibration()
    drive = Drive(seed, max_roll_deg=0.0, max_pitch_deg=0.0) if level else Drive(seed)
    ts = np.arange(0.0, seconds, 0.1)
    if change_G is not None:
        model = model.with_hard_iron_change(change_G)
    acc = drive.linear_accs_ned_g(ts)
    s = model.sample(drive.attitudes(ts), np.random.default_rng([seed, 9]), acc, extra)
    h = scale * cal.mag.apply(mag_counts_to_gauss(s.mag_counts))
    g = cal.accel.apply(acc_counts_to_g(s.acc_counts))
    b = cal.mag.matrix_array @ np.asarray(change_G if change_G is not None else ZERO)
    return np.column_stack([ts, h, g]), scale * b


def fit(
    rows: np.ndarray, reference: Reference | None = REF, window: float = 120.0
) -> DriftEstimate:
    est = DriftEstimator(DriftSettings(), window_s=window)
    for i in range(0, len(rows), 50):
        est.add(rows[i : i + 50])
    e = est.estimate(reference)
    assert e is not None
    return e


# -- the estimator ------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2])
def test_a_good_calibration_fits_no_offset_and_a_change_fits_itself(seed: int) -> None:
    rows, _ = drive_rows(seed, 120.0)
    e = fit(rows)
    assert 1000.0 * math.hypot(*e.offset_G[:2]) < 1.0  # the horizontal part: well known
    assert 1000.0 * abs(e.offset_G[2]) < 3.0 * 1000.0 * e.sigma_G
    assert e.field_G == pytest.approx(FIELD.total_G, rel=0.005) and e.referenced
    assert e.n_dip > 100  # the straights give quasi-static samples
    change = (0.025, -0.015, 0.02)
    rows, b = drive_rows(seed, 120.0, change_G=change)
    e = fit(rows)
    np.testing.assert_allclose(1000.0 * np.array(e.offset_G[:2]), 1000.0 * b[:2], atol=1.0)
    assert abs(e.offset_G[2] - b[2]) < 3.0 * e.sigma_G and 1000.0 * e.sigma_G < 2.0


def test_a_level_drive_knows_the_horizontal_offset_only_without_the_model() -> None:
    rows, b = drive_rows(3, 120.0, change_G=(0.02, 0.01, 0.03), level=True)
    alone = fit(rows, Reference())
    known, sigma = alone.known(alone.offset_G, 0.003)
    assert not alone.referenced
    # turns alone: x and y, not z (a level vehicle's z reads the same at every heading)
    np.testing.assert_allclose(1000.0 * np.array(known[:2]), 1000.0 * b[:2], atol=1.5)
    assert abs(known[2]) < 1e-4 and sigma < 0.003
    helped = fit(rows)  # the model's field and dip pin the vertical part too
    np.testing.assert_allclose(1000.0 * np.array(helped.offset_G), 1000.0 * b, atol=2.0)


def test_a_calibration_on_another_scale_is_not_judged_against_the_model() -> None:
    # reads 5 % more than the model's field (fitted without the position, say): the
    # model's field is dropped, and the fit finds no offset where there is none
    rows, _ = drive_rows(4, 120.0, scale=1.05)
    e = fit(rows)
    assert not e.referenced
    assert 1000.0 * np.linalg.norm(e.known(e.offset_G, 0.003)[0]) < 2.0


def test_a_magnet_going_by_is_left_out() -> None:
    ts = np.arange(0.0, 120.0, 0.1)
    magnet = magnet_pass(ts, 60.0, 0.5, (0.3, -0.2, 0.9))
    rows, _ = drive_rows(5, 120.0, extra=magnet)
    clean = fit(drive_rows(5, 120.0)[0])
    e = fit(rows)
    assert 1000.0 * np.linalg.norm(np.subtract(e.offset_G, clean.offset_G)) < 1.5
    assert 55.0 < e.outlier_t < 75.0  # the pass is seen, and where
    assert e.n_field < clean.n_field - 100  # with its tails


def test_the_window_forgets_and_cuts() -> None:
    rows, _ = drive_rows(1, 100.0)
    est = DriftEstimator(DriftSettings(), window_s=30.0)
    for i in range(0, len(rows), 50):
        est.add(rows[i : i + 50])
    assert est.samples == 301  # 30 s at 10 Hz, both ends in
    est.cut(90.0)
    assert est.samples == 100 and est.estimate(REF) is None  # too few to fit
    est.reset()
    assert est.samples == 0
    with pytest.raises(ValueError):
        DriftEstimator(DriftSettings(), window_s=5.0)


def test_offsets_move_in_sensor_axes_through_the_matrix_and_mounting() -> None:
    m = np.array([[1.05, 0.02, 0.0], [0.0, 0.97, 0.01], [0.0, 0.0, 1.01]])
    cal = Calibration(mag=AffineCalibration.from_arrays((0.1, -0.05, 0.2), m))
    mount = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # yaw 90
    b = (0.01, 0.02, -0.03)
    new = with_offset_change(cal, mount, b)
    raw = np.array([0.3, 0.1, 0.5])
    before = mount @ cal.mag.apply(raw)
    after = mount @ new.mag.apply(raw)
    np.testing.assert_allclose(before - after, b, atol=1e-12)  # the engine reads b less
    assert new.mag.matrix == cal.mag.matrix and new.accel == cal.accel


def test_heading_error_of_an_offset() -> None:
    assert heading_error_deg((0.0, 0.02, 0.5), 0.2) == pytest.approx(math.degrees(math.asin(0.1)))
    assert heading_error_deg((0.3, 0.0, 0.0), 0.2) == 90.0
    assert math.isnan(heading_error_deg((0.01, 0.0, 0.0), 0.0))


# -- the judge ---------------------------------------------------------------------------


def est(t: float, mG: tuple[float, float, float], sigma_mG: float = 0.5) -> DriftEstimate:
    """A fit saying ``mG`` with ``sigma_mG`` in every direction."""
    v = (sigma_mG / 1000.0) ** 2
    return DriftEstimate(
        t=t,
        offset_G=(mG[0] / 1000.0, mG[1] / 1000.0, mG[2] / 1000.0),
        cov_G2=(v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v),
        field_G=FIELD.total_G,
        vertical_G=FIELD.total_G * math.sin(math.radians(FIELD.inclination_deg)),
        residual_G=0.0005,
        n_field=600,
        n_dip=300,
        span_s=60.0,
    )


def test_drift_is_declared_after_three_fits_and_cleared_after_three() -> None:
    j = DriftJudge()
    v = j.judge(est(0.0, (1.0, 0.0, 0.0)), None, ZERO, learn=False, quiet=True)
    assert v.state == "ok" and not v.detected
    states = []
    for k in range(4):
        v = j.judge(est(5.0 * (k + 1), (15.0, 0.0, 0.0)), None, ZERO, learn=False, quiet=True)
        states.append((v.state, v.detected))
        assert v.step_G is None  # detect only
    assert states == [("ok", False), ("ok", False), ("drift", True), ("drift", False)]
    assert v.drift_G == pytest.approx((0.015, 0.0, 0.0))
    for k in range(3):
        v = j.judge(est(30.0 + 5 * k, (2.0, 0.0, 0.0)), None, ZERO, learn=False, quiet=True)
    assert v.state == "ok" and v.cleared


def test_no_verdict_on_what_is_not_known_nor_on_a_garbled_fit() -> None:
    j = DriftJudge()
    for k in range(6):  # a large change known only to 5 mG: no drift
        v = j.judge(est(5.0 * k, (40.0, 0.0, 0.0), 5.0), None, ZERO, learn=True, quiet=True)
        assert v.state == "collecting" and v.step_G is None and v.drift_G is None
    j = DriftJudge()
    garbled = dataclasses.replace(est(0.0, (40.0, 0.0, 0.0)), consistent=False)
    for _ in range(6):  # a window of two offsets (across a change): no verdict either
        v = j.judge(garbled, garbled, ZERO, learn=True, quiet=True)
        assert v.state == "collecting" and v.step_G is None


def test_the_long_window_is_cut_where_the_recent_one_disagrees() -> None:
    j = DriftJudge()
    same = j.judge(est(100.0, (1.0, 0.0, 0.0)), est(100.0, (0.0, 0.0, 0.0)), ZERO,
                   learn=False, quiet=True)  # fmt: skip
    assert same.cut_before is None
    v = j.judge(est(105.0, (30.0, 0.0, 0.0)), est(105.0, (1.0, 0.0, 0.0)), ZERO,
                learn=False, quiet=True)  # fmt: skip
    assert v.cut_before == pytest.approx(105.0 - 0.5 * DriftSettings().window_s)


def test_an_offset_already_applied_is_no_drift() -> None:
    j = DriftJudge()
    applied = (0.02, 0.0, 0.0)
    for k in range(5):
        v = j.judge(est(5.0 * k, (20.0, 0.5, 0.0)), None, applied, learn=False, quiet=True)
    assert v.state == "ok" and not v.detected


def test_learning_steps_are_bounded_spaced_and_end() -> None:
    s = DriftSettings()
    j = DriftJudge(s)
    applied = ZERO
    steps = []
    t = 0.0
    for _ in range(40):
        e = est(t, (60.0, -20.0, 10.0), 0.5)
        v = j.judge(e, e, applied, learn=True, quiet=True)
        if v.step_G is not None:
            assert 1000.0 * np.linalg.norm(v.step_G) <= s.learn_step_mG + 1e-9
            steps.append(t)
            applied = tuple(np.add(applied, v.step_G))
        if v.learned:
            break
        t += 5.0
    assert v.learned
    assert 1000.0 * np.linalg.norm(np.subtract(applied, (0.06, -0.02, 0.01))) < 1e-6
    assert len(steps) == 3 and min(np.diff(steps)) >= s.learn_interval_s


def test_learning_waits_for_quiet_agreement_and_stability() -> None:
    j = DriftJudge()
    for k in range(5):  # disturbed: nothing applied
        e = est(5.0 * k, (20.0, 0.0, 0.0))
        assert j.judge(e, e, ZERO, learn=True, quiet=False).step_G is None
    # the recent fit disagrees with the long one: a mixture across a change, wait
    j = DriftJudge()
    for k in range(5):
        v = j.judge(est(5.0 * k, (30.0, 0.0, 0.0)), est(5.0 * k, (20.0, 0.0, 0.0)), ZERO,
                    learn=True, quiet=True)  # fmt: skip
        assert v.step_G is None
    # unstable: the long fit still moves
    j = DriftJudge()
    for k in range(5):
        e = est(5.0 * k, (20.0 + 3.0 * k, 0.0, 0.0))
        assert j.judge(e, e, ZERO, learn=True, quiet=True).step_G is None
    # small changes are not learned at all, large ones refused
    j = DriftJudge()
    for k in range(5):
        e = est(5.0 * k, (2.0, 0.0, 0.0), 0.3)
        assert j.judge(e, e, ZERO, learn=True, quiet=True).step_G is None
    j = DriftJudge()
    refusals = []
    for k in range(6):
        e = est(5.0 * k, (0.0, 0.0, 300.0), 2.0)
        v = j.judge(e, e, (0.0, 0.0, 0.24), learn=True, quiet=True)
        assert v.step_G is None
        refusals.append(v.refused)
    assert sum(1 for r in refusals if r) == 1 and "recalibrate" in "".join(refusals)


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="detect_mG"):
        DriftSettings(detect_mG=0.0)
    with pytest.raises(ValueError, match="two blocks"):
        DriftSettings(window_s=8.0)


def test_a_vertical_change_needs_to_be_larger() -> None:
    def declared(mG: tuple[float, float, float]) -> bool:
        j = DriftJudge()
        for k in range(4):
            v = j.judge(est(5.0 * k, mG), None, ZERO, learn=False, quiet=True)
        return v.state == "drift"

    assert declared((12.0, 0.0, 0.0)) and not declared((0.0, 0.0, 12.0))
    assert declared((0.0, 0.0, 16.0)) and declared((0.0, 0.0, -16.0))


def test_the_estimators_median_is_numpys_bit_for_bit() -> None:
    # the estimator's one-partition median (every estimate takes several) against np.median:
    # odd and even sizes, ties, infinities and NaN
    rng = np.random.default_rng(11)
    for n in [*range(0, 40), 301, 1000, 1001]:
        for kind in range(4):
            x = rng.normal(size=n)
            if kind == 1:
                x = np.round(x, 1)  # ties
            elif kind == 2 and n:
                x[rng.integers(n)] = rng.choice([math.inf, -math.inf])
            elif kind == 3 and n:
                x[rng.integers(n)] = math.nan
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                want, got = float(np.median(x)), _median(x)
            assert (math.isnan(want) and math.isnan(got)) or got == want, (n, kind, got, want)
            assert math.copysign(1.0, got) == math.copysign(1.0, want) or math.isnan(want)
