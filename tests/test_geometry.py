"""The one copy of each angle formula (bridge.core.geometry) and the heading judgement."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.core.geometry import (
    dcm_to_quaternion,
    euler_to_dcm,
    euler_to_quaternion,
    quaternion_to_dcm,
    wrap_degrees_180,
    wrap_degrees_360,
    wrap_radians_pi,
)
from bridge.core.quality import heading_usable

angles = st.floats(-1e6, 1e6, allow_nan=False)


@given(angles)
def test_fold_360_is_in_range_and_the_same_direction(a: float) -> None:
    w = wrap_degrees_360(a)
    assert 0.0 <= w < 360.0
    assert math.cos(math.radians(w)) == pytest.approx(math.cos(math.radians(a)), abs=1e-6)
    assert math.sin(math.radians(w)) == pytest.approx(math.sin(math.radians(a)), abs=1e-6)


def test_fold_360_by_hand() -> None:
    assert wrap_degrees_360(360.0) == 0.0
    assert wrap_degrees_360(-1e-15) == 0.0  # -1e-15 + 360 rounds to 360.0: never returned
    assert wrap_degrees_360(-90.0) == 270.0
    assert wrap_degrees_360(725.5) == 5.5
    assert wrap_degrees_180(190.0) == -170.0 and wrap_degrees_180(-180.0) == -180.0


@given(angles)
def test_fold_pi_is_in_range_and_the_same_direction(a: float) -> None:
    w = wrap_radians_pi(a)
    assert -math.pi < w <= math.pi
    assert math.cos(w) == pytest.approx(math.cos(a), abs=1e-6)
    assert math.sin(w) == pytest.approx(math.sin(a), abs=1e-6)


@given(st.floats(-math.pi, math.pi, exclude_min=True))
def test_fold_pi_leaves_an_angle_in_range_untouched(a: float) -> None:
    assert wrap_radians_pi(a) == a


def test_fold_pi_by_hand() -> None:
    assert wrap_radians_pi(-math.pi) == math.pi
    assert wrap_radians_pi(1.5 * math.pi) == pytest.approx(-0.5 * math.pi, abs=1e-15)
    assert wrap_radians_pi(math.radians(270.0)) == math.radians(270.0) - 2.0 * math.pi


@given(
    st.floats(-math.pi, math.pi),
    st.floats(-0.5 * math.pi, 0.5 * math.pi),
    st.floats(-math.pi, math.pi),
)
def test_quaternion_is_the_rotation_of_the_euler_angles(r: float, p: float, y: float) -> None:
    q = euler_to_quaternion(r, p, y)
    assert q[0] >= 0.0 and sum(x * x for x in q) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(quaternion_to_dcm(q), euler_to_dcm(r, p, y), atol=1e-12)
    # The matrix route (Shepperd's method) names the same rotation, same sign convention.
    np.testing.assert_allclose(q, dcm_to_quaternion(euler_to_dcm(r, p, y)), atol=1e-9)


def test_quaternion_by_hand() -> None:
    h = math.sqrt(0.5)
    assert euler_to_quaternion(0.0, 0.0, 0.0) == (1.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(euler_to_quaternion(0.0, 0.0, math.pi / 2), (h, 0, 0, h))
    np.testing.assert_allclose(euler_to_quaternion(math.pi / 2, 0.0, 0.0), (h, h, 0, 0))
    # yaw 270 deg: w would be negative; the conjugate sign is taken (w >= 0)
    np.testing.assert_allclose(euler_to_quaternion(0.0, 0.0, 1.5 * math.pi), (h, 0, 0, -h))


@pytest.mark.parametrize(
    ("saturated", "disturbed", "usable"),
    [(False, False, True), (True, False, False), (False, True, False), (True, True, False)],
)
def test_heading_usable(saturated: bool, disturbed: bool, usable: bool) -> None:
    assert heading_usable(saturated, disturbed) is usable
