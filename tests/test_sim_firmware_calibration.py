"""The simulated firmware's on-board calibration routines against the datasheet: MAGCAL
(min/max tracking, its result, its failures) and ACCCAL (the level reference, motion).

The firmware is driven in simulated time by a :class:`~firmware_host.Host`.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from firmware_host import DECL_DEG, Host, angle_err, firmware

from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    ParamsFrame,
)
from bridge.sim.flash import Flash
from bridge.sim.motion import AttitudeList, OnboardCalRotation, Sequence, Shaken, Still, YawTurns
from bridge.sim.physics import UnitErrors

# ---------------------------------------------------------------- MAGCAL


def expected_minmax(frames: list[AttitudeFrame]) -> tuple[int, list[int] | None, list[int] | None]:
    """The datasheet's tracking rules, re-implemented from the frames (factory level ref)."""
    n, xy, z = 0, None, None
    for f in frames:
        g = np.array([f.ax - 2458.0, f.ay - 2458.0, f.az - 2949.5 + 491.5])
        tilt = math.degrees(math.acos(g[2] / np.linalg.norm(g)))
        level, side = tilt < 20.0, abs(g[2]) / 491.5 < 0.35
        if level:
            xy = (
                [f.mx, f.mx, f.my, f.my]
                if xy is None
                else [min(xy[0], f.mx), max(xy[1], f.mx), min(xy[2], f.my), max(xy[3], f.my)]
            )
        if side:
            z = [f.mz, f.mz] if z is None else [min(z[0], f.mz), max(z[1], f.mz)]
        n += level or side
    return n, xy, z


def test_magcal_full_routine_computes_the_datasheet_result() -> None:
    # a unit with hard iron and unequal gains: heading is off until MAGCAL fixes it
    errors = UnitErrors(
        hard_iron_G=np.array([0.05, -0.03, 0.02]),
        soft_iron=np.diag([1.05, 0.95, 1.0]),
        mag_noise_G=0.0003,
    )
    routine = OnboardCalRotation(turn_s=20.0, tip_s=3.0)
    motion = Sequence([AttitudeList([(0.0, 0.0, 0.0)], dwell_s=1.0), routine])
    flash = Flash()
    h = Host(firmware(motion, errors, flash), step=0.01)
    h.run(0.5)
    lat, f = h.command(CommandFrame.magcal_start())
    assert f == AckFrame("MAGCAL", True) and lat <= 0.2
    h.run(1.0 + routine.duration - h.t + 0.2)
    cal_frames = [f for _, f in h.frames() if f.flags & Flags.CAL]
    assert len(cal_frames) > 400
    # PGMRC at 1 Hz, each equal to the rules applied to the CAL frames sent before it
    progress = [(t, f) for t, f in h.log if isinstance(f, CalProgressFrame)]
    assert len(progress) >= int(routine.duration)
    np.testing.assert_allclose(np.diff([t for t, _ in progress]), 1.0, atol=0.011)
    for t, p in progress[::7]:
        n, xy, z = expected_minmax([f for tt, f in h.frames() if tt <= t and f.flags & Flags.CAL])
        assert p == CalProgressFrame(n, *(xy or [0, 0, 0, 0]), *(z or [0, 0]))
    # the first report comes before the unit was tipped: z not tracked yet -> 0,0
    assert (progress[0][1].zmin, progress[0][1].zmax) == (0, 0)
    assert progress[0][1].xmax > progress[0][1].xmin > 0
    lat, f = h.command(CommandFrame.magcal_end())
    assert isinstance(f, AckFrame) and f.ok and lat <= 0.5
    n, xy, z = expected_minmax(cal_frames)
    assert xy is not None and z is not None
    sx, sy, sz = xy[1] - xy[0], xy[3] - xy[2], z[1] - z[0]
    want = AckFrame.magcal_ok(
        (xy[1] + xy[0]) / 2, (xy[3] + xy[2]) / 2, (z[1] + z[0]) / 2, 1.0, sx / sy, sx / sz
    )
    assert f == want
    # physics agrees: offsets sit at the hard iron, Ky and Kz undo the gain errors
    xoff, yoff, zoff, kx, ky, kz = f.values
    assert xoff == pytest.approx(2458 + 2560 * 0.05, abs=4)
    assert yoff == pytest.approx(2458 - 2560 * 0.03, abs=4)
    assert zoff == pytest.approx(2458 + 2560 * 0.02, abs=4)
    assert (kx, ky, kz) == (
        1.0,
        pytest.approx(1.05 / 0.95, abs=0.01),
        pytest.approx(1.05, abs=0.01),
    )
    h.run(0.3)
    assert h.frames()[-1][1].flags == Flags.MAGOK  # CAL left, MAGOK set
    _, params = h.command(CommandFrame.par_get())
    assert isinstance(params, ParamsFrame) and params.fields()[:6] == f.fields
    assert params.fields()[6:] == ("2458.0", "2458.0", "2949.5")
    # and the on-board heading of the calibrated unit is now right (it was not before)
    headings = [0.0, 75.0, 160.0, 250.0, 330.0]
    check = AttitudeList([(0.0, 0.0, math.radians(y)) for y in headings], dwell_s=0.5)
    before = Host(firmware(check, errors), step=0.05)
    after = Host(firmware(check, errors, flash), step=0.05)
    worst_before = worst_after = 0.0
    for hh in (before, after):
        hh.run(check.duration)
    for (t, fb), (_, fa) in zip(before.frames(), after.frames(), strict=True):
        i = check.segment_at(t)
        if i is None:
            continue
        want_hdg = headings[i] - DECL_DEG
        worst_before = max(worst_before, angle_err(fb.heading, want_hdg))
        worst_after = max(worst_after, angle_err(fa.heading, want_hdg))
    assert worst_before > 4.0 and worst_after < 0.8


