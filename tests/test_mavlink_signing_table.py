"""The signing replay table in the state directory: when it is saved, what comes back, and
what a disk that refuses it does (in memory, on a real :class:`StateStore` and a manual
clock; the whole restart through a real signed peer is in test_mavlink_signing.py)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest
from harness import ManualClock

from bridge.mavlink.signing import Signing
from bridge.mavlink.signing_table import SAVE_EVERY_S, SIGNING_DOCUMENT, SigningTable
from bridge.storage import StateStore

KEY = bytes.fromhex("a3" * 16 + "5c" * 16)
STREAM = [0, 255, 190, 123_456]  # link 0, a ground station's stream, its newest timestamp


def test_a_marked_table_is_saved_on_its_period_and_comes_back_after_a_restart(
    tmp_path: Path,
) -> None:
    clock = ManualClock(100.0)
    signing = Signing(KEY)
    table = SigningTable(signing, StateStore(tmp_path), clock)
    assert table.save_due == math.inf  # nothing new: nothing to save
    signing.restore({"streams": [STREAM]})  # as a valid signed packet leaves it
    assert table.mark() is True  # the first since the save: wake the saver
    assert table.mark() is False  # already waiting to be saved
    assert table.save_due == -math.inf  # never saved: at once
    table.save()
    assert not table.dirty and table.save_due == math.inf
    assert (tmp_path / f"{SIGNING_DOCUMENT}.json").is_file()
    clock.t = 103.0
    table.mark()
    assert table.save_due == 100.0 + SAVE_EVERY_S  # at most once a period after the last

    # a restart: a new table, read back before anything is obeyed
    again = Signing(KEY)
    SigningTable(again, StateStore(tmp_path), clock).restore()
    assert again.snapshot()["streams"] == [STREAM]


def test_a_disk_that_refuses_the_table_is_said_once_and_tried_a_period_later(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocked = tmp_path / "state"
    blocked.write_text("a file where the state directory should be\n")
    clock = ManualClock(50.0)
    signing = Signing(KEY)
    signing.restore({"streams": [STREAM]})
    table = SigningTable(signing, StateStore(blocked), clock)
    table.mark()
    with caplog.at_level(logging.ERROR, logger="bridge.mavlink.signing_table"):
        table.save()
        clock.t = 51.0
        table.save()  # a write-ahead before an obeyed command, failing again
    said = [r for r in caplog.records if "signing replay table not saved" in r.getMessage()]
    assert len(said) == 1  # once, not once per packet
    # still to be saved, but not at once: a period after the last try
    assert table.dirty and table.save_due == 51.0 + SAVE_EVERY_S
    assert blocked.read_text().startswith("a file where")  # nothing written over it


def test_without_a_key_or_a_state_directory_nothing_is_kept(tmp_path: Path) -> None:
    clock = ManualClock(0.0)
    keyless = SigningTable(None, StateStore(tmp_path), clock)
    keyless.mark()
    keyless.save()
    assert not keyless.dirty and keyless.save_due == math.inf
    assert not any(tmp_path.iterdir())
    signing = Signing(KEY)
    nowhere = SigningTable(signing, None, clock)
    nowhere.restore()  # nothing to read: a first run
    nowhere.mark()
    nowhere.save()
    assert not nowhere.dirty  # nowhere to keep it: nothing to come back for
