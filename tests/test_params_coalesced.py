"""Parameter writes are gentle and complete: a storm of sets is about one params.json write a
second, nothing set is lost at shutdown, and a write that failed is done once storage is back
(said when it fails and when it works again). A real state directory (real files, fsync)."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from harness import ManualClock

from bridge.app.params import PARAMS_DOCUMENT, SAVE_INTERVAL_S, ParamStore
from bridge.app.paramspec import same_calibration
from bridge.app.settings import EngineSettings
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import Calibration
from bridge.documents import LoadResult
from bridge.events import Event, EventBus
from bridge.storage import StateStore
from bridge.zenoh.services import calibration_state

pytestmark = pytest.mark.integration  # real sockets, processes or threads


class CountingStore:
    """The real state directory, counting the writes that reach it."""

    def __init__(self, directory: Path) -> None:
        self.inner = StateStore(directory)
        self.writes: list[float] = []

    def save(self, name: str, payload: dict[str, Any], version: int = 1) -> None:
        self.writes.append(time.monotonic())
        self.inner.save(name, payload, version)

    def load(self, name: str) -> LoadResult:
        return self.inner.load(name)


def make(directory: Path, events: EventBus | None = None) -> tuple[ParamStore, CountingStore]:
    docs = CountingStore(directory)
    settings = EngineSettings(AttitudeEngine(Calibration()))
    return ParamStore(settings, docs, events=events), docs


def stored(directory: Path) -> dict[str, float]:
    payload = StateStore(directory).load(PARAMS_DOCUMENT).payload or {}
    return dict(payload.get("set", {}))


def test_a_set_storm_is_about_one_write_a_second_and_nothing_is_lost(tmp_path: Path) -> None:
    params, docs = make(tmp_path / "state")
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < 3.0:  # as fast as sets come (thousands a second)
        assert params.set("BRG_SR_HUD", float(1 + n % 40)).accepted
        n += 1
    elapsed = time.monotonic() - t0
    assert n > 1000
    assert len(docs.writes) <= elapsed / SAVE_INTERVAL_S + 2, (len(docs.writes), n)
    gaps = [b - a for a, b in zip(docs.writes, docs.writes[1:], strict=False)]
    assert all(g >= 0.9 * SAVE_INTERVAL_S for g in gaps), gaps
    last = params.get("BRG_SR_HUD")
    params.close()  # the bridge stops a moment after the last set: it is written
    assert stored(tmp_path / "state")["BRG_SR_HUD"] == last


class Answers:
    """``save_then``'s callbacks: each answer, and an event when one comes."""

    def __init__(self) -> None:
        self.got: list[bool] = []
        self.came = threading.Event()

    def __call__(self, ok: bool) -> None:
        self.got.append(ok)
        self.came.set()

    def next(self) -> bool:
        assert self.came.wait(5.0), "no answer from the paced write"
        self.came.clear()
        return self.got[-1]


def test_an_explicit_save_storm_is_paced_too_and_no_caller_waits(tmp_path: Path) -> None:
    """PREFLIGHT_STORAGE write, again and again, each right after a set: every value is
    written, a write a second at most, and the caller (MAVLink's dispatch) is never held:
    within the interval it is answered later, from the saver's write."""
    params, docs = make(tmp_path / "state")
    answers = Answers()
    later = 0
    for i in range(5):
        params.set("BRG_SR_HUD", float(i + 1))
        now = params.save_then(answers)
        if now is None:  # the last write was less than a second ago
            later += 1
            assert answers.next() is True
        else:
            assert now is True and not answers.got
        assert stored(tmp_path / "state")["BRG_SR_HUD"] == float(i + 1)
    assert later >= 4  # (the first may find the saver's write done or the interval over)
    assert len(docs.writes) == 5 and len(answers.got) == later
    gaps = [b - a for a, b in zip(docs.writes, docs.writes[1:], strict=False)]
    assert all(g >= 0.9 * SAVE_INTERVAL_S for g in gaps), gaps
    params.close()


