"""Motion scripts: ground truth, smoothness, and the coverage calibration relies on."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from bridge.core.geometry import dcm_to_rotvec, euler_to_dcm
from bridge.sim.drive import Drive
from bridge.sim.motion import (
    SIX_FACES,
    AttitudeList,
    HandOnboardCalRotation,
    HandShake,
    Motion,
    OnboardCalRotation,
    Sequence,
    Shaken,
    SixFaces,
    Still,
    Tumble,
    YawTurns,
    linear_acc_of,
    with_shake,
)
from bridge.sim.physics import default_field_ned_G

DOWN = np.array([0.0, 0.0, 1.0])


def rot_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(dcm_to_rotvec(Ra.T @ Rb))))


def assert_rotations(Rs: np.ndarray) -> None:
    """Every matrix of the stack ``Rs`` is a rotation (orthonormal, determinant +1), in one
    comparison of each kind (a test of hundreds of frames spent most of its time in calls)."""
    np.testing.assert_allclose(
        Rs @ Rs.transpose(0, 2, 1), np.broadcast_to(np.eye(3), Rs.shape), atol=1e-9
    )
    assert np.linalg.det(Rs) == pytest.approx(np.ones(len(Rs)), abs=1e-9)


# ---------------------------------------------------------------- geodesic grid (80 sections)


def _geodesic_sections() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Icosahedron (20 faces), each face split in 4: the 80 sections MAG_CAL_PROGRESS reports."""
    phi = (1 + 5**0.5) / 2
    v = []
    for a, b in itertools.product((-1.0, 1.0), (-phi, phi)):
        v += [(0.0, a, b), (a, b, 0.0), (b, 0.0, a)]
    V = np.array(v) / np.linalg.norm(v[0])
    faces = [
        f
        for f in itertools.combinations(range(12), 3)
        if all(V[i] @ V[j] > 0.4 for i, j in itertools.combinations(f, 2))
    ]
    assert len(faces) == 20

    def mid(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        m = p + q
        return m / np.linalg.norm(m)

    tris = []
    for i, j, k in faces:
        a, b, c = V[i], V[j], V[k]
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        tris += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
    return tris


SECTIONS = _geodesic_sections()
# inward-facing edge normals of each spherical triangle, for a vectorised point-in-triangle test
_EDGES = np.array(
    [
        [np.sign(np.cross(a, b) @ c) * np.cross(p, q) for p, q in ((a, b), (b, c), (c, a))]
        for a, b, c in SECTIONS
    ]
)  # (80, 3 edges, 3)


def sections_of(u: np.ndarray) -> set[int]:
    """The geodesic sections that directions ``u`` (N, 3) fall in."""
    inside = (np.einsum("sek,nk->nse", _EDGES, u) >= -1e-12).all(axis=2)  # (N, 80)
    assert inside.any(axis=1).all(), "a direction fell in no section"
    return set(np.argmax(inside, axis=1).tolist())


def test_geodesic_sections_tile_the_sphere() -> None:
    # the helper itself: every direction lands in exactly one section, all 80 are reachable
    rng = np.random.default_rng(0)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert len(sections_of(u)) == 80
    # and the sections are the same size (within the geodesic grid's 20 %): fair coverage cells
    counts = np.bincount(
        np.argmax((np.einsum("sek,nk->nse", _EDGES, u) >= 0).all(axis=2), axis=1), minlength=80
    )
    assert counts.min() > 0.4 * counts.mean()


# ---------------------------------------------------------------- simple scripts


def test_still_is_still() -> None:
    m = Still.from_deg(10.0, -20.0, 135.0)
    assert isinstance(m, Motion) and m.duration == math.inf
    np.testing.assert_allclose(m.attitude(0.0), m.attitude(1e4))
    roll, pitch, yaw = m.euler(3.0)
    assert (math.degrees(roll), math.degrees(pitch), math.degrees(yaw)) == pytest.approx(
        (10.0, -20.0, 135.0)
    )
    assert m.heading_deg(5.0) == pytest.approx(135.0)
    assert m.linear_acc_ned_g(1.0).tolist() == [0.0, 0.0, 0.0]


def test_yaw_turns() -> None:
    m = YawTurns(rate_dps=12.0, roll=math.radians(5.0), pitch=math.radians(-3.0))
    for t in (0.0, 7.5, 29.0, 45.0):
        assert m.heading_deg(t) == pytest.approx((12.0 * t) % 360.0, abs=1e-9)
        r, p, _ = m.euler(t)
        assert (math.degrees(r), math.degrees(p)) == pytest.approx((5.0, -3.0))
    # a turn about the vertical: gravity in body axes never changes
    g0 = m.attitude(0.0).T @ DOWN
    for t in np.linspace(0, 60, 13):
        np.testing.assert_allclose(m.attitude(float(t)).T @ DOWN, g0, atol=1e-12)


def test_attitude_list_dwells_and_turns_smoothly() -> None:
    eulers = [(0.0, 0.0, 0.0), (0.0, 0.0, math.radians(90.0)), (math.radians(30.0), 0.0, 0.0)]
    m = AttitudeList(eulers, dwell_s=2.0, transition_s=1.0)
    assert m.duration == pytest.approx(3 * 2.0 + 2 * 1.0)
    for i, e in enumerate(eulers):
        t = i * 3.0 + 1.0  # middle of a dwell
        np.testing.assert_allclose(m.attitude(t), euler_to_dcm(*e), atol=1e-12)
        assert m.segment_at(t) == i
    # half-way through the first transition: 45 deg from both ends (smooth-step is symmetric)
    mid = m.attitude(2.5)
    assert m.segment_at(2.5) is None
    assert rot_angle_deg(m.attitude(0.0), mid) == pytest.approx(45.0, abs=1e-6)
    assert rot_angle_deg(mid, m.attitude(3.5)) == pytest.approx(45.0, abs=1e-6)
    # continuous, with no step at the dwell/transition handovers
    ts = np.arange(0.0, m.duration, 0.01)
    steps = [rot_angle_deg(m.attitude(a), m.attitude(b)) for a, b in itertools.pairwise(ts)]
    assert max(steps) < 1.6  # peak rate 1.5 x 90 deg/s -> 1.35 deg per 10 ms
    # held at the end, and before the start
    np.testing.assert_allclose(m.attitude(1e6), euler_to_dcm(*eulers[-1]), atol=1e-12)
    np.testing.assert_allclose(m.attitude(-5.0), euler_to_dcm(*eulers[0]), atol=1e-12)
    with pytest.raises(ValueError):
        AttitudeList([], 1.0)
    with pytest.raises(ValueError):
        AttitudeList(eulers, dwell_s=-1.0)


def test_onboard_cal_rotation_matches_the_datasheet_routine() -> None:
    m = OnboardCalRotation(turn_s=20.0, tip_s=4.0, yaw0=math.radians(30.0))
    assert m.duration == pytest.approx(44.0)
    level_t = np.arange(0.0, 20.0, 0.1)
    side_t = np.arange(24.0, 44.0, 0.1)
    # level phase: gravity straight along +z (tilt 0), heading sweeps the full circle
    level_g = [m.attitude(float(t)).T @ DOWN for t in level_t]
    np.testing.assert_allclose(
        np.array(level_g), np.broadcast_to(DOWN, (len(level_t), 3)), atol=1e-12
    )
    assert all(m.phase_at(float(t)) == "level" for t in level_t)
    headings = np.array([m.heading_deg(float(t)) for t in level_t])
    assert np.histogram(headings, bins=36, range=(0, 360))[0].min() > 0
    # side phase: |gz| < 0.35 g, and body z sweeps every horizontal direction
    az = []
    for t in side_t:
        R = m.attitude(float(t))
        assert abs((R.T @ DOWN)[2]) < 0.35
        assert m.phase_at(float(t)) == "side"
        z_ned = R[:, 2]
        assert abs(z_ned[2]) < 1e-9  # horizontal
        az.append(math.degrees(math.atan2(z_ned[1], z_ned[0])) % 360.0)
    assert np.histogram(az, bins=36, range=(0, 360))[0].min() > 0
    # the tip is a continuous move from level to the side
    assert m.phase_at(22.0) == "tip"
    steps = [
        rot_angle_deg(m.attitude(a), m.attitude(b))
        for a, b in itertools.pairwise(np.arange(19.0, 25.0, 0.01))
    ]
    assert max(steps) < 0.4


def test_the_routine_at_hand_pace_keeps_the_datasheets_conditions_and_turns_fully() -> None:
    m = HandOnboardCalRotation(turn_s=15.0, tip_s=3.0, yaw0=0.3, wobble_deg=3.0, seed=2)
    assert m.duration == pytest.approx(15.0 + 1.0 + 3.0 + 1.0 + 15.0)
    assert m.side_starts_at == pytest.approx(20.0)
    ts = np.arange(0.0, m.duration, 0.05)
    phases = [m.phase_at(float(t)) for t in ts]
    assert [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]] == [
        "level",
        "pause",
        "tip",
        "pause",
        "side",
    ]
    assert m.phase_at(m.duration + 1.0) == "held"
    tilt, gz_side, level_yaw, side_az, Rs = [], [], [], [], []
    for t, p in zip(ts, phases, strict=True):
        R = m.attitude(float(t))
        Rs.append(R)
        g = R.T @ DOWN  # gravity in body axes
        if p == "level":
            tilt.append(math.degrees(math.acos(g[2])))
            level_yaw.append(m.heading_deg(float(t)))
        elif p == "side":
            gz_side.append(abs(g[2]))
            side_az.append(math.degrees(math.atan2(R[1, 2], R[0, 2])) % 360.0)
    assert_rotations(np.array(Rs))
    # the hand wobbles (never exactly level) but stays within the device's conditions
    assert 1.0 < max(tilt) <= 3.0 * math.sqrt(2.0) + 1e-9 < 20.0
    assert max(gz_side) < 0.35 and max(gz_side) > 0.01
    # one full turn level, one on the side: every 10-degree sector is swept
    assert np.histogram(level_yaw, bins=36, range=(0, 360))[0].min() > 0
    assert np.histogram(side_az, bins=36, range=(0, 360))[0].min() > 0
    # at rest at both ends of a turn, twice the mean rate half way
    rate = np.degrees(np.abs(np.diff(np.unwrap(np.radians(level_yaw))))) / 0.05
    assert rate[0] < 2.0 and rate[-1] < 2.0 and 40.0 < rate.max() < 50.0
    assert m.side_turned_deg(20.0) == 0.0 and m.side_turned_deg(35.0) == pytest.approx(360.0)
    assert m.side_turned_deg(27.5) == pytest.approx(180.0)
    # an "about" full turn and a seeded wobble
    short = HandOnboardCalRotation(15.0, side_turn_deg=300.0, seed=2)
    assert short.side_turned_deg(short.duration) == pytest.approx(300.0)
    other = HandOnboardCalRotation(15.0, 3.0, 0.3, wobble_deg=3.0, seed=3)
    assert rot_angle_deg(other.attitude(5.0), m.attitude(5.0)) > 0.1


