"""The simulated firmware against the datasheet, one behaviour at a time.

The firmware is sans-I/O, so every test drives it with a simulated clock: a
:class:`Host` steps time, polls, decodes what arrives with the *host* decoder
and records when each sentence appeared. Every wait is bounded in simulated time.
"""

from __future__ import annotations

import functools
import math
import operator
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    GmrDecoder,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
)
from bridge.sim.firmware import Firmware
from bridge.sim.flash import FLASH_FILE_MAX_BYTES, Flash
from bridge.sim.motion import (
    AttitudeList,
    HandShake,
    Motion,
    OnboardCalRotation,
    Sequence,
    Shaken,
    Still,
    Tumble,
    YawTurns,
)
from bridge.sim.physics import SensorModel, UnitErrors

FIELD = np.array([0.2152, 0.0138, 0.4333])  # NED gauss, about Zurich
DECL_DEG = math.degrees(math.atan2(FIELD[1], FIELD[0]))
FACTORY_FIELDS = "2458.0,2458.0,2458.0,1.0000,1.0000,1.0000,2458.0,2458.0,2949.5"


def raw_line(body: str, cs: int | None = None) -> bytes:
    """A line built by hand (checksum = XOR of the body), independent of the codec."""
    value = functools.reduce(operator.xor, body.encode(), 0) if cs is None else cs
    return f"${body}*{value:02X}\r\n".encode()


class Host:
    """Drives a firmware in simulated time and records ``(time, frame)`` as decoded."""

    def __init__(self, fw: Firmware, t0: float = 0.0, step: float = 0.001) -> None:
        self.fw = fw
        self.t = t0
        self.step = step
        self.dec = GmrDecoder("host")
        self.log: list[tuple[float, GmrFrame]] = []
        self.raw = bytearray()

    def send(self, cmd: CommandFrame | bytes) -> float:
        data = cmd if isinstance(cmd, bytes) else encode(cmd)
        self.fw.receive(data, self.t)
        return self.t

    def run(self, dt: float, step: float | None = None) -> list[tuple[float, GmrFrame]]:
        """Advance ``dt`` seconds; return what arrived meanwhile."""
        step = step or self.step
        start = len(self.log)
        end = self.t + dt
        while self.t < end - 1e-12:
            self.t = min(end, self.t + step)
            self._poll()
        return self.log[start:]

    def _poll(self) -> None:
        data = self.fw.poll(self.t)
        self.raw += data
        for f in self.dec.feed(data):
            self.log.append((self.t, f))

    def wait_for(self, pred: Callable[[GmrFrame], bool], timeout: float) -> tuple[float, GmrFrame]:
        """Run until a frame matching ``pred`` arrives (simulated deadline ``timeout``)."""
        start = len(self.log)
        end = self.t + timeout
        while self.t < end:
            self.t = min(end, self.t + self.step)
            self._poll()
            for t, f in self.log[start:]:
                if pred(f):
                    return t, f
            start = len(self.log)
        raise AssertionError(f"nothing matched within {timeout} s")

    def command(self, cmd: CommandFrame, timeout: float = 2.0) -> tuple[float, GmrFrame]:
        """Send ``cmd``; return (latency, answer)."""
        t0 = self.send(cmd)
        t, f = self.wait_for(cmd.is_answer, timeout)
        return t - t0, f

    def frames(self, since: float = -math.inf) -> list[tuple[float, AttitudeFrame]]:
        return [(t, f) for t, f in self.log if isinstance(f, AttitudeFrame) and t >= since]


def firmware(
    motion: Motion | None = None,
    errors: UnitErrors | None = None,
    flash: Flash | None = None,
    seed: int = 0,
) -> Firmware:
    sensor = SensorModel(errors or UnitErrors.ideal(), FIELD)
    return Firmware(
        sensor,
        motion or Still(),
        flash or Flash(),
        np.random.default_rng(seed),
        power_on_at=0.0,
    )


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


