"""The calibration controller's pure parts: collectors, device parameters, fixed yaw, reports.

Inputs are built from geometry and the simulator's physics (known hard iron,
known attitudes), so every expected value is derived independently of the
code under test.
"""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest
from harness import HarnessPort, LinkHarness, ScriptedCompass

from bridge.app.calibration.controller import (
    CalibrationController,
    CalibratorSettings,
    Outcome,
    Result,
)
from bridge.calibration.fits.accel_faces import Face
from bridge.calibration.fits.acceptance import Acceptance
from bridge.calibration.fits.coverage import section
from bridge.calibration.fits.fixed_yaw import fixed_yaw_calibration
from bridge.calibration.fits.methods import BEST, CalibrationData, fit, judge
from bridge.calibration.fits.sanity import orientation_confidence
from bridge.calibration.sessions.collect import (
    FaceCollector,
    MagCollector,
    StillCollector,
    counts_to_nominal,
    sphere_step,
)
from bridge.calibration.sessions.onboard import OnboardMagTracker
from bridge.calibration.sessions.report import Failure, SessionReport, fit_report
from bridge.calibration.sessions.state import Mode
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.core.geometry import axis_angle_to_dcm, euler_to_dcm, random_rotations
from bridge.core.mounting import Rotation, rotation_matrix
from bridge.events import EventBus
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    GmrDecoder,
    ParamsFrame,
    encode,
)
from bridge.sim.firmware import make_firmware
from bridge.sim.motion import AttitudeList, HandOnboardCalRotation, Sequence

B_NED = np.array([0.21, 0.01, 0.43])  # gauss, a mid-latitude field
V3 = tuple[float, float, float]


def _v(a: np.ndarray) -> V3:
    return (float(a[0]), float(a[1]), float(a[2]))


# -- nominal transfer and saturation --------------------------------------------------


def test_counts_to_nominal_and_saturation() -> None:
    mag, acc, sat = counts_to_nominal(2458 + 256, 2458, 2458 - 512, 2458, 2458, 2458 + 491)
    assert mag == pytest.approx((0.1, 0.0, -0.2))
    assert acc == pytest.approx((0.0, 0.0, 491 / 491.5))
    assert not sat
    for rail in (0, 4095):
        assert counts_to_nominal(rail, 2000, 2000, 2458, 2458, 2949)[2]
        assert counts_to_nominal(2000, 2000, 2000, 2458, rail, 2949)[2]


# -- MagCollector -----------------------------------------------------------------


def _sphere_samples(n: int, centre: np.ndarray, seed: int = 0) -> np.ndarray:
    R = random_rotations(np.random.default_rng(seed), n)
    return np.einsum("nji,j->ni", R, B_NED) + centre


def test_mag_collector_keeps_pairs_never_saturated_and_reaches_step_two() -> None:
    centre = np.array([0.05, -0.08, 0.12])
    col = MagCollector(capacity=60, seed=1)
    # a saturated frame is never kept, however new its direction
    assert not col.offer((1.0, 1.0, 1.0), (0.0, 0.0, 1.0), True)
    assert col.acceptor.counters.saturated == 1 and len(col) == 0
    x = _sphere_samples(4000, centre)
    for m in x:
        mv = _v(m)
        col.offer(mv, (2.0 * mv[0], 2.0 * mv[1], 2.0 * mv[2]), False)
        if col.full:
            break
    assert col.full and col.step == 1
    assert col.percent == pytest.approx(33.3)
    # step one's sphere: centre and radius of the field
    sph = sphere_step(col.acceptor.samples)
    assert sph is not None
    assert np.allclose(sph[0], centre, atol=1e-6) and sph[1] == pytest.approx(
        float(np.linalg.norm(B_NED)), abs=1e-6
    )
    removed = col.begin_step_two(*sph)
    assert removed > 0 and col.step == 2 and not col.full
    assert col.percent == pytest.approx(33.3)
    mag, acc = col.data()
    assert len(mag) == 60 - removed
    assert np.allclose(acc, 2.0 * mag)  # each accelerometer sample stayed with its frame
    # coverage is seen from the fitted centre: every kept sample's section is marked
    hit = {section(m - centre) for m in mag}
    assert hit == set(col.sections_hit)
    assert bin(int.from_bytes(col.mask, "little")).count("1") == len(hit)


