"""The one bounded poll of the integration tier: tests that watch real threads, processes,
ptys and sockets have no event to wait on, so they ask a predicate until it holds or the
test's deadline passes. (The in-memory tier never waits: it runs on a manual clock,
``tests/harness.py``.)"""

from __future__ import annotations

import time
from collections.abc import Callable

from benchmarks.procstat import wait_until as _poll


def wait_until(pred: Callable[[], object], timeout: float, step: float = 0.01) -> bool:
    """Whether ``pred()`` held within ``timeout`` s: asked every ``step`` s, and once more
    at the end (a predicate that became true during the last sleep counts). The loop is the
    live benchmarks' (:func:`benchmarks.procstat.wait_until`), asked more often here."""
    return _poll(pred, timeout, step)


def wait_for(pred: Callable[[], object], what: str, timeout: float, step: float = 0.01) -> float:
    """:func:`wait_until` that fails the test (AssertionError naming ``what``) if ``pred``
    never held; returns the seconds it took."""
    start = time.monotonic()
    if not wait_until(pred, timeout, step):
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")
    return time.monotonic() - start
