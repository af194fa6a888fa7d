"""sd_notify over real unix datagram sockets; the watchdog thread against a controlled clock."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from harness import ManualClock

from benchmarks.procstat import datagrams
from bridge.link.observed import ObservedTransport
from bridge.systemd.notify import (
    Liveness,
    Notifier,
    ServiceNotifier,
    notify_address,
    watchdog_interval_s,
)
from bridge.types import ClosedOnExit

DEADLINE_S = 5.0


class FakeManager(ClosedOnExit):
    """The service manager's end: a bound AF_UNIX datagram socket that collects messages."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)
        self.sock.settimeout(0.05)
        self.messages: list[dict[str, str]] = []

    def pump(self, seconds: float) -> None:
        for data in datagrams(self.sock, within_s=seconds):
            self.messages.append(dict(line.split("=", 1) for line in data.decode().split("\n")))

    def wait_for(
        self, pred: Callable[[dict[str, str]], bool], timeout: float = DEADLINE_S
    ) -> dict[str, str]:
        end = time.monotonic() + timeout
        seen = 0
        while time.monotonic() < end:
            for m in self.messages[seen:]:
                if pred(m):
                    return m
            seen = len(self.messages)
            self.pump(0.05)
        raise AssertionError(f"no matching message within {timeout} s; got {self.messages}")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def abstract_manager() -> Iterator[tuple[FakeManager, str]]:
    name = f"compass-bridge-test-{os.getpid()}-{threading.get_ident()}"
    with FakeManager("\0" + name) as mgr:
        yield mgr, "@" + name


def test_address_forms() -> None:
    assert notify_address("/run/systemd/notify") == "/run/systemd/notify"
    assert notify_address("@abc") == "\0abc"
    assert notify_address("vsock:2:1234") is None
    assert notify_address("@") is None
    assert notify_address("relative") is None


@pytest.mark.integration
def test_path_socket_messages(tmp_path: Path) -> None:
    with FakeManager(str(tmp_path / "notify")) as mgr:
        n = Notifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "notify")})
        assert n.enabled
        assert n.ready("up and\nrunning")
        assert n.watchdog()
        assert n.stopping()
        mgr.pump(0.2)
        assert mgr.messages[0] == {"READY": "1", "STATUS": "up and running"}
        assert mgr.messages[1] == {"WATCHDOG": "1"}
        assert mgr.messages[2] == {"STOPPING": "1"}


@pytest.mark.integration
def test_abstract_socket_and_reloading_carries_monotonic_usec(
    abstract_manager: tuple[FakeManager, str],
) -> None:
    mgr, env_value = abstract_manager
    n = Notifier.from_env({"NOTIFY_SOCKET": env_value})
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    ServiceNotifier(n, Liveness(), status=lambda: "", streaming=lambda: True).reloading()
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    msg = mgr.wait_for(lambda m: "RELOADING" in m)
    assert msg["RELOADING"] == "1"
    assert before <= int(msg["MONOTONIC_USEC"]) <= after


def test_no_socket_is_a_silent_no_op() -> None:
    n = Notifier.from_env({})
    assert not n.enabled
    assert n.ready() is False
    assert n.errors == 0


@pytest.mark.integration
def test_missing_manager_is_counted_not_raised(tmp_path: Path) -> None:
    n = Notifier(str(tmp_path / "nobody-listens"))
    assert n.watchdog() is False
    assert n.watchdog() is False
    assert n.errors == 2


@pytest.mark.integration
def test_full_manager_queue_never_blocks(tmp_path: Path) -> None:
    with FakeManager(str(tmp_path / "notify")):  # bound, but never read
        n = Notifier(str(tmp_path / "notify"))
        t0 = time.monotonic()
        results = [n.status("x" * 300) for _ in range(5000)]
        assert time.monotonic() - t0 < DEADLINE_S  # a blocking send would hang here
        assert not all(results) and n.errors > 0  # the queue filled up: counted, not waited on


@pytest.mark.integration
def test_status_is_one_line_and_bounded(tmp_path: Path) -> None:
    with FakeManager(str(tmp_path / "notify")) as mgr:
        Notifier(str(tmp_path / "notify")).status("a\nb\r\nc " + "z" * 1000)
        msg = mgr.wait_for(lambda m: "STATUS" in m)
        assert msg["STATUS"].startswith("a b c z")
        assert len(msg) == 1 and len(msg["STATUS"]) <= 400


def test_watchdog_interval_parsing() -> None:
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 10.0
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "ten"}) is None
    # Inherited from a parent that is the one being watched: not ours.
    assert watchdog_interval_s({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}, pid=42) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "42"}, pid=42) == 1.0


