"""The simulated firmware against the datasheet, one behaviour at a time: power-up, frames
and their sequence numbers, the on-board attitude, the simple commands, RESET, garbage
and power cycles, and the world (a shaking hand, a hard-iron change) reaching its frames.

The firmware is sans-I/O, so every test drives it with a simulated clock: a
:class:`~firmware_host.Host` steps time, polls, decodes what arrives with the *host*
decoder and records when each sentence appeared. Every wait is bounded in simulated time.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from codec_props import line
from firmware_host import (
    DECL_DEG,
    FACTORY_FIELDS,
    FIELD,
    Host,
    angle_err,
    failing_flash_host,
    firmware,
)

from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    Flags,
    ParamsFrame,
    VersionFrame,
)
from bridge.sim.firmware import Firmware
from bridge.sim.flash import Flash
from bridge.sim.motion import AttitudeList, HandShake, Still, Tumble
from bridge.sim.physics import SensorModel, UnitErrors


def reference_attitude(f: AttitudeFrame, p: ParamsFrame) -> tuple[float, float, float]:
    """The datasheet's angles written as a rotation (de-tilt H by Ry(theta) Rx(gamma))."""
    H = np.array([p.kx * (f.mx - p.xoff), p.ky * (f.my - p.yoff), p.kz * (f.mz - p.zoff)])
    g = np.array([f.ax - p.gxoff, f.ay - p.gyoff, f.az - p.gzoff + 491.5])
    theta = -math.asin(g[0] / np.linalg.norm(g))
    gamma = math.atan2(g[1], g[2])
    c, s = math.cos(gamma), math.sin(gamma)
    Rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    c, s = math.cos(theta), math.sin(theta)
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    X, Y, _ = Ry @ Rx @ H
    return math.degrees(math.atan2(-Y, X)) % 360.0, math.degrees(theta), math.degrees(gamma)


def radians3(e: tuple[float, float, float] | list[float]) -> tuple[float, float, float]:
    return (math.radians(e[0]), math.radians(e[1]), math.radians(e[2]))


# ---------------------------------------------------------------- power-up, frames, seq


def test_power_up_version_then_10hz_frames_from_seq_0() -> None:
    h = Host(firmware())
    log = h.run(1.05)
    assert isinstance(log[0][1], VersionFrame)
    assert log[0][1] == VersionFrame("2.1.0", "B3", "GMR-000417")
    assert log[0][0] <= 0.001
    frames = h.frames()
    assert [f.seq for _, f in frames] == list(range(10))
    times = np.array([t for t, _ in frames])
    np.testing.assert_allclose(np.diff(times), 0.1, atol=0.0011)
    assert all(f.flags == Flags(0) for _, f in frames)  # factory flash: no MAGOK/ACCOK
    assert h.dec.counters.dropped.total == 0


def test_power_up_on_first_use_when_no_time_given() -> None:
    fw = Firmware(SensorModel(UnitErrors.ideal(), FIELD), Still(), Flash(), np.random.default_rng())
    h = Host(fw, t0=1000.0)
    log = h.run(0.25)
    assert isinstance(log[0][1], VersionFrame)
    assert [f.seq for _, f in h.frames()] == [0, 1]
    assert fw.motion_epoch == pytest.approx(1000.001)


def test_seq_wraps_from_65535_to_0() -> None:
    fw = firmware()
    h = Host(fw, step=0.01)
    h.run(0.05)
    fw.seq = 65533
    h.run(0.6)
    assert [f.seq for _, f in h.frames()][:6] == [65533, 65534, 65535, 0, 1, 2]


def test_output_does_not_depend_on_poll_granularity() -> None:
    def stream(step: float) -> bytes:
        fw = firmware(Still.from_deg(5, 10, 20), UnitErrors.draw(np.random.default_rng(1)))
        h = Host(fw, step=step)
        h.run(2.05)
        return bytes(h.raw)

    fine, coarse = stream(0.001), stream(0.37)
    assert fine == coarse and fine.count(b"$PGMRA") == 20


def test_a_suspended_host_gets_a_seq_jump_not_a_flood() -> None:
    fw = firmware()
    h = Host(fw, step=0.01)
    h.run(1.0)
    last = h.frames()[-1][1].seq
    h.run(30.0, step=30.0)  # the caller slept for 30 s
    after = [f.seq for _, f in h.frames()][last + 1 :]
    assert len(after) <= 25  # about the last 2 s of frames, not 300
    # but seq counts every frame the device sent meanwhile: it matches elapsed time
    assert h.frames()[-1][1].seq == pytest.approx(310, abs=1)
    assert after == list(range(after[0], after[0] + len(after)))


