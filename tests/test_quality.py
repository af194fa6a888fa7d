"""Quality flags: disturbance and acceleration raise and clear where they should."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.core import sensor
from bridge.core.attitude import AttitudeEngine, FieldReference
from bridge.core.geometry import euler_to_dcm
from bridge.core.quality import (
    Debounce,
    QualityLimits,
    QualityMonitor,
    accel_out_of_limits,
    field_out_of_limits,
)

LIM = QualityLimits(field_tolerance=0.15, dip_tolerance_deg=5.0, accel_tolerance_g=0.1)


def test_field_limits() -> None:
    assert not field_out_of_limits(0.50, 60.0, 0.50, 60.0, LIM)
    assert not field_out_of_limits(0.57, 64.9, 0.50, 60.0, LIM)  # 14 %, 4.9 deg
    assert field_out_of_limits(0.58, 60.0, 0.50, 60.0, LIM)  # 16 % strong
    assert field_out_of_limits(0.42, 60.0, 0.50, 60.0, LIM)  # 16 % weak
    assert field_out_of_limits(0.50, 54.0, 0.50, 60.0, LIM)  # dip 6 deg off
    assert field_out_of_limits(math.nan, 60.0, 0.50, 60.0, LIM)
    assert field_out_of_limits(0.50, math.nan, 0.50, 60.0, LIM)
    # unknown expectations are not checked
    assert not field_out_of_limits(0.9, 10.0, None, None, LIM)
    assert not field_out_of_limits(0.50, None, 0.50, 60.0, LIM)


def test_accel_limits() -> None:
    assert not accel_out_of_limits(1.0, LIM)
    assert not accel_out_of_limits(1.09, LIM)
    assert not accel_out_of_limits(0.91, LIM)
    assert accel_out_of_limits(1.11, LIM)
    assert accel_out_of_limits(0.5, LIM)
    assert accel_out_of_limits(math.nan, LIM)


def test_debounce_needs_consecutive_frames() -> None:
    d = Debounce(raise_after=3, clear_after=2)
    # isolated glitches never raise it
    assert [d.update(b) for b in (True, False, True, True, False, True, False)] == [False] * 7
    assert [d.update(True) for _ in range(3)] == [False, False, True]
    # one good frame does not clear it; two do
    assert d.update(False) is True
    assert d.update(True) is True
    assert [d.update(False) for _ in range(2)] == [True, False]
    d.update(True), d.update(True), d.update(True)
    d.reset()
    assert d.state is False
    with pytest.raises(ValueError):
        Debounce(0, 1)


def test_monitor_ignores_dip_while_accelerating() -> None:
    q = QualityMonitor(QualityLimits(raise_after=1, clear_after=1))
    # at rest, dip 20 deg off: disturbed
    assert q.update(0.5, 40.0, 1.0, 0.5, 60.0) == (True, False)
    # accelerating: the dip is not trusted, magnitude fine -> not disturbed, accelerating
    assert q.update(0.5, 40.0, 1.3, 0.5, 60.0) == (False, True)
    # accelerating and the magnitude is off: still disturbed
    assert q.update(0.7, 40.0, 1.3, 0.5, 60.0) == (True, True)
    assert q.disturbed and q.accelerating
    q.reset()
    assert not q.disturbed and not q.accelerating


@pytest.mark.parametrize(
    "kwargs",
    [
        {"field_tolerance": 0.0},
        {"dip_tolerance_deg": -1.0},
        {"accel_tolerance_g": math.inf},
        {"degraded_pitch_deg": 95.0},
        {"raise_after": 0},
        {"clear_after": 1.5},
    ],
)
def test_limits_validate(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        QualityLimits(**kwargs)


# -- through the engine ------------------------------------------------------------------------

B_NED = np.array([0.2, 0.0, 0.45])
TOTAL = float(np.linalg.norm(B_NED))
DIP = math.degrees(math.atan2(0.45, 0.2))


def _frame(
    R: np.ndarray, extra_mag_G: np.ndarray | None = None, acc_scale: float = 1.0
) -> tuple[float, ...]:
    mag = R.T @ B_NED + (extra_mag_G if extra_mag_G is not None else 0.0)
    acc = acc_scale * (R.T @ np.array([0.0, 0.0, 1.0]))
    m = sensor.gauss_to_mag_counts(mag)
    a = sensor.g_to_acc_counts(acc)
    return (*(float(v) for v in m), *(float(v) for v in a))


def test_engine_raises_and_clears_disturbance_with_debounce() -> None:
    eng = AttitudeEngine(
        reference=FieldReference(declination_deg=0.0, total_G=TOTAL, dip_deg=DIP),
        limits=QualityLimits(raise_after=3, clear_after=4),
    )
    R = euler_to_dcm(0.1, -0.2, 1.0)
    clean = _frame(R)
    magnet = _frame(R, extra_mag_G=np.array([0.15, 0.0, 0.0]))  # a magnet 0.15 G along x
    sol = eng.solve_counts(*clean)
    assert not sol.disturbed and sol.field_strength_G == pytest.approx(TOTAL, rel=1e-9)
    assert sol.dip_deg == pytest.approx(DIP, abs=1e-6)
    # one noisy frame: no flap
    assert not eng.solve_counts(*magnet).disturbed
    assert not eng.solve_counts(*clean).disturbed
    flags = [eng.solve_counts(*magnet).disturbed for _ in range(3)]
    assert flags == [False, False, True]
    flags = [eng.solve_counts(*clean).disturbed for _ in range(4)]
    assert flags == [True, True, True, False]


def test_engine_flags_acceleration() -> None:
    eng = AttitudeEngine(limits=QualityLimits(raise_after=2, clear_after=2))
    R = euler_to_dcm(0.0, 0.0, 0.5)
    assert not eng.solve_counts(*_frame(R, acc_scale=1.05)).accelerating
    assert [eng.solve_counts(*_frame(R, acc_scale=1.3)).accelerating for _ in range(2)] == [
        False,
        True,
    ]
    sol = eng.solve_counts(*_frame(R, acc_scale=0.8))
    assert sol.accelerating and sol.accel_norm_g == pytest.approx(0.8, rel=1e-9)
    assert [eng.solve_counts(*_frame(R)).accelerating for _ in range(2)] == [True, False]


def test_no_reference_means_no_disturbance_judgement() -> None:
    eng = AttitudeEngine(limits=QualityLimits(raise_after=1, clear_after=1))
    R = euler_to_dcm(0.0, 0.0, 0.0)
    sol = eng.solve_counts(*_frame(R, extra_mag_G=np.array([0.3, 0.0, 0.0])))
    assert not sol.disturbed
    # once the expected field is known, the same frame is judged
    eng.update_reference(FieldReference(total_G=TOTAL, dip_deg=DIP))
    assert eng.solve_counts(*_frame(R, extra_mag_G=np.array([0.3, 0.0, 0.0]))).disturbed


_maybe = st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True, width=32))


@examples(100)  # Hypothesis's default count, a third of it everyday
@given(
    frames=st.lists(
        st.tuples(
            st.floats(0.0, 1.2) | st.sampled_from([math.nan, math.inf]),
            _maybe,
            st.floats(0.0, 2.5) | st.sampled_from([math.nan]),
            st.sampled_from([None, 0.0, 0.5]),
            st.sampled_from([None, 60.0, -30.0]),
        ),
        max_size=40,
    ),
    raise_after=st.integers(1, 4),
    clear_after=st.integers(1, 4),
)
def test_monitor_update_is_the_limit_functions_debounced(
    frames: list[tuple[float, float | None, float, float | None, float | None]],
    raise_after: int,
    clear_after: int,
) -> None:
    """QualityMonitor.update must judge exactly as
    accel_out_of_limits / field_out_of_limits (dip ignored under acceleration) fed
    through two Debounce flags."""
    lim = QualityLimits(raise_after=raise_after, clear_after=clear_after)
    mon = QualityMonitor(lim)
    field_flag, accel_flag = Debounce(raise_after, clear_after), Debounce(raise_after, clear_after)
    for field_G, dip, acc, exp_total, exp_dip in frames:
        accel_bad = accel_out_of_limits(acc, lim)
        field_bad = field_out_of_limits(
            field_G, None if accel_bad else dip, exp_total, exp_dip, lim
        )
        want = (field_flag.update(field_bad), accel_flag.update(accel_bad))
        assert mon.update(field_G, dip, acc, exp_total, exp_dip) == want
        assert (mon.disturbed, mon.accelerating) == want
