"""No thread of the daemon dies silently: a worker that ends with an exception is
logged once and counted, and the watchdog stops pinging so the service manager restarts the
bridge. The service runs in-process on the simulated compass; the service manager is a real
unix datagram socket (tests/service_harness.py)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from service_harness import FakeServiceManager

from bridge.config import load_config
from bridge.daemon import Service, build_outputs, runner

pytestmark = pytest.mark.integration

DEADLINE_S = 15.0


@pytest.fixture
def service(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[Service, FakeServiceManager]]:
    monkeypatch.setattr(runner, "SILENCE_LIMIT_S", 1.0)  # the watchdog's patience, shortened
    manager = FakeServiceManager()
    cfg = load_config(
        None,
        ["device.port=sim", f"storage.dir={tmp_path / 'state'}", "mavlink.endpoints=[]"],
        env={},
    )
    env = {"NOTIFY_SOCKET": manager.notify_socket, "WATCHDOG_USEC": "600000"}
    svc = Service(cfg, lambda c, d: build_outputs(c, d, console=False), env=env)
    stop = threading.Event()
    th = threading.Thread(target=svc.run, args=(stop,), name="service-under-test", daemon=True)
    th.start()
    try:
        yield svc, manager
    finally:
        stop.set()
        th.join(DEADLINE_S)
        manager.close()
    assert not th.is_alive()


def test_a_worker_that_dies_stops_the_watchdog(
    service: tuple[Service, FakeServiceManager], caplog: pytest.LogCaptureFixture
) -> None:
    svc, manager = service
    i, _ = manager.wait_for(lambda m: m.get("WATCHDOG") == "1", timeout=DEADLINE_S)

    def worker() -> None:
        raise RuntimeError("boom")

    caplog.set_level(logging.ERROR, logger="bridge.daemon.runner")
    for _ in range(2):  # the second death of the same thread is counted, not logged again
        t = threading.Thread(target=worker, name="mavlink-dispatch")
        t.start()
        t.join(DEADLINE_S)
    assert svc.dead_threads() == ["mavlink-dispatch"]
    died = [r for r in caplog.records if "thread mavlink-dispatch died" in r.getMessage()]
    assert len(died) == 1 and died[0].exc_info is not None
    # Within the silence limit the STATUS says why, and no WATCHDOG=1 follows it.
    j, hung = manager.wait_for(
        lambda m: "thread mavlink-dispatch died" in (m.get("STATUS") or ""),
        after=i,
        timeout=DEADLINE_S,
    )
    assert "worker threads silent" in (hung.get("STATUS") or "")
    mark = len(manager.messages)
    manager.wait_for(lambda m: m.t - hung.t > 1.5, after=mark - 1, timeout=DEADLINE_S)
    assert not any(m.get("WATCHDOG") == "1" and m.t > hung.t + 0.2 for m in manager.since(j))


def test_healthy_workers_keep_the_watchdog_pinging(
    service: tuple[Service, FakeServiceManager],
) -> None:
    svc, manager = service
    i, _ = manager.wait_for(lambda m: m.get("WATCHDOG") == "1", timeout=DEADLINE_S)
    manager.wait_for(
        lambda m: sum(1 for x in manager.since(i) if x.get("WATCHDOG") == "1") >= 6,
        after=i,
        timeout=DEADLINE_S,
    )
    assert svc.dead_threads() == []
