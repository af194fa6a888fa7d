"""State storage on a real filesystem: atomic saves, corruption fallback, kill -9 mid-save."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from bridge.storage import (
    DocumentError,
    FileMissing,
    FileRefused,
    StateStore,
    StorageError,
    read_regular_file,
    resolve_state_dir,
)


def test_round_trip_and_previous_copy(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("calibration", {"gen": 1})
    store.save("calibration", {"gen": 2})
    res = store.load("calibration")
    assert res.source == "current" and res.payload == {"gen": 2}
    prev = json.loads((tmp_path / "calibration.json.prev").read_text())
    assert prev["payload"] == {"gen": 1}
    assert prev["schema"] == "compass-bridge/calibration" and prev["version"] == 1


def test_missing_gives_none_without_problems(tmp_path: Path) -> None:
    res = StateStore(tmp_path).load("params")
    assert res.payload is None and res.source == "none" and res.problems == ()


@pytest.mark.parametrize(
    "damage",
    [
        lambda b: b[: len(b) // 2],  # truncated by power loss
        lambda b: b.replace(b'"gen": 2', b'"gen": 3'),  # a flipped digit: still valid JSON
        lambda b: b"",  # empty file
        lambda b: b"\x00\xff" * 20,  # binary junk
    ],
)
def test_corrupt_current_falls_back_to_previous(
    tmp_path: Path, damage: Callable[[bytes], bytes]
) -> None:
    store = StateStore(tmp_path)
    store.save("calibration", {"gen": 1})
    store.save("calibration", {"gen": 2})
    path = tmp_path / "calibration.json"
    path.write_bytes(damage(path.read_bytes()))
    res = store.load("calibration")
    assert res.source == "previous" and res.payload == {"gen": 1}
    assert res.problems and "calibration.json" in res.problems[0]


def test_corrupt_current_never_replaces_good_previous(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("calibration", {"gen": 1})
    store.save("calibration", {"gen": 2})
    (tmp_path / "calibration.json").write_text("{broken")
    store.save("calibration", {"gen": 3})
    assert store.load("calibration").payload == {"gen": 3}
    (tmp_path / "calibration.json").write_text("{broken")
    # the previous copy is still gen 1, not the broken file
    assert store.load("calibration").payload == {"gen": 1}


def test_wrong_schema_is_rejected(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("params", {"a": 1})
    os.replace(tmp_path / "params.json", tmp_path / "calibration.json")
    assert store.load("calibration").source == "none"


def test_unwritable_dir_raises_storage_error_and_keeps_old(tmp_path: Path) -> None:
    # A path under a regular file cannot be created by anyone, root included.
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(StorageError, match="cannot save"):
        StateStore(blocker / "state").save("params", {"a": 1})


def test_full_disk_raises_storage_error(tmp_path: Path) -> None:
    if not Path("/dev/full").exists():
        pytest.fail("/dev/full is needed to simulate a full disk")
    store = StateStore(tmp_path)
    store.save("params", {"a": 1})
    # Make the temp file a symlink to /dev/full: the write fails with ENOSPC.
    (tmp_path / "params.json.tmp").symlink_to("/dev/full")
    with pytest.raises(StorageError, match="No space"):
        store.save("params", {"a": 2})
    assert store.load("params").payload == {"a": 1}


def test_nan_is_refused_not_written(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    with pytest.raises(ValueError):
        store.save("params", {"a": float("nan")})
    assert store.load("params").source == "none"


def test_unstorable_payload_is_a_storage_error_too(tmp_path: Path) -> None:
    # The callers catch StorageError: a payload error must not escape them as another type.
    store = StateStore(tmp_path)
    for bad in ({"a": float("inf")}, {"a": object()}):
        with pytest.raises(DocumentError) as info:
            store.save("params", bad)
        assert isinstance(info.value, StorageError)
    with pytest.raises(StorageError, match="bad document name"):
        store.save("../x", {"a": 1})
    assert list(tmp_path.iterdir()) == []


def test_nul_byte_in_the_directory_is_a_storage_error(tmp_path: Path) -> None:
    """ValueError("embedded null byte") once escaped save() and killed its caller."""
    store = StateStore(str(tmp_path / "var") + "\0state")
    with pytest.raises(StorageError, match="null byte") as info:
        store.save("params", {"a": 1})
    assert type(info.value) is StorageError
    assert store.load("params").source == "none"  # and loading it is no crash either
    assert list(tmp_path.iterdir()) == []


def test_a_fifo_planted_as_a_document_does_not_hang_the_load(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "calibration.json")
    res = StateStore(tmp_path).load("calibration")  # would block forever in a plain open()
    assert res.source == "none"
    assert any("named pipe" in p for p in res.problems), res.problems


# --- read_regular_file: every file a configuration names is read through it ---------------


def test_read_regular_file_reads_a_small_file(tmp_path: Path) -> None:
    (tmp_path / "f").write_bytes(b"abc\n")
    assert read_regular_file(tmp_path / "f", 4) == b"abc\n"
    (tmp_path / "empty").write_bytes(b"")
    assert read_regular_file(str(tmp_path / "empty"), 0) == b""


@pytest.mark.parametrize(
    ("target", "why"),
    [
        ("/dev/zero", "character device"),
        ("/dev/urandom", "character device"),
        ("fifo", "named pipe"),
        ("dir", "directory"),
        ("big", "over the 1024-byte limit"),
        ("nul\0name", "NUL byte"),
    ],
)
def test_read_regular_file_refuses_what_could_hang_or_flood(
    tmp_path: Path, target: str, why: str
) -> None:
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dir").mkdir()
    (tmp_path / "big").write_bytes(b"x" * 1025)
    path = target if target.startswith("/") else str(tmp_path / target)
    t0 = time.monotonic()
    with pytest.raises(FileRefused, match=why):
        read_regular_file(path, 1024)
    assert time.monotonic() - t0 < 5.0  # refused, not read until memory runs out


def test_read_regular_file_through_a_symlink_to_a_device_is_refused(tmp_path: Path) -> None:
    (tmp_path / "key").symlink_to("/dev/zero")
    with pytest.raises(FileRefused, match="character device"):
        read_regular_file(tmp_path / "key", 64)
    with pytest.raises(FileMissing):
        read_regular_file(tmp_path / "missing", 64)


def test_state_dir_resolution(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("STATE_DIRECTORY", "/run/a:/run/b")
    assert resolve_state_dir("") == Path("/run/a")
    assert resolve_state_dir("/x") == Path("/x")
    monkeypatch.delenv("STATE_DIRECTORY")
    assert resolve_state_dir("") == Path("/var/lib/compass-bridge")


_SAVER = """
import sys
from bridge.storage import StateStore
store = StateStore(sys.argv[1])
i = int(store.load("calibration").payload["gen"]) + 1
store.save("calibration", {"gen": i, "pad": "x" * 20000})
print("saved", flush=True)
while True:
    i += 1
    store.save("calibration", {"gen": i, "pad": "x" * 20000})
"""


@pytest.mark.integration
def test_kill_9_during_saves_never_loses_calibration(tmp_path: Path) -> None:
    """kill -9 a process that saves in a tight loop, many times: a valid copy always loads."""
    store = StateStore(tmp_path)
    store.save("calibration", {"gen": 0, "pad": ""})
    last = 0
    deadline = time.monotonic() + 100  # 25 interpreters started on a loaded 2-core machine
    for i in range(25):
        assert time.monotonic() < deadline
        proc = subprocess.Popen(
            [sys.executable, "-c", _SAVER, str(tmp_path)], stdout=subprocess.PIPE, text=True
        )
        assert proc.stdout is not None
        # "saved" once its first save is complete: the kill lands while it saves again
        assert proc.stdout.readline().strip() == "saved"
        time.sleep(0.005 * (i % 7))  # land the kill at varying points of a later save
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        res = store.load("calibration")
        assert res.payload is not None, res.problems
        gen = int(res.payload["gen"])
        # A completed save survives the kill; at most the save in flight is lost.
        assert gen > last, (gen, last, res.source)
        last = gen
