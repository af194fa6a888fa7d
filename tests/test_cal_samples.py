"""Sample acceptance: spacing (ArduPilot's rule), saturation, non-finite rows, outliers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.samples import (
    SampleAcceptor,
    acceptance_angle,
    acceptance_distance,
    inlier_mask,
    robust_sigma,
    select_spread,
    usable_mask,
)


def _unit(v: list[float]) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    return a / np.linalg.norm(a)


def test_acceptance_angle_is_half_the_polyhedron_spacing() -> None:
    # For V = 12 the formula describes the icosahedron: neighbouring vertices are
    # atan(2) = 63.43 deg apart, and ArduPilot demands half of that.
    icosa_edge = math.acos(float(_unit([0, 1, 1.618034]) @ _unit([0, -1, 1.618034])))
    assert math.isclose(2.0 * acceptance_angle(12), icosa_edge, rel_tol=1e-5)
    assert math.isclose(icosa_edge, math.atan(2.0), rel_tol=1e-5)
    # Denser buffers demand closer spacing, about 1/sqrt(N) (area per sample).
    assert acceptance_angle(1200) < acceptance_angle(300) < acceptance_angle(75)
    assert math.isclose(acceptance_angle(300) / acceptance_angle(1200), 2.0, rel_tol=0.05)
    # chord on the sphere
    d = acceptance_distance(0.5, 300)
    assert math.isclose(d, 0.5 * 2.0 * math.sin(acceptance_angle(300) / 2.0))
    with pytest.raises(ValueError):
        acceptance_distance(-1.0)
    with pytest.raises(ValueError):
        acceptance_angle(3)


def test_near_duplicates_rejected_spread_samples_kept() -> None:
    acc = SampleAcceptor(capacity=300, radius_G=0.5)
    d = acc.min_distance_G
    base = np.array([0.1, 0.2, 0.3])
    step = np.array([1.0, 0.0, 0.0])
    assert acc.offer(base)
    assert not acc.offer(base)  # exact duplicate
    assert not acc.offer(base + 0.9 * d * step)  # just too close
    assert acc.offer(base + 1.1 * d * step)  # just far enough
    assert len(acc) == 2
    assert acc.counters.near_duplicate == 2 and acc.counters.accepted == 2


def test_saturated_and_non_finite_samples_are_counted_and_dropped() -> None:
    acc = SampleAcceptor(radius_G=0.5)
    assert not acc.offer([0.1, 0.2, 0.3], saturated=True)
    assert not acc.offer([np.nan, 0.2, 0.3])
    assert not acc.offer([0.1, 0.2])  # wrong length is bad input, not a crash
    assert not acc.offer_counts([4095, 2458, 2458], [0.6, 0.0, 0.0])  # ADC rail
    assert acc.offer_counts([3000, 2458, 2458], [0.2, 0.0, 0.0])
    c = acc.counters
    assert (c.saturated, c.non_finite, c.accepted, len(acc)) == (2, 2, 1, 1)
    assert c.rejected == 4


def test_a_unit_held_still_fills_one_slot() -> None:
    rng = np.random.default_rng(1)
    still = np.array([0.2, 0.0, 0.4]) + rng.normal(0.0, 5e-4, size=(500, 3))
    acc = SampleAcceptor(radius_G=0.48)
    kept = sum(acc.offer(s) for s in still)
    assert kept == 1 and acc.counters.near_duplicate == 499


def test_buffer_full_and_thinning_after_radius_grows() -> None:
    rng = np.random.default_rng(2)
    d = rng.normal(size=(5000, 3))
    d = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    acc = SampleAcceptor(capacity=300)  # starts at ArduPilot's 200 mG radius
    for s in d:
        acc.offer(s)
    assert acc.full and acc.counters.buffer_full > 0
    acc.set_radius(0.5)  # the sphere fit found the real radius: spacing grows 2.5x
    removed = acc.thin(order=rng.permutation(len(acc)))
    assert removed > 0 and len(acc) == 300 - removed
    kept = acc.samples
    gaps = np.linalg.norm(kept[:, None, :] - kept[None, :, :], axis=2)
    gaps[np.diag_indices(len(kept))] = np.inf
    assert gaps.min() >= acc.min_distance_G
    with pytest.raises(ValueError):
        acc.thin(order=[0, 0, 1])


def test_select_spread_matches_the_acceptor_and_skips_saturated() -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(size=(400, 3)) * 0.3
    sat = np.zeros(400, dtype=bool)
    sat[::7] = True
    idx = select_spread(x, 0.3, 300, sat)
    assert not np.any(sat[idx])
    acc = SampleAcceptor(300, 0.3)
    expected = [i for i in range(400) if acc.offer(x[i], saturated=bool(sat[i]))]
    assert idx.tolist() == expected


def test_outliers_removed_normal_residuals_kept() -> None:
    rng = np.random.default_rng(6)
    r = rng.normal(0.0, 1e-3, size=2000)
    r[[10, 500, 1500]] = [0.02, -0.015, 0.05]  # spikes of 15-50 sigma
    r[700] = np.nan
    keep = inlier_mask(r, k=5.0)
    assert not keep[[10, 500, 1500, 700]].any()
    assert np.count_nonzero(~keep) <= 5  # Gaussian tails beyond 5 sigma are rare
    assert math.isclose(robust_sigma(r), 1e-3, rel_tol=0.1)


def test_outlier_floor_protects_quantised_data() -> None:
    r = np.zeros(100)
    r[0] = 1e-5  # far below one ADC count: not evidence of a bad sample
    assert inlier_mask(r).all()
    with pytest.raises(ValueError):
        inlier_mask(r, k=0.0)


def test_usable_mask_validates_shapes() -> None:
    x = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert usable_mask(x, [False, False, True]).tolist() == [True, False, False]
    with pytest.raises(ValueError):
        usable_mask(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        usable_mask(x, [True])
