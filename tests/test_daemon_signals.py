"""The daemon's main loop sleeps until a signal wakes it; SIGHUP and SIGTERM stay prompt.

It looked five times a second for a stop or a reload, and beat for a watchdog nobody
read, with or without a service manager. Without one it now sleeps until a signal
comes: the SIGHUP handler and the SIGINT/SIGTERM handler it finds (the CLI's, which sets
``stop``) wake it. A caller in another thread (no signals there) or a replay (its end)
keep the look; a service manager (``$NOTIFY_SOCKET``) gets a beat a second. Real signals, delivered to this
process while :meth:`Service.run` runs in its main thread, as under ``compass-bridge run``.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_until

from bridge.cli import stop_on_signals
from bridge.config import Config, config_from_mapping
from bridge.daemon import Service
from bridge.daemon.runner import MAIN_TICK_S, MANAGED_BEAT_S, SILENCE_LIMIT_S

pytestmark = pytest.mark.integration  # real signals, a real daemon's threads

DEADLINE_S = 10.0


def config(state: Path, **device: Any) -> Config:
    raw = {
        "device": {"port": "sim", "rate_hz": 10, **device},
        "storage": {"dir": str(state)},
        "mavlink": {"endpoints": []},
    }
    return config_from_mapping(raw, env={}, hostname="t")


def wait_for(pred: Callable[[], bool]) -> bool:
    return wait_until(pred, DEADLINE_S)


def test_sighup_and_sigterm_wake_the_sleeping_main_loop(tmp_path: Path) -> None:
    assert threading.current_thread() is threading.main_thread()
    cfg = config(tmp_path / "state")
    svc = Service(cfg, lambda c, d: [], reload_config=lambda: cfg, env={})
    stop = threading.Event()
    seen: dict[str, Any] = {}

    def drive() -> None:
        try:
            if not wait_for(lambda: svc._signals):
                return
            seen["tick"] = svc._tick_s()  # no manager, signals installed: no look at all
            os.kill(os.getpid(), signal.SIGHUP)
            seen["reloaded"] = wait_for(lambda: svc.reloads == 1)
            os.kill(os.getpid(), signal.SIGTERM)  # the CLI's handler sets stop
        finally:
            # A loop that no signal woke would sleep for ever: wake it, and fail below.
            if not wait_for(lambda: not svc._signals):
                seen["stuck"] = True
                stop.set()
                svc._wake.set()

    driver = threading.Thread(target=drive, daemon=True)
    before = signal.getsignal(signal.SIGHUP)
    with stop_on_signals(stop):
        cli_term = signal.getsignal(signal.SIGTERM)
        driver.start()
        t_run = time.monotonic()
        assert svc.run(stop) == 0
        took = time.monotonic() - t_run
        assert signal.getsignal(signal.SIGTERM) is cli_term  # the CLI's handler is back
    driver.join(DEADLINE_S)
    assert "stuck" not in seen and seen.get("reloaded"), seen
    # No look at all: the reload and the stop came from the signals' wake-ups alone.
    assert seen["tick"] is None
    assert stop.is_set() and took < DEADLINE_S
    assert signal.getsignal(signal.SIGHUP) is before


def test_the_loop_still_looks_where_no_signal_can_wake_it(tmp_path: Path) -> None:
    state = tmp_path / "state"
    # Run from another thread: no signal handler there, so stop is only seen by looking.
    svc = Service(config(state), lambda c, d: [], env={})
    assert svc._tick_s() == MAIN_TICK_S
    # A service manager reads the beats (STATUS, watchdog pings): they keep coming.
    sock = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as manager:
        manager.bind(str(sock))
        watched = Service(config(state), lambda c, d: [], env={"NOTIFY_SOCKET": str(sock)})
        stop = threading.Event()
        th = threading.Thread(target=watched.run, args=(stop,), daemon=True)
        th.start()
        try:
            assert wait_for(lambda: watched.notify.active)
            assert watched._tick_s() == MAIN_TICK_S  # run outside the main thread
            watched._signals = True  # as if in the main thread: the manager's beats alone
            # (four of them in the silence limit: a hung part is seen as soon as before)
            assert watched._tick_s() == MANAGED_BEAT_S <= SILENCE_LIMIT_S / 4
        finally:
            stop.set()
            th.join(DEADLINE_S)
        assert not th.is_alive()
    # A replay ends by itself: the loop looks for its end.
    replay = Service(config(state), lambda c, d: [], env={})
    replay.cfg = replace(replay.cfg, device=replace(replay.cfg.device, port="replay:run.cbrec"))
    replay._signals = True
    assert replay._tick_s() == MAIN_TICK_S
    for s in (svc, replay):
        s.daemon.stop(timeout=1.0)