def angle_err(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def acks(log: list[tuple[float, GmrFrame]]) -> list[AckFrame]:
    return [f for _, f in log if isinstance(f, AckFrame)]


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
    h.send(raw_line("PGMRQ,VER", cs=0x00))
    h.send(b"$PGMRQ,VER\r\n")
    h.send(raw_line("PGMRA,1,2"))  # a device sentence sent to the device: not a command
    log = h.run(1.0)
    assert not [f for _, f in log if not isinstance(f, AttitudeFrame)]
    assert fw.decoder.counters.dropped["checksum"] == 1
    assert fw.decoder.counters.dropped["no_checksum"] == 1
    assert fw.decoder.counters.dropped["unknown_id"] == 1
    # a good line split into single bytes is still answered
    for b in raw_line("PGMRQ,VER"):
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


# ---------------------------------------------------------------- PAR,SET and flash


def test_par_set_validates_and_persists(tmp_path: Path) -> None:
    path = tmp_path / "flash.json"
    fw = firmware(flash=Flash(path))
    h = Host(fw, step=0.002)
    h.run(0.05)
    good = "2500.0,2400.5,2600.0,1.0000,1.2500,0.8000,2458.0,2458.0,2949.5"
    bad = [
        "4096.0,2400.5,2600.0,1.0,1.0,1.0,2458.0,2458.0,2949.5",  # offset > 4095
        "-1.0,2400.5,2600.0,1.0,1.0,1.0,2458.0,2458.0,2949.5",  # offset < 0
        "2500.0,2400.5,2600.0,0.09,1.0,1.0,2458.0,2458.0,2949.5",  # gain < 0.1
        "2500.0,2400.5,2600.0,1.0,10.5,1.0,2458.0,2458.0,2949.5",  # gain > 10
        "2500.0,2400.5,2600.0,1.0,1.0,1.0,2458.0,2458.0,5000",  # level offset > 4095
        "2500.0,2400.5,2600.0,1.0,1.0,1.0,2458.0,2458.0",  # eight numbers
        "2500.0,2400.5,2600.0,1.0,1.0,1.0,2458.0,2458.0,2949.5,1",  # ten
        "2500.0,x,2600.0,1.0,1.0,1.0,2458.0,2458.0,2949.5",  # not a number
        "2500.0,1e3,2600.0,1.0,1.0,1.0,2458.0,2458.0,2949.5",  # not a plain decimal
    ]
    for text in bad:
        lat, f = h.command(CommandFrame("PAR", ("SET", *text.split(","))))
        assert f == AckFrame.failure("PAR", "ARGS"), text
        assert lat <= 0.5
    _, f = h.command(CommandFrame.par_get())
    assert f == ParamsFrame.factory() and fw.flash.writes == 0
    lat, f = h.command(CommandFrame("PAR", ("SET", *good.split(","))))
    assert f == AckFrame("PAR", True) and lat <= 0.5
    _, f = h.command(CommandFrame.par_get())
    assert isinstance(f, ParamsFrame) and ",".join(f.fields()) == good
    # MAGOK: the magnetometer values differ from factory; ACCOK: the level reference does not
    h.run(0.2)
    assert h.frames()[-1][1].flags == Flags.MAGOK
    # the page is in the file: a power cycle (a new Flash on the same path) still has it
    assert ",".join(Flash(path).page.params().fields()) == good
    # writing factory values back clears the flags again
    h.command(CommandFrame("PAR", ("SET", *FACTORY_FIELDS.split(","))))
    h.run(0.2)
    assert h.frames()[-1][1].flags == Flags(0)


def test_par_set_accepts_the_range_limits() -> None:
    h = Host(firmware(), step=0.002)
    h.run(0.05)
    edge = "0.0,4095.0,2458.0,0.1000,10.0000,1.0000,0.0,4095.0,2949.5"
    _, f = h.command(CommandFrame("PAR", ("SET", *edge.split(","))))
    assert f == AckFrame("PAR", True)
    _, f = h.command(CommandFrame.par_get())
    assert isinstance(f, ParamsFrame) and ",".join(f.fields()) == edge


def test_sat_flag_marks_frames_with_a_channel_at_a_rail() -> None:
    # 0.5 G of hard iron along x: facing north mx passes the top rail, facing south it does not
    errors = UnitErrors(hard_iron_G=np.array([0.5, 0.0, 0.0]))
    m = AttitudeList([(0.0, 0.0, 0.0), (0.0, 0.0, math.pi)], dwell_s=1.0, transition_s=1.0)
    h = Host(firmware(m, errors), step=0.01)
    h.run(m.duration)
    for t, f in h.frames():
        i = m.segment_at(t)
        if i == 0:
            assert f.mx == 4095 and f.flags == Flags.SAT
        elif i == 1:
            assert f.mx < 4095 and f.flags == Flags(0)
    assert any(m.segment_at(t) == 1 for t, _ in h.frames())


def test_flash_write_pauses_frames_without_a_seq_gap() -> None:
    h = Host(firmware(), step=0.0005)
    h.command(CommandFrame.rate(100))
    h.run(0.3)
    params = ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.0, 1.0, 2458.0, 2458.0, 2949.5)
    t_cmd = h.send(CommandFrame.par_set(params))
    t_ack, f = h.wait_for(lambda f: isinstance(f, AckFrame), 0.5)
    assert f == AckFrame("PAR", True) and t_ack - t_cmd <= 0.5
    h.run(0.3)
    frames = h.frames(since=0.25)
    times = np.array([t for t, _ in frames])
    gaps = np.diff(times)
    # exactly one pause: longer than a period, as long as a 30-50 ms write allows
    long = gaps[gaps > 0.0155]
    assert len(long) == 1 and 0.025 < long[0] < 0.0615
    i = int(np.argmax(gaps))
    assert times[i] < t_ack <= times[i + 1]  # the answer leaves when the write is done
    seqs = [f.seq for _, f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


def test_failed_flash_write_sets_flasherr_and_keeps_the_content() -> None:
    fw = firmware()
    h = Host(fw, step=0.002)
    h.run(0.05)
    fw.flash.fail_next_write()
    params = ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.0, 1.0, 2458.0, 2458.0, 2949.5)
    lat, f = h.command(CommandFrame.par_set(params))
    assert f == AckFrame.failure("PAR", "FLASH") and lat <= 0.5
    h.run(0.25)
    assert h.frames()[-1][1].flags == Flags.FLASHERR
    _, f = h.command(CommandFrame.par_get())
    assert f == ParamsFrame.factory()
    # the next good write clears FLASHERR
    _, f = h.command(CommandFrame.par_set(params))
    assert f == AckFrame("PAR", True)
    h.run(0.25)
    assert h.frames()[-1][1].flags == Flags.MAGOK


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
    fw = firmware()
    h = Host(fw, step=0.005)
    h.run(0.05)
    fw.flash.fail_next_write()
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