@pytest.mark.parametrize(
    ("roll_deg", "pitch_deg", "acc_gain", "xy_tracked", "z_tracked"),
    [
        (0.0, 15.0, 1.0, True, False),  # tilt 15 deg: level
        (-14.0, 12.0, 1.0, True, False),  # tilt ~18.4 deg: level
        (0.0, 25.0, 1.0, False, False),  # tilt 25 deg: neither
        (0.0, 18.0, 0.7, True, False),  # tilt is an angle: the accelerometer gain does not matter
        (72.0, 0.0, 1.0, False, True),  # gz = cos 72 = 0.31 g: on its side
        (66.0, 0.0, 1.0, False, False),  # gz = 0.41 g: not yet
        (0.0, -90.0, 1.0, False, True),  # nose down: z horizontal too
        # |gz| is the reading in g (counts / 491.5), not normalised by |g|:
        (66.0, 0.0, 0.8, False, True),  # 0.41 g x 0.8 = 0.33 g -> on its side
        (72.0, 0.0, 1.2, False, False),  # 0.31 g x 1.2 = 0.37 g -> not
    ],
)
def test_magcal_tracks_xy_only_level_and_z_only_on_its_side(
    roll_deg: float, pitch_deg: float, acc_gain: float, xy_tracked: bool, z_tracked: bool
) -> None:
    errors = UnitErrors(acc_matrix=np.eye(3) * acc_gain)
    h = Host(firmware(Still.from_deg(roll_deg, pitch_deg, 40.0), errors), step=0.01)
    h.run(0.05)
    h.command(CommandFrame.magcal_start())
    _, p = h.wait_for(lambda f: isinstance(f, CalProgressFrame), 1.1)
    assert isinstance(p, CalProgressFrame)
    assert ((p.xmin, p.xmax, p.ymin, p.ymax) != (0, 0, 0, 0)) == xy_tracked
    assert ((p.zmin, p.zmax) != (0, 0)) == z_tracked
    assert (p.samples > 0) == (xy_tracked or z_tracked)
    if xy_tracked:
        f = h.frames()[-1][1]
        assert (p.xmin, p.ymin) == (f.mx, f.my)  # a still, noise-free unit: min == max


def test_magcal_without_rotation_fails_with_range_and_leaves_cal_mode() -> None:
    h = Host(firmware(Still.from_deg(0, 0, 30)), step=0.01)
    h.run(0.05)
    h.command(CommandFrame.magcal_start())
    h.run(2.0)
    assert h.frames()[-1][1].flags == Flags.CAL
    lat, f = h.command(CommandFrame.magcal_end())
    assert f == AckFrame.failure("MAGCAL", "RANGE") and lat <= 0.5
    h.run(0.3)
    assert h.frames()[-1][1].flags == Flags(0)
    assert not [f for t, f in h.log if isinstance(f, CalProgressFrame) and t > h.t - 0.25]
    _, f = h.command(CommandFrame.magcal_end())
    assert f == AckFrame.failure("MAGCAL", "STATE")
    _, f = h.command(CommandFrame.par_get())
    assert f == ParamsFrame.factory()


def test_magcal_range_when_one_axis_was_never_turned() -> None:
    # the level turn only: x and y span plenty, z was never tracked (0,0) -> RANGE
    h = Host(firmware(YawTurns(rate_dps=45.0)), step=0.01)
    h.run(0.05)
    h.command(CommandFrame.magcal_start())
    h.run(8.5)
    progress = [f for _, f in h.log if isinstance(f, CalProgressFrame)]
    p = progress[-1]
    assert p.span("x") > 800 and p.span("y") > 800 and (p.zmin, p.zmax) == (0, 0)
    _, f = h.command(CommandFrame.magcal_end())
    assert f == AckFrame.failure("MAGCAL", "RANGE")
    assert h.command(CommandFrame.par_get())[1] == ParamsFrame.factory()


