"""Sensor physics of the simulated compass: the documented model, its inverse, ADC rails, noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.core.geometry import (
    axis_angle_to_dcm,
    dcm_to_rotvec,
    euler_to_dcm,
    random_rotations,
)
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.sim.physics import (
    DEFAULT_LOCATION,
    SensorModel,
    UnitErrors,
    default_field_ned_G,
)

FIELD = np.array([0.2152, 0.0138, 0.4333])  # about Zurich; a fixed vector keeps tests exact


def model_counts_unrounded(e: UnitErrors, R: np.ndarray, field: np.ndarray) -> tuple:
    """The module docstring's model written out independently (noise-free, unquantised)."""
    b = R.T @ field
    g = R.T @ np.array([0.0, 0.0, 1.0])
    mag_G = e.soft_iron @ e.mag_rotation @ b + e.hard_iron_G
    acc_g = e.acc_matrix @ g + e.acc_offset_g
    return 2458 + e.mag_adc_zero + 2560 * mag_G, 2458 + e.acc_adc_zero + 491.5 * acc_g


def quiet(e: UnitErrors) -> UnitErrors:
    """The same unit without noise."""
    d = {k: getattr(e, k) for k in e.__dataclass_fields__}
    return UnitErrors(**(d | {"mag_noise_G": 0.0, "acc_noise_g": 0.0}))


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_true_calibration_inverts_the_model_exactly(seed: int) -> None:
    rng = np.random.default_rng(seed)
    e = UnitErrors.draw(rng)
    cal = e.true_calibration()
    for R in random_rotations(rng, 20):
        mag_c, acc_c = model_counts_unrounded(e, R, FIELD)
        mag = cal.mag.apply(mag_counts_to_gauss(mag_c))
        acc = cal.accel.apply(acc_counts_to_g(acc_c))
        np.testing.assert_allclose(mag, R.T @ FIELD, atol=1e-9)
        np.testing.assert_allclose(acc, R[2, :], atol=1e-9)


@pytest.mark.parametrize("seed", [5, 6])
def test_sample_quantises_the_documented_model(seed: int) -> None:
    rng = np.random.default_rng(seed)
    e = quiet(UnitErrors.draw(rng))
    model = SensorModel(e, FIELD)
    Rs = random_rotations(rng, 200)
    s = model.sample(Rs, rng)
    want_b, want_g = [], []
    for i, R in enumerate(Rs):
        mag_c, acc_c = model_counts_unrounded(e, R, FIELD)
        want_m = np.clip(np.rint(mag_c), 0, 4095)
        want_a = np.clip(np.rint(acc_c), 0, 4095)
        assert s.mag_counts[i].tolist() == want_m.astype(int).tolist()
        assert s.acc_counts[i].tolist() == want_a.astype(int).tolist()
        want_b.append(R.T @ FIELD)
        want_g.append(R[2, :])
    # every frame's ideal vectors against the same per-frame truths, compared all at once
    # (assert_allclose costs ~0.1 ms a call: 400 calls were most of this test)
    np.testing.assert_allclose(s.mag_body_G, np.array(want_b), atol=1e-12)
    np.testing.assert_allclose(s.acc_body_g, np.array(want_g), atol=1e-12)
    # the true calibration applied to quantised counts is off by at most half a count
    cal = e.true_calibration()
    unsat = ~s.saturated
    mag = cal.mag.apply(mag_counts_to_gauss(s.mag_counts[unsat]))
    err_counts = np.abs(mag - s.mag_body_G[unsat]) * 2560
    assert err_counts.max() < 1.0


def test_ideal_unit_reads_the_nominal_transfer() -> None:
    model = SensorModel(UnitErrors.ideal(), FIELD)
    s = model.sample(np.eye(3), np.random.default_rng(0))
    # level, facing north: x sees the north component, z the down component, az +1 g
    assert s.mag_counts.tolist() == [
        [round(2458 + 2560 * 0.2152), round(2458 + 2560 * 0.0138), 3567]
    ]
    assert s.acc_counts.tolist() == [[2458, 2458, 2950]]  # 2949.5 rounds half to even
    assert s.saturated.tolist() == [False]