def test_liveness_reports_only_parts_silent_too_long() -> None:
    lv = Liveness()
    lv.watch("reader", 2.0, now=100.0)
    lv.watch("main", 5.0, now=100.0)
    assert lv.silent(101.0) == []
    lv.beat("main", 102.5)
    lv.beat("unknown", 102.5)  # ignored, not an error
    silent = dict(lv.silent(103.0))
    assert list(silent) == ["reader"] and silent["reader"] == pytest.approx(3.0)
    lv.beat("reader", 103.0)
    assert lv.silent(104.0) == []
    assert [n for n, _ in lv.silent(108.0)] == ["reader", "main"]
    lv.forget("reader")
    assert [n for n, _ in lv.silent(108.0)] == ["main"]
    with pytest.raises(ValueError):
        lv.watch("x", 0.0, now=0.0)


@contextlib.contextmanager
def _started(
    addr: str,
    streaming: bool,
    *,
    watch: tuple[str, float] | None = None,
    clock: ManualClock | None = None,
    **kw: float,
) -> Iterator[tuple[ServiceNotifier, ManualClock, Liveness, list[bool]]]:
    """A notifier telling the manager at ``addr`` (its ``@name``), on a manual clock (at
    1000 s unless one is given), started for the ``with`` block and closed after: its
    status and readiness follow ``streaming[0]`` (the list given, ``streaming`` at first);
    ``watch``, a part's name and the silence allowed it, is watched from the clock's start.
    Gives the notifier, clock, liveness, flag."""
    clock = ManualClock(1000.0) if clock is None else clock
    lv, flag = Liveness(), [streaming]
    if watch is not None:
        lv.watch(*watch, clock.t)
    svc = ServiceNotifier(
        Notifier(notify_address(addr) or ""),
        lv,
        status=lambda: f"streaming={flag[0]}",
        streaming=lambda: flag[0],
        clock=clock,
        **kw,
    )
    svc.start()
    try:
        yield svc, clock, lv, flag
    finally:
        svc.close()


@pytest.mark.integration
def test_ready_when_streaming_then_status_and_pings(
    abstract_manager: tuple[FakeManager, str],
) -> None:
    mgr, addr = abstract_manager
    with _started(addr, False, watch=("main", 3.0), watchdog_s=0.3) as (_, clock, lv, streaming):
        mgr.wait_for(lambda m: m.get("WATCHDOG") == "1")  # pings start before READY
        mgr.pump(0.3)
        assert not any("READY" in m for m in mgr.messages)
        streaming[0] = True
        ready = mgr.wait_for(lambda m: "READY" in m)
        assert ready["STATUS"] == "streaming=True"
        streaming[0] = False
        clock.t += 1.5  # past the status interval: the change is reported
        lv.beat("main", clock.t)
        mgr.wait_for(lambda m: m.get("STATUS") == "streaming=False")


@pytest.mark.integration
def test_ready_after_bounded_wait_says_why(abstract_manager: tuple[FakeManager, str]) -> None:
    mgr, addr = abstract_manager
    with _started(addr, False, ready_timeout_s=10.0) as (_, clock, _, _):
        mgr.pump(0.3)
        assert not any("READY" in m for m in mgr.messages)
        clock.t += 10.0
        msg = mgr.wait_for(lambda m: "READY" in m)
        assert "without a streaming compass" in msg["STATUS"]
        assert "streaming=False" in msg["STATUS"]


@pytest.mark.integration
def test_pings_stop_while_a_part_is_silent_and_resume(
    abstract_manager: tuple[FakeManager, str],
) -> None:
    """A wedged main loop (no beats) stops WATCHDOG=1; its return resumes them."""
    mgr, addr = abstract_manager
    with _started(addr, True, watch=("main loop", 4.0), watchdog_s=0.3) as (svc, clock, lv, _):
        mgr.wait_for(lambda m: m.get("WATCHDOG") == "1")
        clock.t += 5.0  # the main loop did not beat for 5 s ...

        def run_clock_until(pred: Callable[[], bool]) -> None:
            # ... and time goes on (pings are paced by the clock, 0.1 s per step here).
            end = time.monotonic() + DEADLINE_S
            while not pred() and time.monotonic() < end:
                clock.t += 0.1
                mgr.pump(0.05)
            assert pred()

        run_clock_until(lambda: svc.withheld_pings >= 3)
        mgr.pump(0.1)
        n_before, pings_before = len(mgr.messages), svc.pings
        run_clock_until(lambda: svc.withheld_pings >= 8)
        assert svc.pings == pings_before
        assert not any("WATCHDOG" in m for m in mgr.messages[n_before:])
        n_back = len(mgr.messages)
        lv.beat("main loop", clock.t)  # it is back
        run_clock_until(lambda: svc.pings > pings_before)
        mgr.pump(0.2)
        assert any(m.get("WATCHDOG") == "1" for m in mgr.messages[n_back:])


