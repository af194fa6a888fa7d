"""The heading feed's ``reset_counter`` moves on the sample that carries the step (in memory).

PX4's EKF2 resets its yaw to the ODOMETRY sample whose ``reset_counter`` changed. A
frame solved with the old calibration (or mounting, or declination) but sent after the
change must keep the old counter, or EKF2 resets to the old heading and then has to
converge on the new one through its innovation gate: in PX4 SITL that took 0.64 s for
a 5 deg step, against 0.14 s for a reset (tests/test_autopilot_px4.py).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from harness import ManualClock
from test_mavlink_rig import offline_daemon
from test_mavlink_telemetry import decode

from bridge.app.sample import CompassSample
from bridge.core import sensor
from bridge.core.mounting import Mounting
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings

# A level unit heading 30 deg magnetic (NED field of 0.2 G north, 0.45 G down).
_YAW = math.radians(30.0)
_MAG = (0.2 * math.cos(_YAW), -0.2 * math.sin(_YAW), 0.45)
_M = sensor.gauss_to_mag_counts(np.array(_MAG))
_A = sensor.g_to_acc_counts(np.array((0.0, 0.0, 1.0)))
_COUNTS = (
    round(float(_M[0])),
    round(float(_M[1])),
    round(float(_M[2])),
    round(float(_A[0])),
    round(float(_A[1])),
    round(float(_A[2])),
)


def _feed(tmp_path: Path) -> tuple[Any, Any]:
    """(the settings, the MAVLink output's heading feed) of an offline companion bridge."""
    cfg, daemon = offline_daemon(tmp_path, "feed", role="companion", heading_feed="px4_odometry")
    out = MavlinkOutput(
        MavlinkSettings.from_config(cfg), daemon.bridge.services, clock=ManualClock(100.0)
    )
    settings = daemon.bridge.settings
    settings.subscribe(out.feed.on_settings)  # what MavlinkOutput.start subscribes
    return settings, out.feed


def _solved(settings: Any, t: float) -> CompassSample:
    """The unit's frame solved by the engine's configuration now."""
    a = settings.engine.solve_counts(*(float(c) for c in _COUNTS))
    return CompassSample.from_solution(a, t, raw_counts=_COUNTS)


def _odometry(feed: Any, s: CompassSample) -> tuple[int, float]:
    """(reset_counter, yaw in degrees) of the ODOMETRY the feed sends for ``s``."""
    m = decode(feed.odometry(s))
    w, x, y, z = m.q
    return m.reset_counter, math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def _turn(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def test_a_sample_solved_before_a_step_keeps_the_old_counter_and_the_next_carries_both(
    tmp_path: Path,
) -> None:
    settings, feed = _feed(tmp_path)
    counter0, yaw0 = _odometry(feed, _solved(settings, 1.0))
    # The pipeline solved a frame; the mounting changes (an operator's PARAM_SET) before
    # the feed sends that frame's sample.
    in_flight = _solved(settings, 2.0)
    settings.set_mounting(Mounting(trim_yaw_deg=45.0), "test")
    counter, yaw = _odometry(feed, in_flight)
    assert (counter, yaw) == (counter0, yaw0)  # the old heading, with the old counter
    counter, yaw = _odometry(feed, _solved(settings, 3.0))
    assert counter == counter0 + 1 and abs(abs(_turn(yaw, yaw0)) - 45.0) < 0.01
    assert _odometry(feed, _solved(settings, 4.0))[0] == counter0 + 1  # counted once


def test_two_steps_before_one_sample_move_the_counter_on_that_sample(tmp_path: Path) -> None:
    settings, feed = _feed(tmp_path)
    counter0, _ = _odometry(feed, _solved(settings, 1.0))
    settings.set_mounting(Mounting(trim_yaw_deg=45.0), "test")
    settings.set_mounting(Mounting(trim_yaw_deg=90.0), "test")
    counter, _ = _odometry(feed, _solved(settings, 2.0))
    # moved (by both: EKF2 resets on any change of the counter)
    assert counter == counter0 + 2


def test_a_change_that_is_no_heading_step_leaves_the_counter(tmp_path: Path) -> None:
    settings, feed = _feed(tmp_path)
    counter0, _ = _odometry(feed, _solved(settings, 1.0))
    settings.set_heading_reference("true", "test")  # (no declination known: no step either)
    settings.set_limits(settings.limits, "test")  # unchanged: no change at all
    assert _odometry(feed, _solved(settings, 2.0))[0] == counter0


def test_a_sample_solved_after_a_step_carries_it_before_any_listener_hears_of_it(
    tmp_path: Path,
) -> None:
    """The pipeline may solve and send a frame between the engine's swap and the settings'
    listeners hearing of the change: that sample has the new heading, so the new counter."""
    cfg, daemon = offline_daemon(tmp_path, "feed", role="companion", heading_feed="px4_odometry")
    feed = MavlinkOutput(
        MavlinkSettings.from_config(cfg), daemon.bridge.services, clock=ManualClock(100.0)
    ).feed
    settings = daemon.bridge.settings
    sent: list[tuple[int, float]] = []
    # subscribed ahead of the feed: what it sends was solved by the new configuration
    # before the feed heard of the change
    settings.subscribe(lambda _change: sent.append(_odometry(feed, _solved(settings, 2.0))))
    settings.subscribe(feed.on_settings)
    counter0, yaw0 = _odometry(feed, _solved(settings, 1.0))
    settings.set_mounting(Mounting(trim_yaw_deg=45.0), "test")
    ((counter, yaw),) = sent
    assert counter == counter0 + 1 and abs(abs(_turn(yaw, yaw0)) - 45.0) < 0.01