def test_a_save_with_nothing_pending_writes_nothing_and_waits_for_nothing(tmp_path: Path) -> None:
    """PREFLIGHT_STORAGE after the saver has written what was set: the stored values are
    those in use, so nothing is written again and the answer is at once."""
    params, docs = make(tmp_path / "state")
    answers = Answers()
    params.set("BRG_SR_HUD", 3.0)
    assert params.save_then(answers) is True  # the first write: due at once (saver's or its)
    writes = len(docs.writes)
    assert writes == 1
    for _ in range(3):
        assert params.save_then(answers) is True
    assert len(docs.writes) == writes
    params.set("BRG_SR_HUD", 4.0)  # pending again: written, paced as before
    if params.save_then(answers) is None:
        assert answers.next() is True
    assert len(docs.writes) == 2 and answers.got in ([], [True])
    assert stored(tmp_path / "state")["BRG_SR_HUD"] == 4.0
    params.close()


def test_read_back_with_a_write_pending_is_what_was_set_and_waits_for_nothing(
    tmp_path: Path,
) -> None:
    """PREFLIGHT_STORAGE read while the paced write is still to come: what was set is what
    is stored -- the values set are read back (not params.json's older ones), and so are
    those of a reset, with no write and no wait; the saver's write then puts them in the
    file. The store's clock is held still, so its saver writes only when it is moved on."""
    clock = ManualClock()  # (the store's: its saver writes only when it is moved on)
    docs = CountingStore(tmp_path / "state")
    params = ParamStore(EngineSettings(AttitudeEngine(Calibration())), docs, clock=clock)
    answers = Answers()
    params.set("BRG_SR_HUD", 3.0)
    assert params.save_then(answers) is True  # the first write: due at once
    params.set("BRG_SR_HUD", 7.0)  # pending: the file still says 3 until the clock moves
    params.set("BRG_SR_SIMU", 5.0)
    params.reload()
    assert params.get("BRG_SR_HUD") == 7.0 and params.get("BRG_SR_SIMU") == 5.0
    assert len(docs.writes) == 1 and stored(tmp_path / "state") == {"BRG_SR_HUD": 3.0}
    assert params.save_then(answers) is None
    clock.advance(SAVE_INTERVAL_S)  # the interval is over: the saver writes
    assert answers.next() is True
    assert stored(tmp_path / "state") == {"BRG_SR_HUD": 7.0, "BRG_SR_SIMU": 5.0}
    params.reset()  # pending again: the defaults are what is stored
    default = params.values()["BRG_SR_HUD"]
    params.reload()
    assert default != 7.0 and params.get("BRG_SR_HUD") == default
    assert len(docs.writes) == 2
    clock.advance(SAVE_INTERVAL_S)
    assert params.save_then(answers) is True  # the interval is over: written at once
    assert stored(tmp_path / "state") == {} and answers.got == [True]
    params.close()


def test_a_write_that_failed_is_done_when_storage_is_back(tmp_path: Path) -> None:
    blocker = tmp_path / "blocked"
    blocker.write_text("a file where the state directory's parent should be\n")
    events: list[Event] = []
    bus = EventBus()
    bus.subscribe(events.append)
    params, docs = make(blocker / "state", bus)
    got = threading.Event()
    bus.subscribe(lambda e: got.set() if e.kind == "params.saved" else None)
    for v in (2.0, 3.0, 5.0):
        params.set("BRG_SR_HUD", v)
    deadline = time.monotonic() + 5.0
    while not params.last_error and time.monotonic() < deadline:
        time.sleep(0.05)
    assert params.last_error and not params.saved
    time.sleep(2.5 * SAVE_INTERVAL_S)  # retried, still failing: said once, not every time
    assert [e.kind for e in events] == ["params.storage_error"]
    assert len(docs.writes) >= 2
    blocker.unlink()  # space is back
    assert got.wait(5.0)
    assert params.saved and stored(blocker / "state")["BRG_SR_HUD"] == 5.0
    assert [e.kind for e in events] == ["params.storage_error", "params.saved"]
    params.close()