# ---------------------------------------------------------------- on-board attitude


def test_onboard_angles_match_truth_for_an_ideal_unit() -> None:
    eulers = [
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 90.0),
        (0.0, 0.0, 200.0),
        (20.0, 0.0, 45.0),
        (0.0, -30.0, 300.0),
        (-15.0, 25.0, 10.0),
        (120.0, 10.0, 80.0),
    ]
    m = AttitudeList([radians3(e) for e in eulers], dwell_s=1.0, transition_s=0.5)
    h = Host(firmware(m), step=0.01)
    h.run(m.duration)
    checked = 0
    for t, f in h.frames():
        i = m.segment_at(t)
        if i is None:
            continue
        roll, pitch, yaw = eulers[i]
        assert angle_err(f.heading, yaw - DECL_DEG) < 0.4, (eulers[i], f)
        assert f.pitch == pytest.approx(pitch, abs=0.4)
        assert angle_err(f.roll, roll) < 0.4
        checked += 1
    assert checked >= 60


def test_onboard_angles_follow_the_datasheet_formulas_exactly() -> None:
    # arbitrary flash parameters and a unit with errors: the frame's angles are exactly
    # the datasheet's formulas applied to the frame's own counts (to the 0.1 printed)
    errors = UnitErrors.draw(np.random.default_rng(11))
    rng = np.random.default_rng(12)
    eulers = rng.uniform([-60, -60, 0], [60, 60, 360], size=(15, 3)).tolist()
    m = AttitudeList([radians3(e) for e in eulers], dwell_s=0.3, transition_s=0.2)
    h = Host(firmware(m, errors), step=0.01)
    params = ParamsFrame(2501.3, 2399.9, 2612.0, 1.0213, 0.9876, 1.1, 2470.2, 2440.0, 2950.1)
    _, ack = h.command(CommandFrame.par_set(params))
    assert ack == AckFrame("PAR", True)
    _, got = h.command(CommandFrame.par_get())
    assert got == params
    h.run(m.duration)
    frames = h.frames()
    assert len(frames) > 40
    for _, f in frames:
        hdg, pitch, roll = reference_attitude(f, params)
        assert angle_err(f.heading, hdg) <= 0.05 + 1e-9
        assert f.pitch == pytest.approx(pitch, abs=0.05 + 1e-9)
        assert angle_err(f.roll, roll) <= 0.05 + 1e-9
        assert 0.0 <= f.heading < 360.0


# ---------------------------------------------------------------- simple commands


def test_ver_unknown_and_bad_arguments() -> None:
    h = Host(firmware())
    h.run(0.05)
    lat, f = h.command(CommandFrame.ver())
    assert f == VersionFrame("2.1.0", "B3", "GMR-000417") and lat <= 0.2
    lat, f = h.command(CommandFrame("FOO", ("1",)))
    assert f == AckFrame.failure("FOO", "UNKNOWN") and lat <= 0.2
    for cmd in (
        CommandFrame("VER", ("X",)),
        CommandFrame("RESET", ("NOW",)),
        CommandFrame("ACCCAL", ("2",)),
        CommandFrame("MAGCAL", ()),
        CommandFrame("MAGCAL", ("GO",)),
        CommandFrame("PAR", ("PUT",)),
        CommandFrame("PAR", ()),
    ):
        lat, f = h.command(cmd)
        assert f == AckFrame.failure(cmd.command, "ARGS") and lat <= 0.2, cmd


def test_lines_with_a_bad_or_missing_checksum_get_no_answer() -> None:
    fw = firmware()
    h = Host(fw, step=0.005)
    h.run(0.05)
    h.send(line("PGMRQ,VER", cs=0x00))
    h.send(b"$PGMRQ,VER\r\n")
    h.send(line("PGMRA,1,2"))  # a device sentence sent to the device: not a command
    log = h.run(1.0)
    assert not [f for _, f in log if not isinstance(f, AttitudeFrame)]
    assert fw.decoder.counters.dropped["checksum"] == 1
    assert fw.decoder.counters.dropped["no_checksum"] == 1
    assert fw.decoder.counters.dropped["unknown_id"] == 1
    # a good line split into single bytes is still answered
    for b in line("PGMRQ,VER"):
        h.send(bytes([b]))
        h.run(0.002)
    h.wait_for(lambda f: isinstance(f, VersionFrame), 0.2)