def test_mag_collector_direction_hint_points_at_an_unvisited_section() -> None:
    centre = np.zeros(3)
    col = MagCollector(capacity=300)
    x = _sphere_samples(3000, centre, seed=2)
    upper = x[x[:, 2] > 0.1]  # only directions with the field pointing down-body
    for m in upper:
        col.offer(_v(m), (0.0, 0.0, 1.0), False)
        # asked every frame (as the snapshots ask): never a section reached since
        h = col.direction_hint()
        assert h == (0.0, 0.0, 0.0) or section(np.asarray(h)) not in col.sections_hit
    hint = np.asarray(col.direction_hint())
    assert float(np.linalg.norm(hint)) == pytest.approx(1.0)
    assert section(hint) not in col.sections_hit
    assert hint[2] < 0.5  # towards the unvisited (upper-body) half
    assert MagCollector().direction_hint() == (0.0, 0.0, 0.0)  # nothing known yet


# -- FaceCollector / StillCollector ---------------------------------------------------


def _face_frames(
    face: Face, t0: float, seconds: float, rate: float, rng: np.random.Generator
) -> list[tuple[float, V3]]:
    g = np.asarray(face.gravity_body) * 1.03 + np.array([0.02, -0.01, 0.03])  # an uncalibrated unit
    n = round(seconds * rate)
    return [(t0 + k / rate, _v(g + rng.normal(0.0, 0.002, 3))) for k in range(n)]


def test_face_collector_follows_px4_six_faces() -> None:
    rng = np.random.default_rng(3)
    col = FaceCollector(still_s=1.0, collect_s=1.5)
    notices: list[tuple[str, str]] = []
    t = 0.0
    order = [Face.LEVEL, Face.LEFT_SIDE, Face.NOSE_DOWN, Face.LEVEL, Face.UPSIDE_DOWN]
    order += [Face.RIGHT_SIDE, Face.NOSE_UP]
    for face in order:
        for tt, acc in _face_frames(face, t, 3.0, 20.0, rng):
            notices += [(n.kind, n.face.px4_side) for n in col.feed(tt, acc)]
        t += 3.0
        # turning to the next face: not still
        for k in range(20):
            a = rng.normal(0.0, 0.5, 3)
            notices += [(n.kind, n.face.px4_side) for n in col.feed(t + k / 20.0, _v(a))]
        t += 1.0
    assert notices == [
        ("detected", "down"),
        ("done", "down"),
        ("detected", "left"),
        ("done", "left"),
        ("detected", "front"),
        ("done", "front"),
        ("already_done", "down"),
        ("detected", "up"),
        ("done", "up"),
        ("detected", "right"),
        ("done", "right"),
        ("detected", "back"),
        ("done", "back"),
    ]
    assert col.done and col.percent == pytest.approx(100.0)
    want = np.asarray(Face.NOSE_DOWN.gravity_body) * 1.03 + np.array([0.02, -0.01, 0.03])
    assert np.allclose(col.means[Face.NOSE_DOWN], want, atol=0.002)


def test_face_collector_restarts_a_face_when_the_unit_moves() -> None:
    rng = np.random.default_rng(4)
    col = FaceCollector(still_s=1.0, collect_s=1.5)
    kinds = []
    for tt, acc in _face_frames(Face.LEVEL, 0.0, 1.5, 20.0, rng):  # detected, not yet done
        kinds += [n.kind for n in col.feed(tt, acc)]
    for k in range(5):  # a knock
        kinds += [n.kind for n in col.feed(1.5 + k / 20.0, (0.3, 0.2, 0.8))]
    assert kinds == ["detected", "moved"]
    assert Face.LEVEL not in col.means and col.current is None
    assert col.feed(2.0, (math.nan, 0.0, 1.0)) == []  # non-finite: ignored


def test_still_collector_means_and_motion() -> None:
    still = StillCollector(collect_s=1.0, still_tol_g=0.02)
    for k in range(11):
        still.feed(k / 10.0, (0.2, 0.0, 0.4), (0.01, 0.02, 0.99 + 0.001 * (k % 2)))
    assert still.complete and still.still
    mag, acc, _ = still.means()
    assert np.allclose(mag, (0.2, 0.0, 0.4)) and np.allclose(
        acc, (0.01, 0.02, 0.99 + 0.001 * 5 / 11)
    )
    moving = StillCollector(collect_s=1.0)
    for k in range(11):
        moving.feed(k / 10.0, (0.2, 0.0, 0.4), (0.1 * k, 0.0, 1.0))
    assert moving.complete and not moving.still