def test_six_faces_put_each_axis_down() -> None:
    m = SixFaces(dwell_s=5.0, transition_s=3.0)
    # gravity in body axes on each face (datasheet sign: level reads +z)
    want = {
        "LEVEL": (0, 0, 1),
        "LEFT": (0, -1, 0),
        "RIGHT": (0, 1, 0),
        "NOSEDOWN": (1, 0, 0),
        "NOSEUP": (-1, 0, 0),
        "BACK": (0, 0, -1),
    }
    assert [name for name, _ in SIX_FACES] == list(want)
    seen = []
    for i in range(6):
        t = i * 8.0 + 2.5
        face = m.face_at(t)
        assert face is not None
        seen.append(face)
        np.testing.assert_allclose(m.attitude(t).T @ DOWN, want[face], atol=1e-12)
        assert m.face_at(i * 8.0 + 6.5) in (None, "BACK")  # turning (or the last face held)
    assert seen == list(want)
    assert m.face_at(6.5) is None
    assert m.duration == pytest.approx(6 * 5.0 + 5 * 3.0)


def test_sequence_and_shaken() -> None:
    a = AttitudeList([(0.0, 0.0, 0.0)], dwell_s=3.0)
    b = Shaken(Still.from_deg(0.0, 0.0, 90.0), amplitude_g=[0.0, 0.0, 0.2], freq_hz=2.0)
    s = Sequence([a, b])
    assert s.duration == math.inf
    assert s.heading_deg(1.0) == pytest.approx(0.0)
    assert s.heading_deg(4.0) == pytest.approx(90.0)
    assert linear_acc_of(s, 1.0).tolist() == [0.0, 0.0, 0.0]
    accs = np.array([linear_acc_of(s, 3.0 + t) for t in np.arange(0.0, 1.0, 0.01)])
    assert accs[:, 2].max() == pytest.approx(0.2, abs=0.01)
    assert accs[:, 2].min() == pytest.approx(-0.2, abs=0.01)
    assert np.abs(accs[:, :2]).max() == 0.0
    with pytest.raises(ValueError, match="endless"):
        Sequence([YawTurns(5.0), a])
    with pytest.raises(ValueError):
        Sequence([])