@pytest.mark.parametrize("hz", [1, 2, 5, 10, 20, 50, 100])
def test_rate_sets_the_frame_interval(hz: int) -> None:
    h = Host(firmware(), step=0.001)
    h.run(0.15)
    lat, f = h.command(CommandFrame.rate(hz))
    assert f == AckFrame("RATE", True, (str(hz),)) and lat <= 0.2
    t_ack = h.t
    h.run(max(3.0 / hz, 0.2) + 0.01)
    frames = h.frames(since=t_ack)
    times = np.array([t for t, _ in frames])
    assert len(times) >= 3
    np.testing.assert_allclose(np.diff(times), 1.0 / hz, atol=0.0011)
    seqs = [f.seq for _, f in h.frames()]
    assert seqs == list(range(len(seqs)))  # a rate change is no seq gap


@pytest.mark.parametrize("arg", ["0", "3", "1000", "-10", "abc", "10.0", ""])
def test_rate_rejects_other_values(arg: str) -> None:
    h = Host(firmware(), step=0.002)
    h.run(0.05)
    lat, f = h.command(CommandFrame("RATE", (arg,)))
    assert f == AckFrame.failure("RATE", "ARGS") and lat <= 0.2
    t = h.t
    h.run(0.5)
    times = np.array([t for t, _ in h.frames(since=t)])
    np.testing.assert_allclose(np.diff(times), 0.1, atol=0.0021)  # still 10 Hz
    _, f = h.command(CommandFrame("RATE", ()))
    assert f == AckFrame.failure("RATE", "ARGS")


def test_par_get_reports_the_factory_flash() -> None:
    h = Host(firmware())
    h.run(0.05)
    lat, f = h.command(CommandFrame.par_get())
    assert lat <= 0.2
    assert isinstance(f, ParamsFrame) and f == ParamsFrame.factory()
    assert b"$PGMRP," + FACTORY_FIELDS.encode() + b"*" in bytes(h.raw)


# ---------------------------------------------------------------- RESET, garbage, power


def test_reset_goes_silent_then_boots_at_10hz_from_seq_0() -> None:
    fw = firmware()
    h = Host(fw, step=0.001)
    h.command(CommandFrame.rate(50))
    h.command(CommandFrame.magcal_start())
    h.run(0.5)
    assert h.frames()[-1][1].seq > 20
    t0 = h.send(CommandFrame.reset())
    t_ack, f = h.wait_for(lambda f: isinstance(f, AckFrame), 0.2)
    assert f == AckFrame("RESET", True) and t_ack - t0 <= 0.2
    # a command sent during the silence is not heard
    h.run(0.1)
    h.send(CommandFrame.ver())
    t_v, _ = h.wait_for(lambda f: isinstance(f, VersionFrame), 1.0)
    assert 0.29 <= t_v - t_ack <= 0.31  # nothing at all in between
    assert [x for t, x in h.log if t_ack < t < t_v] == []
    h.run(0.55)
    after = h.frames(since=t_v)
    assert [f.seq for _, f in after] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(np.diff([t for t, _ in after]), 0.1, atol=0.0011)
    assert all(f.flags == Flags(0) for _, f in after)  # CAL is gone
    assert len([x for _, x in h.log if isinstance(x, VersionFrame)]) == 2  # power-up + reset


def test_garbage_appears_in_the_output_and_is_only_noise() -> None:
    fw = firmware()
    h = Host(fw, step=0.01)
    h.run(0.5)
    n_before = len(h.raw)
    fw.inject_garbage(300)
    h.run(0.5)
    assert len(h.raw) - n_before >= 300 + 4 * 60
    seqs = [f.seq for _, f in h.frames()]
    assert seqs == list(range(len(seqs))) and len(seqs) == 10
    assert h.dec.counters.dropped.total >= 1


def test_power_cycle_keeps_flash_and_forgets_ram() -> None:
    h = failing_flash_host(step=0.005)
    fw = h.fw
    params = ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.0, 1.0, 2458.0, 2458.0, 2950.0)
    h.command(CommandFrame.par_set(params))  # fails: FLASHERR
    assert h.command(CommandFrame.par_set(params))[1] == AckFrame("PAR", True)
    fw.flash.fail_next_write()
    h.command(CommandFrame.par_set(ParamsFrame.factory()))  # fails: FLASHERR, content kept
    h.command(CommandFrame.rate(20))
    h.run(0.2)
    assert h.frames()[-1][1].flags == Flags.MAGOK | Flags.ACCOK | Flags.FLASHERR
    fw.power_off(h.t)
    assert h.run(1.0) == []
    h.send(CommandFrame.ver())  # nobody listens
    fw.power_on(h.t)
    log = h.run(0.35)
    assert isinstance(log[0][1], VersionFrame)
    frames = [f for _, f in log if isinstance(f, AttitudeFrame)]
    assert [f.seq for f in frames] == [0, 1, 2]
    assert frames[-1].flags == Flags.MAGOK | Flags.ACCOK
    assert h.command(CommandFrame.par_get())[1] == params