@pytest.mark.integration
def test_stopping_suppresses_later_status(abstract_manager: tuple[FakeManager, str]) -> None:
    mgr, addr = abstract_manager
    with _started(addr, True) as (svc, clock, _, streaming):
        mgr.wait_for(lambda m: "READY" in m)
        svc.stopping("stopping")
        mgr.wait_for(lambda m: "STOPPING" in m)
        streaming[0] = False
        clock.t += 5.0
        mgr.pump(0.5)
        assert not any(m.get("STATUS") == "streaming=False" for m in mgr.messages)


class _FakePort:
    """A transport stand-in for the wrapper's pass-through (the real ports are in other tests)."""

    name = "/dev/fake"
    interactive = True
    baud = 115200

    def __init__(self) -> None:
        self.closed = 0
        self.block: threading.Event | None = None  # set: read() waits for it (a wedged driver)

    def open(self) -> None:
        pass

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self.block is not None:
            self.block.wait(DEADLINE_S)
        return b"x"

    def write(self, data: bytes) -> None:
        pass

    def close(self) -> None:
        self.closed += 1


@pytest.mark.integration
def test_observed_transport_beats_and_swaps() -> None:
    clock, lv = ManualClock(1000.0), Liveness()
    lv.watch("reader", 2.0, clock.t)
    inner = _FakePort()
    wt = ObservedTransport(inner, lambda: lv.beat("reader", clock.t))
    assert wt.baud == 115200 and wt.name == "/dev/fake"
    clock.t += 1.5
    assert wt.read(10, 0.05) == b"x"
    clock.t += 1.5
    assert lv.silent(clock.t) == []  # the read 1.5 s ago was a beat

    # A read that does not return (a wedged driver) is no beat: the reader goes silent.
    hung = threading.Event()
    inner.block = hung
    done = threading.Event()

    def reader() -> None:
        wt.read(10, 0.05)
        done.set()

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    assert not done.wait(0.3)
    clock.t += 3.0
    assert [n for n, _ in lv.silent(clock.t)] == ["reader"]
    hung.set()
    assert done.wait(DEADLINE_S)
    inner.block = None
    assert lv.silent(clock.t) == []  # the read returned: a beat

    # A reload's new transport is taken on by the reader: its read fails once, the old closes.
    new = _FakePort()
    new.name = "/dev/new"
    wt.replace(new)
    with pytest.raises(OSError, match="reload"):
        wt.read(10, 0.05)
    assert inner.closed == 1 and wt.name == "/dev/new"
    assert wt.read(10, 0.05) == b"x"


def test_without_a_manager_no_thread_wakes_to_build_statuses() -> None:
    calls: list[str] = []

    def status() -> str:
        calls.append("status")
        return "streaming"

    svc = ServiceNotifier(Notifier.from_env({}), Liveness(), status=status, streaming=lambda: True)
    before = set(threading.enumerate())
    svc.start()
    try:
        assert [t for t in threading.enumerate() if t not in before and t.name == "sd-notify"] == []
        assert calls == [] and not svc.ready_sent  # nothing built, nothing claimed sent
    finally:
        svc.close()


class CountingClock(ManualClock):
    """The manual clock, counting its readings: the thread reads it once a wake-up."""

    def __init__(self) -> None:
        super().__init__()
        self.readings = 0

    def __call__(self) -> float:
        self.readings += 1
        return self.t


@pytest.mark.integration
def test_after_ready_the_thread_sleeps_until_its_next_status_look_or_ping(
    abstract_manager: tuple[FakeManager, str],
) -> None:
    """Once READY is out, nothing is due before the next STATUS look (1 s) or ping
    (watchdog / 3, 2 s here): the thread sleeps until then instead of ticking five times a
    second. Time stands still here, so over 0.8 s of real time it wakes at most once."""
    mgr, addr = abstract_manager
    clock = CountingClock()
    with _started(addr, True, clock=clock, watchdog_s=6.0) as (svc, _, _, streaming):
        mgr.wait_for(lambda m: "READY" in m)
        mgr.pump(0.2)
        before = clock.readings
        mgr.pump(0.8)
        assert clock.readings - before <= 2  # a tick of 0.2 s would read it four times
        streaming[0] = False
        clock.t += 1.0  # the status look is due: the change goes out
        mgr.wait_for(lambda m: m.get("STATUS") == "streaming=False")
        clock.t += 1.0  # ... and the ping (2 s after the last)
        mgr.wait_for(lambda m: m.get("WATCHDOG") == "1" and svc.pings >= 2)