def test_sample_shapes_and_bad_input() -> None:
    model = SensorModel(UnitErrors.ideal(), FIELD)
    rng = np.random.default_rng(0)
    one = model.sample(np.eye(3), rng)
    many = model.sample(random_rotations(rng, 7), rng)
    assert one.mag_counts.shape == (1, 3) and one.saturated.shape == (1,)
    assert many.acc_counts.shape == (7, 3) and many.mag_body_G.shape == (7, 3)
    assert one.mag_counts.dtype.kind == "i"
    with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
        model.sample(np.eye(4), rng)
    with pytest.raises(ValueError, match="proper rotation"):
        UnitErrors(mag_rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="finite"):
        UnitErrors(hard_iron_G=np.array([math.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        UnitErrors(soft_iron=np.eye(2))
    with pytest.raises(ValueError, match="noise"):
        UnitErrors(mag_noise_G=-1.0)
    e = UnitErrors.draw(rng)
    with pytest.raises(ValueError):
        e.hard_iron_G[0] = 1.0  # frozen means frozen: arrays are read-only


def test_linear_acceleration_follows_the_gravity_vector_sign() -> None:
    # accelerating north at 0.5 g while level: the datasheet's gravity vector reads g - a
    model = SensorModel(UnitErrors.ideal(), FIELD)
    s = model.sample(np.eye(3), np.random.default_rng(0), linear_acc_ned_g=[0.5, 0.0, 0.0])
    np.testing.assert_allclose(s.acc_body_g[0], [-0.5, 0.0, 1.0])
    assert s.acc_counts[0].tolist() == [round(2458 - 0.5 * 491.5), 2458, 2950]


@pytest.mark.parametrize("seed", [7, 8])
def test_one_frame_at_a_time_samples_what_the_stack_samples_bit_for_bit(seed: int) -> None:
    # The firmware samples one frame per tick (sample's one-frame path, no broadcasting);
    # the benchmarks a stack at once: the same counts, flags and truth, exactly. (Quiet:
    # a stack draws its noise axis by axis for all frames, frames one by one draw theirs
    # frame by frame -- the same noise code, a different order of the same stream.)
    rng = np.random.default_rng(seed)
    d = {k: getattr(quiet(UnitErrors.draw(rng)), k) for k in UnitErrors.__dataclass_fields__}
    model = SensorModel(UnitErrors(**(d | {"hard_iron_G": np.array([0.3, 0.0, 0.0])})), FIELD)
    # ... and right-angle ones, whose exact (and negative) zeros show a sum's sign of zero
    right = [np.eye(3), -np.eye(3) * [1.0, 1.0, -1.0], euler_to_dcm(0.5 * math.pi, 0.0, 0.0)]
    Rs = np.concatenate([random_rotations(rng, 300), right])
    acc = rng.normal(0.0, 0.3, size=(len(Rs), 3))
    for lin in (None, acc):
        whole = model.sample(Rs, rng, lin)
        ones = [model.sample(R, rng, None if lin is None else lin[i]) for i, R in enumerate(Rs)]
        for f in ("mag_counts", "acc_counts", "saturated", "mag_body_G", "acc_body_g"):
            got = np.concatenate([getattr(s, f) for s in ones])
            assert np.array_equal(got, getattr(whole, f)), f
            assert got.dtype == getattr(whole, f).dtype
            assert got.tobytes() == getattr(whole, f).tobytes(), f  # zeros' signs too
        assert whole.saturated.any() and not whole.saturated.all()


def test_saturation_flag_and_will_clip() -> None:
    # 0.5 G of hard iron along x: pointing north the x channel passes 4095, south it does not
    e = UnitErrors(hard_iron_G=np.array([0.5, 0.0, 0.0]))
    model = SensorModel(e, FIELD)
    rng = np.random.default_rng(0)
    north = model.sample(euler_to_dcm(0.0, 0.0, 0.0), rng)
    south = model.sample(euler_to_dcm(0.0, 0.0, math.pi), rng)
    assert north.mag_counts[0, 0] == 4095 and north.saturated[0]
    assert south.mag_counts[0, 0] < 4095 and not south.saturated[0]
    assert model.will_clip()
    assert not SensorModel(UnitErrors.ideal(), FIELD).will_clip()
    # the low rail counts too
    low = SensorModel(UnitErrors(mag_adc_zero=np.array([-2458.0, 0.0, 0.0])), FIELD)
    s = low.sample(euler_to_dcm(0.0, 0.0, math.pi), rng)
    assert s.mag_counts[0, 0] == 0 and s.saturated[0]
    assert low.will_clip()


@pytest.mark.parametrize("seed", range(8))
def test_headroom_is_the_true_worst_case(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    e = quiet(UnitErrors.draw(rng, hard_iron_frac=(0.0, 0.2)))
    model = SensorModel(e, FIELD)
    room = model.headroom()
    M = e.soft_iron @ e.mag_rotation
    bnorm = float(np.linalg.norm(FIELD))
    for i in range(3):
        # turn the unit so the body field lies along row i of M: channel i is at its maximum
        want = M[i] / np.linalg.norm(M[i]) * bnorm
        axis = np.cross(FIELD, want)
        ang = math.atan2(float(np.linalg.norm(axis)), float(FIELD @ want))
        R = axis_angle_to_dcm(axis, ang).T  # R.T @ FIELD == want
        np.testing.assert_allclose(R.T @ FIELD, want, atol=1e-12)
        top = model.sample(R, rng).mag_counts[0, i]
        if room.mag_high[i] > 1.0:
            assert abs((4094.5 - room.mag_high[i]) - top) <= 0.5
        else:
            assert top == 4095
    # and no random attitude beats the bound
    s = model.sample(random_rotations(rng, 2000), rng)
    assert (s.mag_counts.max(axis=0) <= 4094.5 - room.mag_high + 0.5).all()
    assert (s.mag_counts.min(axis=0) >= room.mag_low).all()
    assert bool(s.saturated.any()) <= model.will_clip()


def test_noise_statistics() -> None:
    e = UnitErrors(mag_noise_G=0.002, acc_noise_g=0.004)
    model = SensorModel(e, FIELD)
    rng = np.random.default_rng(7)
    s = model.sample(np.broadcast_to(np.eye(3), (4000, 3, 3)), rng)
    mag_sd = s.mag_counts.std(axis=0)
    acc_sd = s.acc_counts.std(axis=0)
    np.testing.assert_allclose(mag_sd, 0.002 * 2560, rtol=0.06)  # 5.1 counts
    np.testing.assert_allclose(acc_sd, 0.004 * 491.5, rtol=0.08)  # 2.0 counts
    np.testing.assert_allclose(s.mag_counts.mean(axis=0), 2458 + 2560 * FIELD, atol=0.3)
    # white and independent across channels
    c = np.asarray(np.corrcoef(s.mag_counts.T))
    assert np.abs(c[np.triu_indices(3, 1)]).max() < 0.06
    lag = np.asarray(np.corrcoef(s.mag_counts[:-1, 0], s.mag_counts[1:, 0]))[0, 1]
    assert abs(lag) < 0.06


def test_draw_is_reproducible_and_within_its_bounds() -> None:
    a = UnitErrors.draw(np.random.default_rng(42))
    b = UnitErrors.draw(np.random.default_rng(42))
    c = UnitErrors.draw(np.random.default_rng(43))
    assert np.array_equal(a.soft_iron, b.soft_iron) and np.array_equal(a.hard_iron_G, b.hard_iron_G)
    assert not np.array_equal(a.hard_iron_G, c.hard_iron_G)
    field = 0.5
    for seed in range(30):
        e = UnitErrors.draw(np.random.default_rng(seed), field_G=field)
        h = float(np.linalg.norm(e.hard_iron_G))
        assert 0.1 * field - 1e-12 <= h <= 0.3 * field + 1e-12
        assert math.degrees(float(np.linalg.norm(dcm_to_rotvec(e.mag_rotation)))) <= 2.0 + 1e-9
        assert np.abs(e.mag_adc_zero).max() <= 100 and np.abs(e.acc_adc_zero).max() <= 100
        assert np.abs(e.acc_offset_g).max() <= 0.02
        # gains 1 +- 10 %, soft iron +- 3 %: the sensitivity along each axis stays in range
        sens = np.linalg.norm(e.soft_iron, axis=1)
        assert ((sens > 0.8) & (sens < 1.2)).all()
        assert e.mag_noise_G == 0.0005 and e.acc_noise_g == 0.001
    ideal = UnitErrors.ideal()
    assert np.array_equal(ideal.soft_iron, np.eye(3)) and ideal.mag_noise_G == 0.0


def test_default_site_field_is_a_mid_latitude_field() -> None:
    f = default_field_ned_G()
    total = float(np.linalg.norm(f))
    dip = math.degrees(math.atan2(f[2], math.hypot(f[0], f[1])))
    assert DEFAULT_LOCATION[0] == pytest.approx(47.397742)
    assert 0.45 < total < 0.52 and 60.0 < dip < 67.0
    m = SensorModel.at_location(UnitErrors.ideal())
    np.testing.assert_allclose(m.field_ned_G, f)


def test_a_hard_iron_change_moves_the_counts_and_the_true_calibration() -> None:
    from bridge.sim.physics import DEFAULT_LOCATION

    model = SensorModel.at_location(UnitErrors.draw(np.random.default_rng(4)), DEFAULT_LOCATION)
    delta = np.array([0.01, -0.03, 0.02])
    changed = model.with_hard_iron_change(delta)
    R = np.stack([np.eye(3)] * 5)
    # same noise draws: only the hard iron differs
    a = model.sample(R, np.random.default_rng(1))
    b = changed.sample(R, np.random.default_rng(1))
    np.testing.assert_allclose(b.mag_counts - a.mag_counts, np.tile(2560.0 * delta, (5, 1)), atol=1)
    np.testing.assert_array_equal(a.acc_counts, b.acc_counts)
    off = changed.errors.true_calibration().mag.offset_array
    np.testing.assert_allclose(off - model.errors.true_calibration().mag.offset_array, delta)
    assert model.errors.hard_iron_G is not changed.errors.hard_iron_G  # the unit is untouched


def test_a_magnet_going_by_peaks_and_falls_with_the_cube_of_the_distance() -> None:
    from bridge.sim.physics import magnet_pass

    t = np.array([10.0, 11.0, 12.0, 20.0])
    f = magnet_pass(t, 10.0, 0.5, (0.0, 3.0, 4.0), closest_m=1.0, speed_mps=1.0)
    np.testing.assert_allclose(f[0], [0.0, 0.3, 0.4])
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 0.5 / np.hypot(1.0, t - 10.0) ** 3)
    # through the sensor: in the counts, not in the ideal body field
    model = SensorModel(UnitErrors.ideal(), [0.2, 0.0, 0.4])
    s = model.sample(np.stack([np.eye(3)] * 4), np.random.default_rng(0), None, f / 5.0)
    np.testing.assert_allclose(s.mag_body_G, np.tile([0.2, 0.0, 0.4], (4, 1)))
    np.testing.assert_allclose(s.mag_counts[0, 1:] - s.mag_counts[3, 1:], [153.6, 204.8], atol=1)
    with pytest.raises(ValueError, match="non-zero"):
        magnet_pass(t, 0.0, 0.1, (0.0, 0.0, 0.0))