# ---------------------------------------------------------------- tumble


def test_tumble_is_smooth_at_its_rate_and_reproducible() -> None:
    m = Tumble(seed=3, rate_dps=40.0)
    ts = np.arange(0.0, 120.0, 0.02)
    Rs = m.attitudes(ts)
    assert_rotations(Rs[::500])
    # each step's rotation once: its angle is the rate, its vector the rate vector
    steps = [dcm_to_rotvec(a.T @ b) for a, b in itertools.pairwise(Rs)]
    rates = np.array([math.degrees(float(np.linalg.norm(v))) for v in steps]) / 0.02
    # human rate: the nominal speed (plus the slow spin), never a jump
    assert rates.min() > 0.95 * 40.0 and rates.max() < 1.15 * 40.0
    # smooth: the rate vector changes gradually (bounded angular acceleration)
    w = np.array(steps) / 0.02
    dw = np.degrees(np.linalg.norm(np.diff(w, axis=0), axis=1)) / 0.02
    assert dw.max() < 200.0  # deg/s^2
    np.testing.assert_allclose(Tumble(seed=3, rate_dps=40.0).attitude(77.7), m.attitude(77.7))
    assert rot_angle_deg(Tumble(seed=4, rate_dps=40.0).attitude(10.0), m.attitude(10.0)) > 1.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tumble_covers_every_section_in_a_minute(seed: int) -> None:
    field = default_field_ned_G()
    m = Tumble(seed=seed)  # default 45 deg/s, reference = the default site's field
    Rs = m.attitudes(np.arange(0.0, 60.0, 0.1))  # 10 Hz for 60 s
    b = np.einsum("nji,j->ni", Rs, field / np.linalg.norm(field))
    assert len(sections_of(b)) == 80
    octants = {tuple(u > 0) for u in b}
    assert len(octants) == 8
    # a finer equal-area grid (8 bands in z x 16 in azimuth = 128 cells, ~18 deg, finer than
    # the 24 deg between sweep turns): most of it is hit
    band = np.minimum(((b[:, 2] + 1.0) / 2.0 * 8).astype(int), 7)
    sector = (np.degrees(np.arctan2(b[:, 1], b[:, 0])) % 360.0 // 22.5).astype(int)
    assert len(set(zip(band.tolist(), sector.tolist(), strict=True))) >= 0.8 * 128
    # gravity moves over the body sphere too (accelerometer coverage)
    g = Rs[:, 2, :]
    assert len({tuple(u > 0) for u in g}) == 8


def test_tumble_for_another_field_covers_it_too() -> None:
    equator = np.array([0.3, -0.02, 0.01])  # an almost horizontal field
    m = Tumble(seed=9, rate_dps=50.0, reference_ned=equator)
    Rs = m.attitudes(np.arange(0.0, 60.0, 0.1))
    b = np.einsum("nji,j->ni", Rs, equator / np.linalg.norm(equator))
    assert len(sections_of(b)) == 80
    assert m.sweep_s < 60.0
    with pytest.raises(ValueError):
        Tumble(rate_dps=0.0)
    with pytest.raises(ValueError):
        Tumble(reference_ned=[0.0, 0.0, 0.0])


# ---------------------------------------------------------------- a hand's shake


def test_hand_shake_is_smooth_band_limited_and_seeded() -> None:
    base = Tumble(2, 45.0)
    m = HandShake(base, 0.05, seed=4)
    fs = 50.0
    t = np.arange(0.0, 600.0, 1.0 / fs)
    a = m.shake_g(t)
    # RMS per axis as asked, peaks about 2.4x of it and never beyond the bound
    np.testing.assert_allclose(np.sqrt(np.mean(a * a, axis=0)), 0.05, rtol=0.03)
    peak = float(np.abs(a).max())
    assert 2.0 * 0.05 < peak <= m.peak_bound_g == pytest.approx(0.05 * math.sqrt(6.0))
    # every axis has its power inside 0.4-2.5 Hz, none at the slow rates of a turn
    spec = np.abs(np.fft.rfft(a, axis=0)) ** 2
    f = np.fft.rfftfreq(t.size, 1.0 / fs)
    inside = spec[(f >= 0.39) & (f <= 2.51)].sum(axis=0)
    assert np.all(inside > 0.99 * spec.sum(axis=0))
    # smooth: the step between frames is the derivative's, no jumps
    assert float(np.abs(np.diff(a, axis=0)).max()) < 2.0 * math.pi * 2.5 * peak / fs
    # a pure function of t and the seed; the attitude is the base script's
    assert np.array_equal(HandShake(base, 0.05, seed=4).shake_g(t[:50]), a[:50])
    assert not np.array_equal(HandShake(base, 0.05, seed=5).shake_g(t[:50]), a[:50])
    np.testing.assert_array_equal(m.attitude(12.3), base.attitude(12.3))
    np.testing.assert_allclose(linear_acc_of(m, 7.25), m.shake_g([7.25])[0])
    assert m.duration == base.duration


def test_with_shake_and_bad_shakes() -> None:
    still = Still()
    assert with_shake(still, 0.0) is still
    shaken = with_shake(still, 0.1, seed=3)
    assert isinstance(shaken, HandShake) and shaken.rms_g == 0.1
    # a shaken sequence part keeps its shake
    s = Sequence([AttitudeList([(0.0, 0.0, 0.0)], dwell_s=2.0), shaken])
    assert np.abs(linear_acc_of(s, 1.0)).max() == 0.0
    assert np.abs(np.array([linear_acc_of(s, 2.0 + k / 20) for k in range(40)])).max() > 0.05
    for rms_g in (-0.1, math.nan):
        with pytest.raises(ValueError, match="rms_g"):
            HandShake(still, rms_g=rms_g)
    with pytest.raises(ValueError, match="band_hz"):
        HandShake(still, 0.05, band_hz=(2.5, 0.4))
    with pytest.raises(ValueError, match="tones"):
        HandShake(still, 0.05, tones=0)


# -- a driving vehicle ------------------------------------------------------------------


def test_drive_turns_everywhere_rolls_and_pitches_within_bounds() -> None:
    d = Drive(3)
    ts = np.arange(0.0, 600.0, 0.5)
    e = np.degrees(np.array([d.euler(float(t)) for t in ts]))
    assert np.abs(e[:, :2]).max() <= 15.0 + 1e-9
    assert np.abs(e[:, :2]).max() > 10.0  # it does roll and pitch
    octants = np.histogram(np.array([d.heading_deg(float(t)) for t in ts]), 8, (0, 360))[0]
    assert (octants > 0).all()  # ten minutes see every heading
    rates = [d.yaw_rate_dps(float(t)) for t in ts]  # (each time's asked once)
    straight = [r for r in rates if r == 0.0]
    assert 0.2 * len(ts) < len(straight) < 0.8 * len(ts)  # straights and turns
    assert max(abs(r) for r in rates) == pytest.approx(15.0, abs=0.5)


def test_drive_acceleration_is_the_derivative_of_the_velocity() -> None:
    # velocity v(t) (cos yaw, sin yaw) differentiated numerically: along-track speed
    # change plus the centripetal v * yaw rate, in g (NED)
    d = Drive(5)
    dt = 1e-4
    for t in np.arange(1.0, 300.0, 7.3):

        def vel(x: float) -> np.ndarray:
            yaw = math.radians(d.heading_deg(x))
            return d.speed(x)[0] * np.array([math.cos(yaw), math.sin(yaw), 0.0])

        want = (vel(t + dt) - vel(t - dt)) / (2 * dt) / 9.80665
        np.testing.assert_allclose(d.linear_acc_ned_g(float(t)), want, atol=1e-5)
    turning = max(np.linalg.norm(d.linear_acc_ned_g(float(t))) for t in np.arange(0, 300, 0.5))
    assert 0.2 < turning < 0.4  # about 10 m/s x 15 deg/s


def test_drive_is_a_pure_function_of_time() -> None:
    a, b = Drive(7), Drive(7)
    late = a.attitude(5000.0)  # drawn far ahead first ...
    early = a.attitude(12.0)
    np.testing.assert_array_equal(b.attitude(12.0), early)  # ... same as in order
    np.testing.assert_array_equal(b.attitude(5000.0), late)
    assert not np.array_equal(Drive(8).attitude(12.0), early)
    with pytest.raises(ValueError):
        Drive(1, max_roll_deg=90.0)


def test_drive_streams_are_its_samples_exactly() -> None:
    # the benchmarks draw whole streams at once: the same numbers as time by time,
    # including before the start (held) and in a fresh drive drawn out of order
    d = Drive(4)
    ts = np.concatenate([[-3.0], np.arange(0.0, 200.0, 0.1), [5000.0]])
    one = [float(t) for t in ts]
    np.testing.assert_array_equal(Drive(4).attitudes(ts[::-1])[::-1],
                                  np.stack([d.attitude(t) for t in one]))  # fmt: skip
    np.testing.assert_array_equal(Drive(4).linear_accs_ned_g(ts),
                                  np.stack([d.linear_acc_ned_g(t) for t in one]))  # fmt: skip
    assert Drive(4).attitudes([]).shape == (0, 3, 3)