def test_a_storm_of_compass_sets_is_in_force_at_once_and_written_once_a_second(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """COMPASS_* PARAM_SETs wrote calibration.json once each (200 sets: 200 writes, fsync
    each, on MAVLink's dispatch thread). Now the calibration group is paced as params.json
    is: each value in force at once, the file written at most once a second -- the last
    value included, by the calibration worker -- and at once when the bridge stops. A daemon
    that is never started, its calibration worker running, its real state directory."""
    from test_mavlink_rig import offline_daemon, wait_until

    writes: list[float] = []
    save = StateStore.save

    def counted(self: StateStore, name: str, payload: dict[str, Any], version: int = 1) -> None:
        if name == "calibration":
            writes.append(time.monotonic())
        save(self, name, payload, version)

    monkeypatch.setattr(StateStore, "save", counted)
    _, daemon = offline_daemon(tmp_path / "state", "storm")
    bridge = daemon.bridge
    bridge.calibrator.start()
    try:
        for i in range(200):
            assert bridge.params.set("COMPASS_OFS_X", float(1 + i % 50)).accepted
            assert bridge.params.get("COMPASS_OFS_X") == float(1 + i % 50)  # in force at once
        in_use = bridge.engine.calibration  # the last value's calibration, in force
        wanted = Calibration.from_ardupilot_parameters(bridge.params.values(), in_use.accel)
        assert same_calibration(in_use, wanted, tol=1e-9)
        assert len(writes) <= 3, len(writes)
        # the last one, by the worker
        assert wait_until(lambda: bridge.calibrator.snapshot().calibration_saved, 5.0)
        gaps = [b - a for a, b in itertools.pairwise(writes)]
        assert all(g >= 0.9 for g in gaps), gaps
        stored_doc = StateStore(tmp_path / "state").load("calibration").payload or {}
        assert stored_doc["view"]["COMPASS_OFS_X"] == 50.0  # the last value set
        bridge.params.set("COMPASS_OFS_X", 7.0)  # within the second: pending at the stop
        # Zenoh's status: not saved only for its pace is "saving", not a storage error (the
        # set a second after a stall of the machine would have been saved at once: either).
        zenoh_status = calibration_state(bridge.services)
        assert zenoh_status["saving"] is (not zenoh_status["saved"])
        assert zenoh_status["save_error"] is None
    finally:
        bridge.calibrator.close()
        bridge.params.close()
    stored_doc = StateStore(tmp_path / "state").load("calibration").payload or {}
    assert stored_doc["view"]["COMPASS_OFS_X"] == 7.0


def test_a_compass_set_storage_refused_is_saved_once_storage_is_back(tmp_path: Path) -> None:
    """A COMPASS_* set that storage refused is retried every RETRY_S by the calibration worker.
    The worker slept until a job came, and a set is no job: the calibration stayed unsaved
    (8 s after storage came back, still "NOT saved"). Now the set wakes it."""
    import shutil

    from test_mavlink_rig import offline_daemon, wait_until

    from bridge.app.calibration.keeper import RETRY_S

    state = tmp_path / "state"
    _, daemon = offline_daemon(state, "refused")
    bridge = daemon.bridge
    bridge.calibrator.start()
    try:
        if state.exists():
            shutil.rmtree(state)
        state.write_text("a file where the state directory should be\n")
        assert bridge.params.set("COMPASS_OFS_X", 12.0).accepted  # in force, not saved
        assert not bridge.calibrator.snapshot().calibration_saved
        refused = calibration_state(bridge.services)  # what Zenoh's status and `status` say
        assert refused["saved"] is False and refused["saving"] is False
        assert refused["save_error"]  # why, as storage said it
        assert bridge.params.set("BRG_SR_HUD", 7.0).accepted  # params.json: refused too
        assert wait_until(lambda: bridge.status().parameters_error != "", 5.0)
        state.unlink()  # storage is back
        assert wait_until(lambda: bridge.calibrator.snapshot().calibration_saved, RETRY_S + 5.0)
        assert calibration_state(bridge.services)["save_error"] is None
        assert wait_until(lambda: bridge.status().parameters_error == "", 5.0)
        stored_doc = StateStore(state).load("calibration").payload or {}
        assert stored_doc["view"]["COMPASS_OFS_X"] == 12.0
    finally:
        bridge.calibrator.close()
        bridge.params.close()