# -- OnboardMagTracker ------------------------------------------------------------------


class _Device:
    """Min/max as the datasheet's MAGCAL tracks it, for synthetic turns (counts)."""

    def __init__(self) -> None:
        self.xy: list[int] | None = None
        self.z: list[int] | None = None
        self.n = 0

    def see(self, m: tuple[int, int, int], where: str) -> None:
        if where == "level":
            if self.xy is None:
                self.xy = [m[0], m[0], m[1], m[1]]
            else:
                self.xy = [
                    min(self.xy[0], m[0]),
                    max(self.xy[1], m[0]),
                    min(self.xy[2], m[1]),
                    max(self.xy[3], m[1]),
                ]
        if where == "side":
            self.z = (
                [m[2], m[2]] if self.z is None else [min(self.z[0], m[2]), max(self.z[1], m[2])]
            )
        self.n += 1

    def report(self) -> CalProgressFrame:
        xy, z = self.xy or [0, 0, 0, 0], self.z or [0, 0]
        return CalProgressFrame(self.n, xy[0], xy[1], xy[2], xy[3], z[0], z[1])


LEVEL_ACC = (2458, 2458, 2949)  # level: +1 g on z
SIDE_ACC = (2458, 2949, 2458)  # right side down: +1 g on y


def _turn(
    tracker: OnboardMagTracker,
    dev: _Device,
    where: str,
    start_deg: float,
    degrees: float,
    rate_hz: int = 10,
) -> list[str]:
    """Turn from ``start_deg`` by ``degrees`` at 20 deg/s, with a $PGMRC report every second."""
    off = np.array([2600.0, 2300.0, 2500.0])
    h = 0.21 * 2560.0
    out: list[str] = []
    steps = round(degrees / 20.0 * rate_hz)
    for k in range(steps + 1):
        yaw = math.radians(start_deg + 20.0 * k / rate_hz)
        if where == "level":
            m = off + np.array([h * math.cos(yaw), -h * math.sin(yaw), 1100.0])
            acc = LEVEL_ACC
        else:
            m = off + np.array([h * math.cos(yaw), 1100.0, h * math.sin(yaw)])
            acc = SIDE_ACC
        mc = (int(m[0]), int(m[1]), int(m[2]))
        tracker.frame(*mc, *acc)
        dev.see(mc, where)
        if k % rate_hz == 0:
            what = tracker.progress(dev.report())
            if what:
                out.append(what)
    return out


def test_onboard_tracker_needs_both_full_turns() -> None:
    tr, dev = OnboardMagTracker(), _Device()
    assert tr.classify(*LEVEL_ACC) == "level" and tr.classify(*SIDE_ACC) == "side"
    assert tr.classify(2458, 2458 + 300, 2949 - 60) == "other"  # tilted 30 deg: neither
    # half a level turn, then a long pause: the spans stop growing but it is not a turn
    assert _turn(tr, dev, "level", 0.0, 180.0) == [] and tr.step == 1
    for _ in range(5):
        assert tr.progress(dev.report()) is None
    assert tr.percent < 40.0
    # the rest of the turn (and a little more): level done
    events = _turn(tr, dev, "level", 180.0, 240.0)
    assert events == ["level_done"] and tr.step == 2
    assert tr.level_swept >= 330.0
    assert tr.percent == pytest.approx(50.0, abs=1.0)
    # one full turn on the side: side done once the z span has settled
    events = _turn(tr, dev, "side", 0.0, 380.0)
    for _ in range(3):
        if tr.step == 2:
            events += [e for e in [tr.progress(dev.report())] if e]
    assert events == ["done"] and tr.step == 3
    assert min(tr.spans) >= 400


def test_onboard_tracker_is_not_fooled_by_a_half_turn_on_the_side() -> None:
    tr, dev = OnboardMagTracker(), _Device()
    assert _turn(tr, dev, "level", 0.0, 400.0) == ["level_done"]
    assert _turn(tr, dev, "side", 0.0, 200.0) == []
    for _ in range(5):
        assert tr.progress(dev.report()) is None
    assert tr.step == 2 and 50.0 <= tr.percent < 90.0