def test_a_shaking_hand_reaches_the_accelerometer_frames() -> None:
    # an ideal, noise-free unit lying level, held by a hand shaking 0.1 g RMS per axis:
    # its frames carry the gravity vector minus the shake, to the ADC's count
    hand = HandShake(Still(), 0.1, seed=6)
    h = Host(firmware(hand), step=0.002)
    h.command(CommandFrame.rate(50))
    h.run(10.0)
    frames = [(t, f) for t, f in h.frames() if t > 1.0]
    acc = np.array([[f.ax, f.ay, f.az] for _, f in frames], dtype=float)
    t = np.array([t for t, _ in frames]) - h.fw.motion_epoch
    want = 2458.0 + 491.5 * (np.array([0.0, 0.0, 1.0]) - hand.shake_g(t))
    # a frame is sampled at its tick, up to one polling step before it is read
    slew = hand.peak_bound_g * 2.0 * math.pi * 2.5  # g/s, no faster than the top tone
    assert float(np.abs(acc - want).max()) < 491.5 * slew * h.step + 1.0
    assert np.std(acc, axis=0) == pytest.approx([491.5 * 0.1] * 3, rel=0.35)


def test_the_simulated_port_shakes_as_configured(tmp_path: Path) -> None:
    from bridge.config import config_from_mapping
    from bridge.daemon import make_transport
    from bridge.link.transport import SimTransport
    from bridge.sim.pty import make_motion

    raw = {"device": {"port": "sim"}, "sim": {"motion": "tumble", "seed": 3, "shake_g": 0.05}}
    transport = make_transport(config_from_mapping(raw, env={}, hostname="t"))
    assert isinstance(transport, SimTransport) and isinstance(transport.firmware, Firmware)
    motion = transport.firmware.motion
    assert isinstance(motion, HandShake) and motion.rms_g == 0.05
    assert isinstance(motion.base, Tumble)
    made = make_motion("tumble", 3, 0.05)
    assert isinstance(made, HandShake)
    np.testing.assert_array_equal(motion.shake_g([1.0, 2.0]), made.shake_g([1.0, 2.0]))
    steady = make_transport(config_from_mapping({"device": {"port": "sim"}}, env={}, hostname="t"))
    assert isinstance(steady, SimTransport) and isinstance(steady.firmware, Firmware)
    assert not isinstance(steady.firmware.motion, HandShake)
    with pytest.raises(ValueError, match="motion must be one of"):
        make_motion("spin", 1)


# ---------------------------------------------------------------- a hard-iron change while running


def test_a_hard_iron_change_shows_from_its_time_on_and_survives_a_reset() -> None:
    # an ideal, noise-free unit lying still: its counts move by exactly the change, at the
    # change's time, and a RESET (the device reboots, the world does not) keeps it
    fw = firmware()
    delta = np.array([0.03, -0.02, 0.01])  # gauss, sensor axes
    fw.change_hard_iron(delta, at_s=1.0)
    h = Host(fw, step=0.005)
    h.run(2.0)
    frames = h.frames()
    before = [f for t, f in frames if t < 1.0]
    after = [f for t, f in frames if t > 1.05]
    assert before and after
    mag = lambda f: np.array([f.mx, f.my, f.mz], dtype=float)  # noqa: E731
    np.testing.assert_allclose(mag(after[-1]) - mag(before[0]), 2560.0 * delta, atol=1.0)
    assert all(np.array_equal(mag(f), mag(before[0])) for f in before)
    h.send(CommandFrame.reset())
    h.run(1.0)
    np.testing.assert_array_equal(mag(h.frames()[-1][1]), mag(after[-1]))
    assert fw.sensor.errors.true_calibration().mag.offset == pytest.approx(tuple(delta))


def test_make_firmware_schedules_the_change() -> None:
    from bridge.sim.firmware import make_firmware

    fw = make_firmware(2, ideal=True, motion=Still(), hard_iron_change=((0.0, 0.04, 0.0), 0.5))
    h = Host(fw, step=0.01)
    h.run(1.0)
    ys = [f.my for t, f in h.frames()]
    assert ys[-1] - ys[0] == pytest.approx(2560.0 * 0.04, abs=1.0)
    with pytest.raises(ValueError, match="finite"):
        fw.change_hard_iron((math.nan, 0.0, 0.0))
