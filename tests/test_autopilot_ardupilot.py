"""The heading feed inside the real ArduPilot: Rover SITL's EKF3 takes its yaw from the bridge.

One ArduPilot run serves the whole module (a module-scoped fixture): the
ArduPilot Rover SITL from ``../shared/autopilots/ardupilot`` with EKF3's yaw on
external navigation (``EK3_SRC1_YAW = 6``, compass off) and every stream rate of
its companion port at zero (MAV2_*); the bridge in the companion role beside it,
its simulated compass lying still at a true heading different from the simulated
vehicle's. On one timeline:

1. steady state: the bridge starts once EKF3 has its tilt, and ArduPilot's yaw is
   compared with the fed heading for 30 s;
2. a learned drift correction of 5 deg (the drift monitor's path: the calibration
   controller, source "learned") while ArduPilot is disarmed: the bridge resets
   EKF3's yaw (EKF source set 2, then 1);
3. ArduPilot armed: a mounting change and a learned step are refused (STATUSTEXT on
   the GCS link, the event, the log), nothing reaches EKF3;
4. disarmed again: the mounting change (AHRS_ORIENTATION: yaw 45) is applied and
   ArduPilot's yaw follows;
5. the bridge restarts (a new process would do the same: the feed's clock is the
   wall clock), now without ``[location]``: it asks ArduPilot for its position
   (ArduPilot's companion stream rates are zero) and the lag ArduPilot's
   ``JitterCorrection`` gives the feed is compared with the fresh link's.

Everything is measured from ArduPilot's own dataflash log (XKF1: EKF3's yaw and
gyro bias, VISP: every vision sample received, the corrected time, Ignored) and its
ATTITUDE on the GCS link. docs/mavlink.md quotes the figures these tests print.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import companion_bridge as companion
import pytest
from autopilots import (
    ARDUPILOT_FEED_PARAMS,
    ARDUPILOT_HOME,
    SETTLE_S,
    Autopilot,
    M,
    check_all,
    dataflash,
    start_ardupilot,
)
from companion_bridge import Bridge, start_bridge
from waiting import wait_for

from bridge.app.calibration.store import LEARNED_SOURCE
from bridge.core.wmm import earth_field

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HOME = ARDUPILOT_HOME
COMPASS_YAW = 200.0  #: the compass lies still at this true heading (the vehicle points 120)
LEARNED_STEP_DEG = 5.0
MOUNT_PARAM, MOUNT_YAW45 = "AHRS_ORIENTATION", 1.0  # ArduPilot Rotation 1: yaw 45
#: The companion port's stream rates all zero (MAV2_ is SERIAL1's channel in 4.7).
SILENT_COMPANION = {
    f"MAV2_{s}": 0
    for s in (
        "RAW_SENS",
        "EXT_STAT",
        "RC_CHAN",
        "RAW_CTRL",
        "POSITION",
        "EXTRA1",
        "EXTRA2",
        "EXTRA3",
        "PARAMS",
        "ADSB",
    )
}
BRIDGE = (1, 200)
RESTART_SIGMA_DEG = 8.0


@dataclass
class Timeline:
    """What happened when (Unix time), and what was seen."""

    bridge_start: float = 0.0
    learned_at: float = 0.0
    learned_settled: float = 0.0  #: from here the bridge's record holds the learned heading
    armed_at: float = 0.0
    refused_mount: Any = None  #: PARAM_VALUE echo of the refused mounting change
    refused_learned: str = ""  #: the learned step's refusal
    disarmed_at: float = 0.0
    mount_at: float = 0.0
    mount_settled: float = 0.0  #: from here the bridge's record holds the new mounting's
    noise_at: float = 0.0  #: VISO_YAW_M_NSE lowered
    restart_at: float = 0.0
    position_at: float | None = None  #: the restarted bridge learned the position
    request_lines: list[str] = field(default_factory=list)
    end: float = 0.0
    statustexts: list[str] = field(default_factory=list)
    bridge_heading: list[tuple[float, float]] = field(default_factory=list)
    sent_feed: list[int] = field(default_factory=list)  #: the first bridge's feed stamps
    sent_sigma_b: list[float] = field(default_factory=list)  #: the second's yaw sigmas (rad)
    attitude: list[tuple[float, float]] = field(default_factory=list)  #: (unix, yaw deg)
    log: dict[str, list[Any]] = field(default_factory=dict)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Timeline]:
    work = tmp_path_factory.mktemp("ardupilot")
    params = {**ARDUPILOT_FEED_PARAMS, **SILENT_COMPANION}
    ap: Autopilot = start_ardupilot(work / "ap", params, home=HOME)
    tl = Timeline()
    bridges: list[Bridge] = []
    try:
        obs = ap.observer
        obs.set_message_interval(ap.target, M.MAVLINK_MSG_ID_ATTITUDE, 20.0)
        obs.wait("STATUSTEXT", lambda m: "tilt alignment complete" in m.text)
        location = HOME[:3]
        endpoint = f"udpin:127.0.0.1:{ap.companion_port}"
        tl.bridge_start = time.time()
        a = start_bridge(
            work / "bridge-a",
            endpoint,
            feed="ardupilot_vision",
            location=location,
            compass_at=location,
            yaw_deg=COMPASS_YAW,
        )
        bridges.append(a)
        # 1. steady state: 30 s of fusion after the first second
        time.sleep(32.5)
        # 2. a learned drift correction of 5 deg, ArduPilot disarmed
        cal = companion.learned_calibration(a, LEARNED_STEP_DEG)
        tl.learned_at = time.time()
        out = a.daemon.bridge.calibrator.apply_calibration(
            cal, source=LEARNED_SOURCE, write_device=False
        )
        assert out.ok, out
        time.sleep(SETTLE_S)
        tl.learned_settled = time.time()
        time.sleep(3.0)
        # 3. armed: a mounting change and a learned step are refused
        ack = obs.command(ap.target, M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == M.MAV_RESULT_ACCEPTED, ack
        wait_for(lambda: a.out.autopilot.armed, "the bridge to see ArduPilot armed", 5.0, step=0.05)
        tl.armed_at = time.time()
        tl.refused_mount = companion.set_bridge_parameter(obs, BRIDGE[0], MOUNT_PARAM, MOUNT_YAW45)
        refused = a.daemon.bridge.calibrator.apply_calibration(
            companion.learned_calibration(a, 2.0), source=LEARNED_SOURCE, write_device=False
        )
        tl.refused_learned = "" if refused.ok else refused.message
        time.sleep(1.0)
        ack = obs.command(ap.target, M.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        assert ack.result == M.MAV_RESULT_ACCEPTED, ack
        wait_for(
            lambda: not a.out.autopilot.armed,
            "the bridge to see ArduPilot disarmed",
            5.0,
            step=0.05,
        )
        tl.disarmed_at = time.time()
        time.sleep(0.5)
        # 4. disarmed: the mounting change goes through and ArduPilot follows
        tl.mount_at = time.time()
        echo = companion.set_bridge_parameter(obs, BRIDGE[0], MOUNT_PARAM, MOUNT_YAW45)
        assert echo.param_value == MOUNT_YAW45, echo
        time.sleep(SETTLE_S)
        tl.mount_settled = time.time()
        time.sleep(4.0)
        tl.bridge_heading = list(a.recorder.samples)
        tl.sent_feed = list(a.sent_feed)
        # 5. the bridge restarts, without [location], with a yaw sigma of 8 deg, and
        # VISO_YAW_M_NSE lowered to 0.05 rad: what ArduPilot then logs is the bridge's sigma
        a.stop()
        bridges.remove(a)
        tl.noise_at = time.time()
        obs.mav.param_set_send(1, 1, b"VISO_YAW_M_NSE", 0.05, M.MAV_PARAM_TYPE_REAL32)
        obs.wait("PARAM_VALUE", lambda m: m.param_id == "VISO_YAW_M_NSE")
        tl.restart_at = time.time()
        b = start_bridge(
            work / "bridge-b",
            endpoint,
            feed="ardupilot_vision",
            location=None,
            compass_at=location,
            yaw_deg=COMPASS_YAW,
            mavlink={"heading_feed_sigma_deg": RESTART_SIGMA_DEG},
        )
        bridges.append(b)
        wait_for(
            lambda: b.daemon.bridge.settings.field is not None,
            "a position from ArduPilot",
            20.0,
            step=0.05,
        )
        tl.position_at = time.time()
        tl.request_lines = [ln for ln in b.log if "asking it for" in ln]
        time.sleep(6.0)
        tl.end = time.time()
        tl.bridge_heading += list(b.recorder.samples)
        tl.sent_sigma_b = list(b.sent_sigma)
        tl.statustexts = [
            m.text for _, m in obs.history("STATUSTEXT", lambda m: m.get_srcComponent() == 200)
        ]
        tl.attitude = [
            (t - time.monotonic() + time.time(), math.degrees(m.yaw))
            for t, m in obs.history("ATTITUDE", lambda m: m.get_srcComponent() == 1)
        ]
    finally:
        for br in bridges:
            br.stop()
        ap.stop()
    logs = ap.logs("logs/*.BIN")
    assert logs, f"no dataflash log in {ap.workdir}:\n{ap.console_text()[-2000:]}"
    tl.log = dataflash(logs[-1], ["XKF1", "VISP"])
    yield tl


# ------------------------------------------------------------------------------ reading the log


def _ap_time(tl: Timeline) -> tuple[float, float]:
    """(offset, lag): Unix time = ArduPilot's TimeUS / 1e6 + offset, from VISP's remote
    stamps (the bridge's wall clock) less the link's transit (the minimum)."""
    visp = tl.log["VISP"]
    d = [m.RTimeUS / 1e6 - m.TimeUS / 1e6 for m in visp]
    return min(d) if d else 0.0, 0.0


def _yaw_series(tl: Timeline) -> list[tuple[float, float, float]]:
    """EKF3 core 0: (Unix time, yaw deg, z gyro bias deg/s)."""
    off, _ = _ap_time(tl)
    return [(m.TimeUS / 1e6 + off, m.Yaw, m.GZ) for m in tl.log["XKF1"] if m.C == 0]


def _fed(tl: Timeline) -> list[tuple[float, float]]:
    """The fed heading as ArduPilot logged it: (Unix time received, yaw deg)."""
    off, _ = _ap_time(tl)
    return [(m.TimeUS / 1e6 + off, m.Y % 360.0) for m in tl.log["VISP"]]


def _bridge_at(tl: Timeline, t: float) -> float | None:
    return companion.heading_at(tl.bridge_heading, t)


def _window(series: list[tuple[float, float, float]], t0: float, t1: float) -> list[Any]:
    return [s for s in series if t0 <= s[0] < t1]


# ------------------------------------------------------------------------------ the tests


def check_ardupilot_fuses_the_feed_at_once_and_holds_it(run: Timeline) -> None:
    """Within 2 s of the first packet EKF3's yaw is on the fed heading; over the next 30 s
    it stays within 0.3 deg RMS of it; every sample the bridge sent is logged as used."""
    fed = _fed(run)
    assert fed, "ArduPilot logged no vision sample"
    first = fed[0][0]
    series = _yaw_series(run)
    aligned = next(
        t for t, y, _ in series if t >= first and abs(companion.angle_diff(y, fed[0][1])) < 1.0
    )
    print(
        f"ArduPilot: first VISP {first - run.bridge_start:.2f} s after the bridge started, "
        f"yaw on the fed heading {aligned - first:.2f} s after it"
    )
    assert aligned - first < 2.0
    t0 = aligned + 1.0
    errs = [
        companion.angle_diff(y, f)
        for t, y, _ in _window(series, t0, t0 + 30.0)
        if (f := companion.heading_at(fed, t)) is not None
    ]
    rms = math.sqrt(statistics.fmean(e * e for e in errs))
    print(
        f"ArduPilot steady state: {len(errs)} XKF1 rows, yaw - fed RMS {rms:.3f} deg, "
        f"max {max(abs(e) for e in errs):.3f} deg"
    )
    assert len(errs) > 300 and rms < 0.3
    # every sample the first bridge sent arrived, and ArduPilot used it (VISP.Ign 0)
    visp = {m.RTimeUS: m for m in run.log["VISP"]}
    # (before ArduPilot's first datagram the bridge's udpin has no peer to send to)
    sent = [u for u in run.sent_feed if u >= min(visp)]
    missing = [u for u in sent if u not in visp]
    ignored = [u for u in sent if u in visp and visp[u].Ign != 0]
    print(
        f"ArduPilot: {len(sent) - len(missing)} of {len(sent)} samples the bridge sent logged, "
        f"{len(ignored)} ignored"
    )
    assert sent and not missing and not ignored, [
        round(u / 1e6 - run.bridge_start, 2) for u in missing
    ]


def check_the_yaw_noise_arduPilot_uses_is_the_bridges_sigma_floored_at_viso_yaw_m_nse(
    run: Timeline,
) -> None:
    """VISP.AErr is the angErr ArduPilot computed from the covariance and floored at
    VISO_YAW_M_NSE: 0.2 rad (the default) for the bridge's 2 deg, below that floor; the
    bridge's own sigma once VISO_YAW_M_NSE is 0.05 rad (8 deg with the tilt's heading
    error in quadrature: each one ArduPilot logs is one the bridge sent)."""
    # RTimeUS is the bridge's own time stamp of the sample: the wall clock
    visp = run.log["VISP"]
    # (the old bridge's last sample may reach ArduPilot in the loop that applies the SET)
    before = {round(m.AErr, 4) for m in visp if m.RTimeUS / 1e6 < run.noise_at - 0.5}
    after = {round(m.AErr, 4) for m in visp if m.RTimeUS / 1e6 > run.restart_at}
    print(
        f"ArduPilot VISP.AErr: {sorted(before)} with BRG_YAW_SIGMA 2 and VISO_YAW_M_NSE 0.2; "
        f"{sorted(after)} with 8 and 0.05 (8 deg = {math.radians(RESTART_SIGMA_DEG):.4f} rad)"
    )
    assert before == {0.2}
    meant = {round(sg, 4) for sg in run.sent_sigma_b}
    assert after and after <= meant, (after, sorted(meant))
    assert min(after) >= round(math.radians(RESTART_SIGMA_DEG), 4)


def check_a_learned_correction_resets_a_disarmed_ardupilots_yaw_without_moving_its_gyro_bias(
    run: Timeline,
) -> None:
    step = companion.angle_diff(
        companion.mean_heading(run.bridge_heading, run.learned_settled, run.armed_at),
        companion.mean_heading(run.bridge_heading, run.learned_at - 1.0, run.learned_at),
    )
    assert abs(step - LEARNED_STEP_DEG) < 0.3, step
    series = _yaw_series(run)
    before = _window(series, run.learned_at - 5.0, run.learned_at)
    after = _window(series, run.learned_at, run.armed_at)
    bias0 = statistics.fmean(g for *_, g in before)
    errs = [
        (t, companion.angle_diff(y, b))
        for t, y, _ in after
        if (b := _bridge_at(run, t)) is not None
    ]
    late = [(t, e) for t, e in errs if abs(e) > 1.0]
    followed = max((t for t, _ in late), default=run.learned_at) - run.learned_at
    overshoot = companion.overshoot_deg(
        [(t, y) for t, y, _ in after], run.bridge_heading, run.learned_settled, step
    )
    bias_move = max(abs(g - bias0) for *_, g in after)
    print(
        f"ArduPilot after a learned {step:.2f} deg step (disarmed, yaw reset): within 1 deg "
        f"of the bridge's heading {followed:.2f} s after the step, then stays; overshoot "
        f"{overshoot:.2f} deg; gyro-z bias moved {bias_move:.4f} deg/s"
    )
    assert followed < 1.0
    assert overshoot < 1.0  # a noisy sample: EKF3 realigns to one sample
    assert bias_move < 0.1
    assert any("yaw reset" in s for s in run.statustexts)


def check_heading_changes_are_refused_while_ardupilot_is_armed(run: Timeline) -> None:
    echo = run.refused_mount
    assert echo.param_value == 0.0, echo  # the SET is answered with the unchanged value
    assert "armed" in run.refused_learned
    assert any("refused" in s and "armed" in s for s in run.statustexts), run.statustexts
    series = _yaw_series(run)
    armed = _window(series, run.armed_at, run.disarmed_at)
    ref = _bridge_at(run, run.armed_at)
    assert ref is not None
    worst = max(abs(companion.angle_diff(y, ref)) for _, y, _ in armed)
    print(f"ArduPilot armed: yaw stayed within {worst:.2f} deg of the unchanged heading")
    assert worst < 1.0


def check_an_operator_change_reaches_a_disarmed_ardupilot_within_seconds(run: Timeline) -> None:
    step = companion.angle_diff(
        companion.mean_heading(run.bridge_heading, run.mount_settled, run.restart_at),
        companion.mean_heading(run.bridge_heading, run.disarmed_at, run.mount_at),
    )
    assert abs(abs(step) - 45.0) < 1.0, step
    series = _yaw_series(run)
    after = _window(series, run.mount_at, run.restart_at)
    errs = [
        (t, companion.angle_diff(y, b))
        for t, y, _ in after
        if (b := _bridge_at(run, t)) is not None
    ]
    late = [t for t, e in errs if abs(e) > 5.0]
    within5 = (max(late) - run.mount_at) if late else 0.0
    overshoot = companion.overshoot_deg(
        [(t, y) for t, y, _ in after], run.bridge_heading, run.mount_settled, step
    )
    print("ArduPilot yaw after a 45 deg mounting change (t s: yaw - bridge deg):")
    for t, e in errs[:: max(1, len(errs) // 40)]:
        print(f"  {t - run.mount_at:5.2f}: {e:+7.2f}")
    print(f"within 5 deg after {within5:.2f} s, overshoot {overshoot:.2f} deg")
    assert within5 < 5.0
    assert overshoot < 1.0


def check_a_restarted_bridge_keeps_ardupilots_lag_and_asks_for_the_position(
    run: Timeline,
) -> None:
    visp = run.log["VISP"]
    off, _ = _ap_time(run)

    def lag_ms(m: Any) -> float:
        return m.TimeUS / 1000.0 - m.CTimeMS  # ArduPilot's time of the sample vs arrival

    fresh = [
        lag_ms(m)
        for m in visp
        if run.bridge_start + 5 < m.TimeUS / 1e6 + off < run.bridge_start + 25
    ]
    again = [lag_ms(m) for m in visp if run.restart_at < m.TimeUS / 1e6 + off < run.end]
    print(
        f"ArduPilot lag correction: fresh link median {statistics.median(fresh):.1f} ms "
        f"(max {max(fresh):.1f}); after the restart median {statistics.median(again):.1f} ms "
        f"(max {max(again):.1f})"
    )
    # within 100 ms of the fresh link's, and none at JitterCorrection's 500 ms clamp
    assert abs(statistics.median(again) - statistics.median(fresh)) < 100.0
    assert max(again) < 400.0
    assert run.request_lines, "the bridge did not say it asked for the position"
    assert run.position_at is not None and run.position_at - run.restart_at < 10.0
    print(
        f"position from ArduPilot {run.position_at - run.restart_at:.1f} s after the restart; "
        f"{run.request_lines[0]}"
    )
    decl = earth_field(*HOME[:3]).declination_deg
    assert decl != 0.0


def test_the_heading_feed_inside_ardupilot(run: Any) -> None:
    """One run of the scenario, every check on it (see :func:`autopilots.check_all`)."""
    check_all(
        run,
        [
            check_ardupilot_fuses_the_feed_at_once_and_holds_it,
            check_the_yaw_noise_arduPilot_uses_is_the_bridges_sigma_floored_at_viso_yaw_m_nse,
            check_a_learned_correction_resets_a_disarmed_ardupilots_yaw_without_moving_its_gyro_bias,
            check_heading_changes_are_refused_while_ardupilot_is_armed,
            check_an_operator_change_reaches_a_disarmed_ardupilot_within_seconds,
            check_a_restarted_bridge_keeps_ardupilots_lag_and_asks_for_the_position,
        ],
    )