def test_onboard_tracker_uses_the_device_level_reference() -> None:
    # A device whose flash level reference is tilted: it judges "level" by that page.
    page = ParamsFrame(2458, 2458, 2458, 1, 1, 1, 2458.0, 2458.0 + 250.0, 2949.5)
    tr = OnboardMagTracker(page)
    assert tr.classify(2458, 2458 + 250, 2949) == "level"
    assert OnboardMagTracker().classify(2458, 2458 + 250, 2949) == "other"


def _routine(
    seed: int, motion: HandOnboardCalRotation, end_at: float | None = None, lead_s: float = 5.0
) -> tuple[OnboardMagTracker, list[tuple[float, str]], tuple[float, ...]]:
    """The simulated compass's own MAGCAL while ``motion`` plays (after ``lead_s`` level and
    still), followed by a tracker. ``MAGCAL,END`` goes to the compass when the tracker says
    "done", or at ``end_at`` (motion time) when given. Returns the tracker, what it said when
    (motion time, s), and the compass's answer to END (empty: none)."""
    still = AttitudeList([(0.0, 0.0, 0.0)], lead_s, 0.0)
    fw = make_firmware(seed, motion=Sequence([still, motion]), power_on_at=0.0)
    decoder, tracker = GmrDecoder(), OnboardMagTracker()
    said: list[tuple[float, str]] = []
    answer: tuple[float, ...] = ()
    t = lead_s - 1.0
    fw.receive(encode(CommandFrame.magcal_start()), t)
    ended = False
    while t < lead_s + motion.duration + 6.0:
        t += 0.01
        for f in decoder.feed(fw.poll(t)):
            if isinstance(f, AttitudeFrame):
                tracker.frame(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
            elif isinstance(f, CalProgressFrame):
                what = tracker.progress(f)
                if what:
                    said.append((t - lead_s, what))
                if what == "done" and end_at is None:
                    fw.receive(encode(CommandFrame.magcal_end()), t)
                    ended = True
            elif isinstance(f, AckFrame) and f.values:
                answer = f.values
        if end_at is not None and not ended and t >= lead_s + end_at:
            fw.receive(encode(CommandFrame.magcal_end()), t)
            ended = True
    return tracker, said, answer


def test_onboard_tracker_sees_the_routine_through_at_hand_pace() -> None:
    # The datasheet's motion as a person does it -- a level turn in about 15 s,
    # tipped 90 deg to the right in 3 s, a turn on the side in about 15 s.
    hand = HandOnboardCalRotation(turn_s=15.0, tip_s=3.0, yaw0=0.3, seed=7)
    tr, said, answer = _routine(7, hand)
    assert [w for _, w in said] == ["level_done", "done"] and tr.step == 3
    (t_level, _), (t_done, _) = said
    assert t_level <= hand.turn_s + 1.5  # before the tip
    # ended near the end of the side turn: not before 300 deg, at most 2.5 s after it
    assert hand.side_turned_deg(t_done) >= 300.0 and t_done <= hand.duration + 2.5
    assert min(tr.spans) >= 400
    # nothing was left to see: the compass computes what it would after the whole motion
    _, _, waited = _routine(7, hand, end_at=hand.duration + 1.0)
    assert len(answer) == 6 and answer == waited
    # The tip moves the field against the side turn: the path's net angle about the
    # device's centre stays under the 330 deg a turn needs (the measure that never ended
    # this routine); how far round it reached does not.
    last = tr.history[-1]
    assert tr.side_axis == 0
    centre = np.array([(last.xmin + last.xmax) / 2.0, (last.zmin + last.zmax) / 2.0])
    p = np.array([(x, z) for x, _, z in tr.side_points]) - centre
    steps = np.diff(np.arctan2(p[:, 1], p[:, 0]))
    net = abs(math.degrees(float(((steps + math.pi) % (2 * math.pi) - math.pi).sum())))
    assert net < 330.0 <= tr.side_swept


def test_onboard_tracker_waits_while_a_turn_is_short() -> None:
    hand = HandOnboardCalRotation(turn_s=15.0, tip_s=3.0, yaw0=0.3, seed=7, side_turn_deg=300.0)
    tr, said, answer = _routine(7, hand)
    assert [w for _, w in said] == ["level_done"] and tr.step == 2 and answer == ()
    assert tr.side_swept < 330.0 and 50.0 < tr.percent < 99.0


# -- device parameters -----------------------------------------------------------------


def test_device_params_from_a_host_calibration() -> None:
    R = axis_angle_to_dcm((0.3, -0.2, 0.9), math.radians(2.0))  # a little alignment
    S = np.diag([1.10, 0.99, 1.21])
    cal = AffineCalibration.from_arrays((0.1, -0.05, 0.02), R @ S)
    page = Calibration(mag=cal).device_page(ParamsFrame(1, 2, 3, 1, 1, 1, 2400.0, 2500.0, 2900.0))
    assert (page.xoff, page.yoff, page.zoff) == (2714.0, 2330.0, 2509.2)  # 2458 + 2560 * offset
    assert (
        page.kx == 1.0
        and page.ky == pytest.approx(0.9, abs=1e-4)
        and page.kz == pytest.approx(1.1, abs=1e-4)
    )
    assert page.values() == (2714.0, 2330.0, 2509.2, 1.0, 0.9, 1.1, 2400.0, 2500.0, 2900.0)
    with pytest.raises(ValueError, match="outside the device"):
        Calibration(mag=AffineCalibration.from_arrays((1.0, 0.0, 0.0), np.eye(3))).device_page()
    with pytest.raises(ValueError, match="Kz"):
        Calibration(
            mag=AffineCalibration.from_arrays((0, 0, 0), np.diag([1.0, 1.0, 20.0]))
        ).device_page()


# -- fixed yaw ---------------------------------------------------------------------------


@pytest.mark.parametrize("orient", [Rotation.ROTATION_NONE, Rotation.ROTATION_YAW_90])
def test_fixed_yaw_recovers_the_hard_iron(orient: Rotation) -> None:
    hard = np.array([0.07, -0.11, 0.05])
    mnt = rotation_matrix(orient)  # sensor -> vehicle
    M = np.diag([1.0, 1.0, 1.0])
    yaw_deg, roll, pitch = 123.0, math.radians(4.0), math.radians(-7.0)
    R = euler_to_dcm(roll, pitch, math.radians(yaw_deg))  # vehicle -> NED
    raw_mag = mnt.T @ (R.T @ B_NED) + hard  # what a unit with this hard iron reads
    raw_acc = mnt.T @ (R.T @ np.array([0.0, 0.0, 1.0]))
    cal = fixed_yaw_calibration(raw_mag, raw_acc, yaw_deg, B_NED, Calibration(), mnt)
    assert np.allclose(cal.mag.offset, hard, atol=1e-9)
    assert np.allclose(cal.mag.matrix_array, M)
    # the matrix in use is kept, and the offset accounts for it
    scaled = Calibration(mag=AffineCalibration.from_arrays((0, 0, 0), 1.2 * np.eye(3)))
    raw2 = mnt.T @ (R.T @ B_NED) / 1.2 + hard
    cal2 = fixed_yaw_calibration(raw2, raw_acc, yaw_deg, B_NED, scaled, mnt)
    assert np.allclose(cal2.mag.offset, hard, atol=1e-9)
    assert np.allclose(cal2.mag.matrix_array, 1.2 * np.eye(3))
    with pytest.raises(ValueError):
        fixed_yaw_calibration(raw_mag, np.zeros(3), yaw_deg, B_NED, Calibration())


# -- COMPASS_CAL_FIT ------------------------------------------------------------------


@functools.cache
def _fitted(sigma_G: float) -> tuple[CalibrationData, CalibrationResult]:
    """4000 sphere samples with ``sigma_G`` of noise and the best method's fit of them, not
    yet judged: each is judged against several limits below (deterministic, never changed)."""
    rng = np.random.default_rng(1)
    R = random_rotations(rng, 4000)
    mag = np.einsum("nji,j->ni", R, B_NED) + np.array([0.05, -0.08, 0.1])
    mag += rng.normal(0.0, sigma_G, mag.shape)
    acc = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, 1.0]))
    data = CalibrationData(mag, acc, reference=float(np.linalg.norm(B_NED)))
    return data, fit(BEST, data)


