"""The simulated unit's flash against the datasheet: PAR,SET validated and persisted, the
SAT flag, a flash write pausing frames, a failed write (FLASHERR), the factory page, and
the flash file on disk (atomic, with the previous copy; damage and hostile paths refused).

The firmware is driven in simulated time by a :class:`~firmware_host.Host`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from firmware_host import FACTORY_FIELDS, Host, failing_flash_host, firmware

from bridge.protocol.gmr import AckFrame, CommandFrame, Flags, ParamsFrame
from bridge.sim.flash import FLASH_FILE_MAX_BYTES, Flash
from bridge.sim.motion import AttitudeList
from bridge.sim.physics import UnitErrors

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
    h = failing_flash_host(step=0.002)
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
