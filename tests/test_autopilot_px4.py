"""The heading feed inside the real PX4: EKF2 of PX4 v1.16 SITL (SIH) takes its yaw from the bridge.

One PX4 run serves the module: PX4 from ``../shared/autopilots/px4`` with
``EKF2_EV_CTRL = 8`` (yaw from external vision only), ``EKF2_MAG_TYPE = 5`` and
``SYS_HAS_MAG = 0`` (given as ``PX4_PARAM_*`` at start); the bridge in the
companion role on PX4's onboard link, its simulated compass lying still at a
true heading different from the simulated vehicle's. On one timeline:

1. steady state: 30 s of EKF2's yaw against the fed heading;
2. a learned drift correction of 5 deg: ``reset_counter`` moves, EKF2 resets;
3. an operator's mounting change (AHRS_ORIENTATION yaw 45 from the ground station,
   forwarded by PX4 to component 200): EKF2 follows;
4. the bridge restarts on its state directory against the running PX4 (its clock
   continues: wall time);
5. ``EKF2_EVA_NOISE`` lowered to 0.001 over MAVLink: the variance EKF2 then uses is
   the bridge's sigma^2.

Measured from PX4's own ulog (``vehicle_attitude``, ``vehicle_visual_odometry``,
``estimator_aid_src_ev_yaw``) and its console.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import companion_bridge as companion
import numpy as np
import pytest
from autopilots import SETTLE_S, Autopilot, M, check_all, start_px4, ulog
from companion_bridge import Bridge, start_bridge

from bridge.app.calibration.store import LEARNED_SOURCE

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HOME = (47.397742, 8.545594, 488.0)  #: SIH's default home (Zurich)
COMPASS_YAW = 200.0
MOUNT_PARAM, MOUNT_YAW45 = "AHRS_ORIENTATION", 1.0
SIGMA_DEG = 2.0
TOPICS = (
    "vehicle_attitude",
    "vehicle_visual_odometry",
    "estimator_aid_src_ev_yaw",
    "timesync_status",
)


@dataclass
class Timeline:
    """What happened when (Unix time) and what was seen."""

    bridge_start: float = 0.0
    learned_at: float = 0.0
    learned_settled: float = 0.0  #: from here the bridge's record holds the learned heading
    mount_at: float = 0.0
    mount_settled: float = 0.0  #: from here the bridge's record holds the new mounting's
    restart_at: float = 0.0
    noise_at: float = 0.0
    end: float = 0.0
    #: Unix time = PX4 time (s) + offset, the offset taken at PX4 times ``clock[0]``
    #: (``clock[1]``): PX4's clock and ours drift apart by tens of milliseconds a minute
    #: on a loaded machine, so one offset for the whole run would misplace the steps.
    clock: tuple[Any, Any] = ((0.0,), (0.0,))
    sent_sigma_b: list[float] = field(default_factory=list)  #: the second bridge's sigmas (rad)
    console: str = ""
    bridge_heading: list[tuple[float, float]] = field(default_factory=list)
    log: dict[str, dict[str, Any]] = field(default_factory=dict)


def _yaw_of(q0: Any, q1: Any, q2: Any, q3: Any) -> Any:
    return np.degrees(np.arctan2(2 * (q0 * q3 + q1 * q2), 1 - 2 * (q2 * q2 + q3 * q3)))


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Timeline]:
    work = tmp_path_factory.mktemp("px4")
    ap: Autopilot = start_px4(work / "px4", home=HOME)
    tl = Timeline()
    bridges: list[Bridge] = []
    try:
        obs = ap.observer
        endpoint = f"udpin:127.0.0.1:{ap.companion_port}"

        def bridge(name: str) -> Bridge:
            b = start_bridge(
                work / name,
                endpoint,
                feed="px4_odometry",
                location=HOME,
                compass_at=HOME,
                yaw_deg=COMPASS_YAW,
                system_id=ap.system_id,
                mavlink={"heading_feed_sigma_deg": SIGMA_DEG},
            )
            bridges.append(b)
            return b

        tl.bridge_start = time.time()
        a = bridge("bridge-a")
        time.sleep(32.0)
        # a learned drift correction of 5 deg
        tl.learned_at = time.time()
        out = a.daemon.bridge.calibrator.apply_calibration(
            companion.learned_calibration(a, 5.0), source=LEARNED_SOURCE, write_device=False
        )
        assert out.ok, out
        time.sleep(SETTLE_S)
        tl.learned_settled = time.time()
        time.sleep(3.0)
        # an operator's mounting change, from the ground station through PX4
        tl.mount_at = time.time()
        echo = companion.set_bridge_parameter(obs, ap.system_id, MOUNT_PARAM, MOUNT_YAW45)
        assert echo.param_value == MOUNT_YAW45, echo
        time.sleep(SETTLE_S)
        tl.mount_settled = time.time()
        time.sleep(3.0)
        tl.bridge_heading = list(a.recorder.samples)
        # the bridge restarts
        a.stop()
        bridges.remove(a)
        tl.restart_at = time.time()
        # on the same state directory, as a service restarts: the mounting the operator
        # set is in force from its first sample
        b = bridge("bridge-a")
        assert b.daemon.bridge.params.get(MOUNT_PARAM) == MOUNT_YAW45
        time.sleep(5.0)
        # EKF2_EVA_NOISE lowered: the variance EKF2 uses is then the bridge's
        tl.noise_at = time.time()
        since = time.monotonic()
        obs.mav.param_set_send(ap.system_id, 1, b"EKF2_EVA_NOISE", 0.001, M.MAV_PARAM_TYPE_REAL32)
        obs.wait(
            "PARAM_VALUE",
            lambda m: m.param_id == "EKF2_EVA_NOISE" and m.get_srcComponent() == 1,
            since=since,
        )
        time.sleep(3.0)
        tl.end = time.time()
        tl.bridge_heading += list(b.recorder.samples)
        tl.sent_sigma_b = list(b.sent_sigma)
        arrivals = obs.history("ATTITUDE", lambda m: m.get_srcComponent() == 1)
        now_mono, now_unix = time.monotonic(), time.time()
        tl.clock = _clock_map(
            [(m.time_boot_ms / 1000.0, t - now_mono + now_unix) for t, m in arrivals]
        )
    finally:
        for br in bridges:
            br.stop()
        ap.stop()
    tl.console = ap.console_text()
    logs = ap.logs("rootfs/log/*/*.ulg")
    assert logs, f"no ulog in {ap.workdir}:\n{tl.console[-2000:]}"
    tl.log = ulog(logs[-1], TOPICS)
    yield tl


def _clock_map(pairs: list[tuple[float, float]], span_s: float = 2.0) -> tuple[Any, Any]:
    """PX4 time -> Unix time offsets from (PX4 time, arrival) pairs: in each ``span_s`` of
    PX4 time the smallest (arrival - PX4 time), the least delayed message's."""
    by_span: dict[int, tuple[float, float]] = {}
    for px4_t, unix_t in pairs:
        k, off = int(px4_t // span_s), unix_t - px4_t
        if k not in by_span or off < by_span[k][1]:
            by_span[k] = (px4_t, off)
    anchors = sorted(by_span.values())
    assert anchors, "no ATTITUDE from PX4 to map its clock with"
    return np.array([a for a, _ in anchors]), np.array([o for _, o in anchors])


def _t(tl: Timeline, us: Any) -> Any:
    px4_t = np.asarray(us, dtype=float) / 1e6
    return px4_t + np.interp(px4_t, *tl.clock)


def _attitude(tl: Timeline) -> tuple[Any, Any]:
    a = tl.log["vehicle_attitude"]
    return _t(tl, a["timestamp"]), _yaw_of(a["q[0]"], a["q[1]"], a["q[2]"], a["q[3]"])


def _bridge_at(tl: Timeline, t: float) -> float | None:
    return companion.heading_at(tl.bridge_heading, t)


@dataclass
class Follow:
    """How EKF2 followed a step in the fed heading, measured on PX4's own clock."""

    took: float  #: PX4 seconds from the first stepped ODOMETRY until the yaw stays within tol
    overshoot: float  #: deg past the bridge's new heading, in the step's direction
    delivered: float  #: wall seconds from the bridge's step to that ODOMETRY's arrival
    reset: bool  #: that ODOMETRY's reset_counter moved: EKF2 resets rather than converges
    fed_off: float  #: deg, the fed yaw's mean after the step less the bridge's new heading


def _follow(tl: Timeline, t0: float, t1: float, settled: float, step: float, tol: float) -> Follow:
    """EKF2's yaw after the bridge's heading stepped by ``step`` at wall time ``t0``.

    The time to follow is taken on PX4's clock, from the first ODOMETRY that carries the
    step to the last attitude more than ``tol`` from the fed yaw in force: SITL runs in
    lockstep with SIH, so while the machine starves PX4 its clock stands still, and a
    bound in wall time would measure the machine. The bridge's part -- the step reaching
    PX4 -- is the wall time from its own record's step to that ODOMETRY's arrival.
    """
    vo = tl.log["vehicle_visual_odometry"]
    fed_px4 = np.asarray(vo["timestamp"], dtype=float) / 1e6
    fed_wall = _t(tl, vo["timestamp"])
    fed = _yaw_of(vo["q[0]"], vo["q[1]"], vo["q[2]"], vo["q[3]"])
    before = [(float(t), float(y)) for t, y in zip(fed_wall, fed, strict=True) if t < t0]
    old = companion.mean_heading(before, t0 - 1.0, t0, min_samples=5)
    stepped = [
        i
        for i in np.flatnonzero((fed_wall >= t0 - 0.5) & (fed_wall < t1))
        if abs(companion.angle_diff(float(fed[i]), old)) > abs(step) / 2
    ]
    assert stepped, "no ODOMETRY carried the step"
    i0 = int(stepped[0])
    s0, s1 = fed_px4[i0], fed_px4[np.flatnonzero(fed_wall < t1)[-1]]
    a = tl.log["vehicle_attitude"]
    att_px4 = np.asarray(a["timestamp"], dtype=float) / 1e6
    yaw = _yaw_of(a["q[0]"], a["q[1]"], a["q[2]"], a["q[3]"])
    sel = np.flatnonzero((att_px4 >= s0) & (att_px4 < s1))
    in_force = np.searchsorted(fed_px4, att_px4[sel], side="right") - 1
    late = [
        att_px4[k]
        for k, j in zip(sel, in_force, strict=True)
        if abs(companion.angle_diff(float(yaw[k]), float(fed[j]))) > tol
    ]
    ts = _t(tl, a["timestamp"])
    after = [(float(t), float(y)) for t, y in zip(ts, yaw, strict=True) if t0 <= t < t1]
    was = companion.mean_heading(tl.bridge_heading, t0 - 1.0, t0, min_samples=5)
    bridge_step = next(
        t
        for t, h in tl.bridge_heading
        if t >= t0 - 0.5 and abs(companion.angle_diff(h, was)) > abs(step) / 2
    )
    counter = vo["reset_counter"].astype(int)
    fed_after = [(float(t), float(y)) for t, y in zip(fed_wall, fed, strict=True)]
    return Follow(
        took=(float(max(late)) - s0) if late else 0.0,
        overshoot=companion.overshoot_deg(after, tl.bridge_heading, settled, step),
        delivered=float(fed_wall[i0]) - bridge_step,
        reset=bool(i0 > 0 and counter[i0] != counter[i0 - 1]),
        # (what PX4 follows is what it was fed: that must be the bridge's heading, whole)
        fed_off=companion.angle_diff(
            companion.mean_heading(fed_after, settled, t1, min_samples=5),
            companion.mean_heading(tl.bridge_heading, settled, t1, min_samples=5),
        ),
    )


def check_px4_fuses_the_feed_at_once_and_holds_it(run: Timeline) -> None:
    vo = run.log["vehicle_visual_odometry"]
    ev = run.log["estimator_aid_src_ev_yaw"]
    first = float(min(_t(run, vo["timestamp"][0]), _t(run, ev["timestamp"][0])))
    fused_t = _t(run, ev["timestamp"])[ev["fused"].astype(bool)]
    print(
        f"PX4: first ODOMETRY {first - run.bridge_start:.2f} s after the bridge started, "
        f"first fused {max(0.0, fused_t[0] - first):.2f} s after it"
    )
    assert fused_t[0] - first < 2.0
    ts, yaw = _attitude(run)
    fed_t = _t(run, vo["timestamp"])
    fed = _yaw_of(vo["q[0]"], vo["q[1]"], vo["q[2]"], vo["q[3]"])
    t0 = fused_t[0] + 1.0
    sel = (ts >= t0) & (ts < t0 + 30.0)
    idx = np.searchsorted(fed_t, ts[sel], side="right") - 1
    errs = [companion.angle_diff(y, fed[i]) for y, i in zip(yaw[sel], idx, strict=True) if i >= 0]
    rms = math.sqrt(statistics.fmean(e * e for e in errs))
    print(
        f"PX4 steady state: {len(errs)} attitudes, yaw - fed RMS {rms:.3f} deg, "
        f"max {max(abs(e) for e in errs):.3f} deg"
    )
    assert len(errs) > 300 and rms < 0.3
    # Every sample from the first fused one to the learned step is fused (the few before it
    # are rejected by the innovation gate until EKF2 has reset its yaw to the feed).
    t_ev = _t(run, ev["timestamp"])
    fused = ev["fused"].astype(bool)
    span = (t_ev >= fused_t[0]) & (t_ev < run.learned_at)
    in_span = (fed_t >= fused_t[0]) & (fed_t < run.learned_at)
    n_fed = int(np.sum(in_span))
    rejected_first = int(np.sum(~fused[t_ev < fused_t[0]]))
    print(
        f"PX4: {int(np.sum(fused[span]))} of {n_fed} ODOMETRY samples fused from the first "
        f"fused one to the learned step; {rejected_first} rejected before EKF2's yaw reset"
    )
    # Every sample sent reached EKF2, but those PX4's own clock bunched: SITL runs in
    # lockstep with SIH, so while PX4 is starved of CPU its time stands still and samples
    # the bridge sent 100 ms apart arrive a 4 ms step apart on it; EKF2 drops one that comes
    # within its minimum observation interval of the last ("EV data too fast",
    # EstimatorInterface::setExtVisionData). With none bunched, all of them reached it.
    sampled = np.asarray(vo["timestamp_sample"], dtype=float)[in_span]
    bunched = int(np.sum(np.diff(sampled) < 50_000))  # under half the feed's 100 ms, in us
    print(f"PX4: {bunched} ODOMETRY samples within 50 ms of the one before on PX4's clock")
    assert -1 <= n_fed - int(np.sum(span)) <= 1 + bunched
    # Held: on a quiet machine every one is fused (317/317, 319/319 alone). With the suite's
    # other real-time tests on the same two cores, EKF2 leaves a few unfused (309/315, and
    # 308/315 with 7 in a row, seen; which of PX4 or the bridge ran late is not known):
    # at least 95 % fused and never a second (10 samples at the feed's 10 Hz) without one.
    fed_span = fused[span]
    runs = np.diff(np.flatnonzero(np.diff(np.r_[1, fed_span.astype(int), 1]) != 0))[::2]
    longest = int(runs.max()) if runs.size else 0
    assert np.mean(fed_span) >= 0.95 and longest <= 10, (np.mean(fed_span), longest)


def check_a_learned_correction_and_an_operator_change_are_followed_by_px4(run: Timeline) -> None:
    step = companion.angle_diff(
        companion.mean_heading(
            run.bridge_heading, run.learned_settled, run.mount_at, min_samples=5
        ),
        companion.mean_heading(
            run.bridge_heading, run.learned_at - 1.0, run.learned_at, min_samples=5
        ),
    )
    assert abs(step - 5.0) < 0.3, step
    f = _follow(run, run.learned_at, run.mount_at, run.learned_settled, step, 1.0)
    print(
        f"PX4 after a learned {step:.2f} deg step: reached PX4 {f.delivered:.2f} s after the "
        f"bridge's step (reset_counter moved: {f.reset}), within 1 deg of it {f.took:.2f} s "
        f"later on PX4's clock, overshoot {f.overshoot:.2f} deg, fed - bridge "
        f"{f.fed_off:+.3f} deg after it"
    )
    # EKF2 resets its yaw to a sample whose reset_counter moved (at once, on its own clock);
    # converging through the innovation gate instead would take seconds.
    assert f.reset and f.took < 0.5 and f.overshoot < 1.0 and abs(f.fed_off) < 0.2, f
    assert f.delivered < 1.0, f  # the bridge's 10 Hz feed, through a loaded machine
    step = companion.angle_diff(
        companion.mean_heading(
            run.bridge_heading, run.mount_settled, run.restart_at, min_samples=5
        ),
        companion.mean_heading(run.bridge_heading, run.mount_at - 1.0, run.mount_at, min_samples=5),
    )
    assert abs(abs(step) - 45.0) < 1.0, step
    f = _follow(run, run.mount_at, run.restart_at, run.mount_settled, step, 5.0)
    f1 = _follow(run, run.mount_at, run.restart_at, run.mount_settled, step, 1.0)
    print(
        f"PX4 after a {step:.1f} deg mounting change: reached PX4 {f.delivered:.2f} s after "
        f"the bridge's step (reset_counter moved: {f.reset}), within 5 deg of it "
        f"{f.took:.2f} s later on PX4's clock, within 1 deg {f1.took:.2f} s, overshoot "
        f"{f.overshoot:.2f} deg, fed - bridge {f.fed_off:+.3f} deg after it"
    )
    assert f.reset and f.took < 0.5 and f.overshoot < 1.0 and abs(f.fed_off) < 0.2, f
    assert f.delivered < 1.0, f


def check_a_restarted_bridge_is_no_time_jump_for_px4(run: Timeline) -> None:
    assert "time jump" not in run.console, run.console[-3000:]
    vo = run.log["vehicle_visual_odometry"]
    ev = run.log["estimator_aid_src_ev_yaw"]
    # On PX4's clock: the restarted bridge's first sample is where reset_counter changes
    # nearest the restart (it starts again from the steps of its own start-up; the other
    # changes are the learned step and the mounting, seconds before). Mapping the restart
    # onto the wall clock would mix the two bridges' samples by the map's tens of ms.
    vo_us = np.asarray(vo["timestamp"], dtype=np.int64)
    changes = np.flatnonzero(np.diff(vo["reset_counter"].astype(int)) != 0) + 1
    assert len(changes), "reset_counter never changed"
    first = int(changes[np.argmin(np.abs(_t(run, vo_us[changes]) - run.restart_at))])
    assert abs(float(_t(run, vo_us[first])) - run.restart_at) < 2.0, first
    age_ms = (vo_us - vo["timestamp_sample"])[first:] / 1000.0
    ev_us = np.asarray(ev["timestamp"], dtype=np.int64)
    fused_after = ev_us[(ev_us >= vo_us[first]) & ev["fused"].astype(bool)]
    gap = (vo_us[first] - vo_us[first - 1]) / 1e6
    took = (fused_after[0] - vo_us[first]) / 1e6
    print(
        f"PX4 after the bridge restarted: the feed's gap {gap:.2f} s, samples "
        f"{age_ms.max():.1f} ms old at most, first fused {took:.2f} s after the first "
        "sample (PX4's clock)"
    )
    assert age_ms.max() < 100.0
    assert took < 0.5
    # PX4's time sync (Timesync::update) resets itself when 5 round trips in a row deviate
    # from its estimate by more than MAX_DEVIATION_SAMPLE ("Time jump detected"): the
    # restarted bridge's clock continues, so the offset PX4 observes does not move.
    ts = run.log["timesync_status"]
    t_ts = _t(run, ts["timestamp"])
    observed = ts["observed_offset"].astype(float) / 1e6

    # The medians of the few seconds either side: one round trip that a busy machine delays
    # moves a single observation by tens of ms, and the offset drifts during a run (tens of
    # ms, restart or not: the further apart the windows, the larger); a restarted clock moves
    # them all by the bridge's uptime.
    # On a slow host PX4's SITL clock (in lockstep with SIH) also runs slower than the wall
    # clock the bridge stamps with -- 2.5-15 % on 27 Nov's slow VM, the offset moving 0.1-1 s
    # between the windows --, so the trend of the windows before the restart is taken out.
    def window(lo: float, hi: float) -> tuple[float, float]:
        sel = (t_ts > run.restart_at + lo) & (t_ts < run.restart_at + hi)
        return float(np.median(t_ts[sel])), float(np.median(observed[sel]))

    t_early, early = window(-10.0, -7.0)
    t_before, before = window(-3.0, 0.0)
    t_after, after = window(1.0, 4.0)
    drift = (before - early) / (t_before - t_early)  # s/s: PX4's clock against the wall
    moved = abs(after - before)
    jump = abs(after - (before + drift * (t_after - t_before)))
    print(
        f"PX4 time sync: observed offset moved by {moved * 1000:.1f} ms across the restart, "
        f"{jump * 1000:.1f} ms beside its drift before it ({drift * 1000:+.1f} ms/s)"
    )
    assert jump < 1.0  # a restarted clock: the bridge's whole uptime (40 s and more here)


def check_px4_uses_the_bridges_variance_above_ekf2_eva_noise(run: Timeline) -> None:
    ev = run.log["estimator_aid_src_ev_yaw"]
    t = _t(run, ev["timestamp"])
    var = ev["observation_variance"]
    default = np.unique(np.round(var[t < run.restart_at], 6))
    lowered = np.unique(np.round(var[t > run.noise_at + 1.0], 6))
    print(
        f"PX4 yaw observation variance: EKF2_EVA_NOISE 0.1 -> {default}, "
        f"0.001 -> {lowered} (BRG_YAW_SIGMA^2 = {math.radians(SIGMA_DEG) ** 2:.6f}, with the "
        "tilt's heading error in quadrature)"
    )
    assert list(default) == [0.1]
    # each variance EKF2 used is one the bridge sent (PX4 logs it as a float32)
    meant = [sg * sg for sg in run.sent_sigma_b]
    assert len(lowered) > 0 and meant
    for v in lowered:
        assert min(abs(float(v) - m) for m in meant) < 2e-6, (v, sorted(set(meant))[:5])
    assert min(lowered) >= round(math.radians(SIGMA_DEG) ** 2, 6) - 1e-6


def test_the_heading_feed_inside_px4(run: Any) -> None:
    """One run of the scenario, every check on it (see :func:`autopilots.check_all`)."""
    check_all(
        run,
        [
            check_px4_fuses_the_feed_at_once_and_holds_it,
            check_a_learned_correction_and_an_operator_change_are_followed_by_px4,
            check_a_restarted_bridge_is_no_time_jump_for_px4,
            check_px4_uses_the_bridges_variance_above_ekf2_eva_noise,
        ],
    )