def _judged(sigma_G: float, limit_mG: float) -> CalibrationResult:
    """The best method on 4000 sphere samples with ``sigma_G`` of noise, COMPASS_CAL_FIT = limit
    (``calibrate``: the fit, judged)."""
    data, fitted = _fitted(sigma_G)
    return judge(fitted, data, Acceptance(fitness_max_mG=limit_mG))


def test_the_fitness_limit_is_compass_cal_fit() -> None:
    # ~10 mG of noise: a fit ArduPilot's default 16 mG passes ...
    ok = _judged(0.01, 16.0)
    assert ok.report.ok and 5.0 < ok.report.fitness_mG < 16.0
    assert _judged(0.01, 100.0).report.ok
    # ... and a limit under its fitness fails, saying why and what to do
    strict = _judged(0.01, 5.0)
    assert strict.report.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    assert strict.report.reason.startswith(
        f"fitness {ok.report.fitness_mG:.2f} mG above COMPASS_CAL_FIT 5.0: keep iron away"
    )
    assert strict.report.notes[0] == strict.report.reason
    assert strict.calibration == ok.calibration
    # ~20 mG: over the default, within QGroundControl's 100 during its calibration --
    # where 4000 samples determine the offsets as well as that noise allows
    rough = _judged(0.02, 16.0)
    assert rough.report.status == "MAG_CAL_FAILED_RESIDUALS_HIGH" and rough.report.fitness_mG > 16.0
    relaxed = _judged(0.02, 100.0)
    assert relaxed.report.ok, relaxed.report.reason
    assert relaxed.report.predicted_heading_deg <= relaxed.report.heading_limit_deg