# ---------------------------------------------------------------- the flash page


def test_flash_factory_state_is_the_datasheet() -> None:
    page = Flash().page
    assert ",".join(page.params().fields()) == FACTORY_FIELDS
    assert (page.magok, page.accok) == (False, False)
    assert Flash().flasherr is False


def test_flash_file_is_written_atomically_with_the_previous_copy(tmp_path: Path) -> None:
    path = tmp_path / "unit.flash"
    flash = Flash(path)
    assert flash.load_source == "factory" and flash.load_error is None  # first use: no file
    p1 = flash.page.with_params(
        ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.1, 0.9, 2458.0, 2458.0, 2949.5), magok=True
    )
    p2 = p1.with_params(
        ParamsFrame(2501.0, 2401.0, 2601.0, 1.0, 1.2, 0.8, 2460.0, 2450.0, 2950.0), accok=True
    )
    assert flash.write(p1) and flash.write(p2)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["unit.flash", "unit.flash.prev"]
    assert Flash(path).page == p2 and Flash(path).load_source == "file"
    # the double buffer: .prev holds the content before the last write
    prev_only = tmp_path / "other.flash"
    prev_only.with_name("other.flash.prev").write_bytes(
        path.with_name("unit.flash.prev").read_bytes()
    )
    assert Flash(prev_only).page == p1