def test_failed_flash_write_in_magcal_end_and_acccal_answers_err_flash() -> None:
    routine = OnboardCalRotation(turn_s=8.0, tip_s=1.0)
    fw = firmware(Sequence([routine, Still.from_deg(0, 0, 0)]))
    h = Host(fw, step=0.01)
    h.command(CommandFrame.magcal_start())
    h.run(routine.duration)
    fw.flash.fail_next_write()
    _, f = h.command(CommandFrame.magcal_end())
    assert f == AckFrame.failure("MAGCAL", "FLASH")
    h.run(0.2)
    assert h.frames()[-1][1].flags == Flags.FLASHERR  # not calibrating, no MAGOK
    fw.flash.fail_next_write()
    _, f = h.command(CommandFrame.acccal())
    assert f == AckFrame.failure("ACCCAL", "FLASH")
    assert fw.flash.page == Flash().page


def test_state_rules() -> None:
    fw = firmware()
    h = Host(fw, step=0.005)
    h.run(0.05)
    assert h.command(CommandFrame.magcal_end())[1] == AckFrame.failure("MAGCAL", "STATE")
    assert h.command(CommandFrame.magcal_abort())[1] == AckFrame.failure("MAGCAL", "STATE")
    assert h.command(CommandFrame.magcal_start())[1] == AckFrame("MAGCAL", True)
    assert h.command(CommandFrame.magcal_start())[1] == AckFrame.failure("MAGCAL", "STATE")
    assert h.command(CommandFrame.acccal())[1] == AckFrame.failure("ACCCAL", "STATE")
    params = ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.0, 1.0, 2458.0, 2458.0, 2949.5)
    assert h.command(CommandFrame.par_set(params))[1] == AckFrame.failure("PAR", "STATE")
    # reading is fine while calibrating
    assert h.command(CommandFrame.par_get())[1] == ParamsFrame.factory()
    assert h.command(CommandFrame.ver())[1] == fw.version
    assert h.command(CommandFrame.magcal_abort())[1] == AckFrame("MAGCAL", True)
    h.run(0.2)
    assert h.frames()[-1][1].flags == Flags(0) and fw.flash.writes == 0
    # after ABORT everything is allowed again
    assert h.command(CommandFrame.par_set(params))[1] == AckFrame("PAR", True)


# ---------------------------------------------------------------- ACCCAL


def test_acccal_averages_one_second_into_the_level_reference() -> None:
    # a unit whose accelerometer zero is off: level reads a 3.5 deg pitch until ACCCAL
    errors = UnitErrors(acc_adc_zero=np.array([30.0, -20.0, 10.0]))
    fw = firmware(Still.from_deg(0, 0, 10), errors)
    h = Host(fw, step=0.005)
    h.run(0.5)
    assert h.frames()[-1][1].pitch == pytest.approx(-math.degrees(math.asin(30 / 491.5)), abs=0.1)
    t0 = h.send(CommandFrame.acccal())
    t1, f = h.wait_for(lambda f: isinstance(f, AckFrame), 1.6)
    assert 1.0 <= t1 - t0 <= 1.5
    # the noise-free level reading is (2488, 2438, 2959.5 -> 2960): exactly its mean
    assert f == AckFrame.acccal_ok(2488.0, 2438.0, 2960.0)
    # frames kept flowing during the second of averaging
    during = [fr for t, fr in h.frames() if t0 < t < t1]
    assert len(during) >= 9
    h.run(0.3)
    last = h.frames()[-1][1]
    assert last.flags == Flags.ACCOK
    assert (last.pitch, last.roll) == (0.0, 0.0)
    _, p = h.command(CommandFrame.par_get())
    assert isinstance(p, ParamsFrame) and (p.gxoff, p.gyoff, p.gzoff) == (2488.0, 2438.0, 2960.0)
    assert (p.xoff, p.kx) == (2458.0, 1.0)


def test_acccal_with_noise_matches_the_frames_mean() -> None:
    errors = UnitErrors.draw(np.random.default_rng(3))
    h = Host(firmware(Still.from_deg(2, -3, 10), errors), step=0.005)
    h.run(0.1)
    t0 = h.send(CommandFrame.acccal())
    _, f = h.wait_for(lambda f: isinstance(f, AckFrame), 1.6)
    assert isinstance(f, AckFrame) and f.ok
    frames = np.array([[fr.ax, fr.ay, fr.az] for t, fr in h.frames() if t > t0])
    np.testing.assert_allclose(f.values, frames.mean(axis=0), atol=1.0)


def test_acccal_while_moving_fails_with_motion() -> None:
    shaking = Shaken(Still(), amplitude_g=[0.05, 0.05, 0.05], freq_hz=3.0)  # ~50 counts p-p
    fw = firmware(shaking, UnitErrors.draw(np.random.default_rng(4)))
    h = Host(fw, step=0.005)
    h.run(0.1)
    t0 = h.send(CommandFrame.acccal())
    t1, f = h.wait_for(lambda f: isinstance(f, AckFrame), 1.6)
    assert f == AckFrame.failure("ACCCAL", "MOTION") and t1 - t0 <= 1.5
    assert fw.flash.writes == 0 and not fw.flash.page.accok
    # a second ACCCAL while the first is averaging is refused
    h.send(CommandFrame.acccal())
    h.run(0.1)
    _, f = h.command(CommandFrame.acccal())
    assert f == AckFrame.failure("ACCCAL", "STATE")