# -- orientation confidence and reports ------------------------------------------------


def test_orientation_confidence_tells_right_from_wrong() -> None:
    Rs = random_rotations(np.random.default_rng(5), 300)
    mag = np.einsum("nji,j->ni", Rs, B_NED) + np.random.default_rng(6).normal(0, 5e-4, (300, 3))
    grav = np.einsum("nji,j->ni", Rs, np.array([0.0, 0.0, 1.0]))
    assert orientation_confidence(mag, grav) > 100.0
    flipped = mag @ rotation_matrix(Rotation.ROTATION_ROLL_180).T  # compass mounted upside down
    assert orientation_confidence(flipped, grav) < 0.01
    assert math.isnan(orientation_confidence(mag[:5], grav[:5]))


def test_a_fit_report_holds_ardupilots_figures_and_reads_back_from_json() -> None:
    cal = Calibration(
        mag=AffineCalibration.from_arrays((0.1, -0.2, 0.05), np.diag([1.1, 0.9, 1.0]))
    )
    rep = fit_report(
        Mode.MAG,
        cal.mag,
        CalibrationReport("ellipsoid_aligned", fitness_mG=1.5, radius_G=0.48),
        autosaved=True,
        confidence=12.0,
    )
    assert rep.ok and rep.failure is None and rep.autosaved
    assert rep.mag is not None and rep.fit is not None
    # COMPASS_OFS is added to the raw field: the negated offset, in mG
    assert rep.mag.ofs_mG == pytest.approx((-100.0, 200.0, -50.0))
    assert rep.mag.scale == pytest.approx(1.0) and rep.mag.diag[:2] == pytest.approx((1.1, 0.9))
    assert rep.fit.fitness_mG == 1.5 and rep.fit.radius_mG == pytest.approx(480.0)
    assert rep.fit.orientation_confidence == 12.0
    d = rep.to_dict()
    assert (d["ofs_x"], d["ofs_y"], d["ofs_z"]) == pytest.approx((-100.0, 200.0, -50.0))
    assert d["status"] == "success" and d["fitness"] == 1.5 and d["autosaved"] is True
    assert d["coverage_pct"] is None  # NaN becomes null
    back = SessionReport.from_dict(json.loads(json.dumps(d, allow_nan=False)))
    assert back.mag == rep.mag and back.fit is not None
    assert back.fit.fitness_mG == 1.5 and math.isnan(back.fit.coverage_pct)
    assert (back.mode, back.method, back.autosaved, back.notes) == (
        rep.mode,
        rep.method,
        rep.autosaved,
        rep.notes,
    )
    # a fit's failing verdict, in the calibrator's neutral terms, with its reason
    bad = fit_report(
        Mode.MAG,
        cal.mag,
        CalibrationReport(
            "ellipsoid_aligned",
            status="MAG_CAL_BAD_RADIUS",  # the older spelling of MAG_CAL_FAILED_RADIUS
            notes=("accelerometer: given", "field radius 990 mG outside 150-950 mG"),
        ),
    )
    assert bad.failure is Failure.RADIUS and bad.reason.startswith("field radius 990")
    again = SessionReport.from_dict(bad.to_dict())
    assert again.failure is Failure.RADIUS and again.reason == bad.reason