@pytest.mark.parametrize(
    "damage",
    [
        lambda b: b[: len(b) // 2],  # truncated by a power cut
        lambda b: b"",  # empty
        lambda b: b.replace(b"2501.0", b"2901.0"),  # a flipped value: CRC mismatch
        lambda b: b"\xff\xfe\x00garbage",  # not even text
        lambda b: b'{"format": "gmr-flash/1", "page": {"kx": 1}, "crc32": 0}',  # wrong shape
        None,  # the file is gone (cut between the two renames)
    ],
)
def test_damaged_flash_file_falls_back_to_the_previous_copy(
    tmp_path: Path, damage: Callable[[bytes], bytes] | None
) -> None:
    path = tmp_path / "unit.flash"
    flash = Flash(path)
    p1 = flash.page.with_params(
        ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.1, 0.9, 2458.0, 2458.0, 2949.5), magok=True
    )
    p2 = p1.with_params(ParamsFrame(2501.0, 2401.0, 2601.0, 1.0, 1.2, 0.8, 2458.0, 2458.0, 2949.5))
    flash.write(p1)
    flash.write(p2)
    if damage is None:
        path.unlink()
    else:
        path.write_bytes(damage(path.read_bytes()))
    again = Flash(path)
    assert again.page == p1 and again.load_source == "prev"
    assert again.load_error is not None and "unit.flash" in again.load_error
    # both copies bad: factory content, still no exception
    path.with_name("unit.flash.prev").write_bytes(b"{")
    worst = Flash(path)
    assert worst.page == Flash().page and worst.load_source == "factory"
    assert worst.load_error is not None


def test_a_flash_path_naming_a_device_a_fifo_or_a_huge_file_is_refused_not_read(
    tmp_path: Path,
) -> None:
    """`--flash /dev/zero` (or a FIFO, or a huge file) gives factory content and a reason."""
    (tmp_path / "dev.flash").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "fifo.flash")
    (tmp_path / "huge.flash").write_bytes(b" " * (FLASH_FILE_MAX_BYTES + 1))
    for name, why in (
        ("dev.flash", "character device"),
        ("fifo.flash", "FIFO"),
        ("huge.flash", "byte limit"),
    ):
        flash = Flash(tmp_path / name)  # returns at once: nothing blocks on a writer
        assert flash.page == Flash().page and flash.load_source == "factory"
        assert flash.load_error is not None and why in flash.load_error, flash.load_error


def test_a_write_cut_midway_leaves_the_previous_content(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "unit.flash"
    flash = Flash(path)
    p1 = flash.page.with_params(
        ParamsFrame(2500.0, 2400.0, 2600.0, 1.0, 1.1, 0.9, 2458.0, 2458.0, 2949.5), magok=True
    )
    assert flash.write(p1)
    real_replace = os.replace
    calls = {"n": 0}

    def cut(src: str, dst: str) -> None:
        calls["n"] += 1
        if calls["n"] == 2:  # the rename of the new page: power lost
            raise OSError(5, "power cut")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", cut)
    assert flash.write(flash.page.with_params(ParamsFrame.factory())) is False
    monkeypatch.undo()
    assert flash.flasherr and flash.page == p1
    assert Flash(path).page == p1
    assert sorted(x.name for x in tmp_path.iterdir()) == ["unit.flash", "unit.flash.prev"]
    flash.power_cycle()
    assert not flash.flasherr and flash.page == p1


def test_fail_next_write_hook() -> None:
    flash = Flash()
    page = flash.page.with_params(flash.page.params(), magok=True)
    flash.fail_next_write(2)
    assert flash.write(page) is False and flash.write(page) is False
    assert flash.flasherr and flash.failed_writes == 2 and not flash.page.magok
    assert flash.write(page) is True
    assert not flash.flasherr and flash.page.magok
    flash.fail_next_write()
    flash.write(page)
    flash.power_cycle()  # FLASHERR is RAM state; the in-memory page survives
    assert not flash.flasherr and flash.page.magok


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