def test_a_reports_rotation_reads_back_as_its_angle() -> None:
    """The JSON form keeps the fit's rotation as an angle (what front ends show); read
    back, the report's ArduPilot figures turn by the same angle."""
    R = axis_angle_to_dcm((0.3, -0.2, 0.9), math.radians(2.5))
    mag = AffineCalibration.from_arrays((0.1, -0.05, 0.02), R @ np.diag([1.1, 0.9, 1.0]))
    rep = fit_report(Mode.MAG, mag, CalibrationReport("ellipsoid_aligned", fitness_mG=1.5))
    d = rep.to_dict()
    assert rep.mag is not None and d["rotation_deg"] == pytest.approx(2.5, abs=1e-9)
    back = SessionReport.from_dict(json.loads(json.dumps(d)))
    assert back.mag is not None and back.mag.rotation_deg == pytest.approx(2.5, abs=1e-9)
    assert (back.mag.ofs_mG, back.mag.diag) == (rep.mag.ofs_mG, rep.mag.diag)


def test_outcome_and_settings_validation() -> None:
    assert Outcome(Result.IN_PROGRESS).ok and not Outcome(Result.DENIED, "busy").ok
    assert Outcome(Result.FAILED, "x").to_dict() == {
        "result": "failed",
        "ok": False,
        "message": "x",
    }
    with pytest.raises(ValueError):
        CalibratorSettings(timeout_s=0.0)
    with pytest.raises(ValueError):
        CalibratorSettings(capacity=5)


# -- the controller on its own: bad input never crashes it ------------------------------


def _frame(
    seq: int, m: tuple[int, int, int], a: tuple[int, int, int], flags: int = 0
) -> AttitudeFrame:
    return AttitudeFrame(seq, 0.0, 0.0, 0.0, *m, *a, Flags(flags))


def test_bad_commands_get_clear_answers_and_junk_is_ignored() -> None:
    bus = EventBus()
    seen: list[str] = []
    bus.subscribe(lambda e: seen.append(e.kind))
    ctl = CalibrationController(AttitudeEngine(), bus)  # host only: no link, no store
    ctl.run_inline()  # no worker thread: nothing here needs one
    with ctl:
        assert ctl.start_mag(mask=2).result is Result.FAILED  # no compass 1 here
        assert ctl.start_mag(mask=1.5).result is Result.FAILED
        assert ctl.start_mag(delay_s=math.nan).result is Result.FAILED
        assert ctl.start_mag(delay_s=-1.0).result is Result.FAILED
        out = ctl.start_mag(onboard=True)
        assert out.result is Result.FAILED and "no device link" in out.message
        assert ctl.fixed_yaw("north").result is Result.FAILED  # type: ignore[arg-type]  # a name, not degrees
        bad = ctl.fixed_yaw(10.0, latitude_deg=95.0, longitude_deg=0.0)
        assert bad.result is Result.FAILED and "bad position" in bad.message
        assert "no position" in ctl.fixed_yaw(10.0).message
        assert ctl.cancel(mask=0.0).result is Result.ACCEPTED
        assert ctl.accept(mask=1.0).result is Result.ACCEPTED
        for junk in (None, "x", b"\x00", 3.0, CalProgressFrame(1, 0, 0, 0, 0, 0, 0)):
            ctl.feed(junk)
        # a running calibration never keeps a saturated frame
        assert ctl.start_mag(mask=1.0).ok
        for k in range(60):
            ctl.feed(_frame(k, (4095, 2000 + 20 * k, 2400), (2458, 2458, 2949)))
            ctl.feed(_frame(k, (2000 + 20 * k, 1800, 2400), (2458, 2458, 2949), int(Flags.SAT)))
        snap = ctl.snapshot()
        assert snap.running and snap.completion_pct == 0.0
        assert ctl.start_accel().result is Result.DENIED
        assert ctl.cancel().ok
        assert ctl.errors == 0
    assert seen.count("calibration.started") == 1 and seen.count("calibration.cancelled") == 1
    assert "calibration.failed" not in seen


def test_heading_only_compass_cannot_be_calibrated() -> None:
    link = HarnessPort(LinkHarness(ScriptedCompass(), protocol="nmea", rate_hz=None))
    ctl = CalibrationController(AttitudeEngine(), EventBus(), link=link)
    ctl.run_inline()
    with ctl:
        for out in (ctl.start_mag(), ctl.start_accel(), ctl.start_level(), ctl.fixed_yaw(0.0)):
            assert out.result is Result.FAILED and "heading-only" in out.message
