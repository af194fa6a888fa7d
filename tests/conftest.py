"""Fixtures shared by the test modules, and how the suite is spread over pytest-xdist workers.

Three things here keep the whole suite (real autopilots included) short on two cores:

* **Bytecode is written** even under ``PYTHONDONTWRITEBYTECODE``: without it every xdist
  worker re-parses and assertion-rewrites all ~110 test modules (about 7 s of CPU each,
  8.8 s against 1.7 s with the cache) and the ~75 Hypothesis modules conftest imports
  (pytest rewrites a plugin's distribution too: 0.8 s a process), and every
  ``compass-bridge`` subprocess recompiles the package. The caches go where Python puts
  them (``__pycache__``, ignored by git; the virtualenv's for Hypothesis).
* **The controller warms that cache once** before the workers start (a collection in a
  subprocess, only when a test module is newer than its rewritten copy), so a fresh
  checkout (CI) does not have twelve workers rewriting the same modules at once.
* **Tests marked ``slow``** (tens of seconds of wall time: real-time autopilots, long
  scenarios) are put at the head of each worker's first share of the collection
  (``--dist worksteal`` splits the collection into one contiguous share a worker), so they
  start at once, side by side, and the short tests fill the time around them.

``-p no:xdist`` (the in-memory tier's command) works too: the xdist options in
pyproject's ``addopts`` are then accepted and ignored.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import logging
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

# Before any test module, the package under test or Hypothesis is imported by this process
# (set after the import below, it left Hypothesis's rewritten modules uncached: rewritten
# again by every run and every xdist worker).
sys.dont_write_bytecode = False

import pytest  # noqa: E402
from helpers import EVERYDAY_SHARE, THOROUGH  # noqa: E402
from hypothesis import settings  # noqa: E402
from service_harness import FakeServiceManager  # noqa: E402

if TYPE_CHECKING:
    from test_mavlink_rig import Rig

# Hypothesis's per-example deadline (200 ms) is a wall-clock bound: with both cores busy the
# first example (lazy imports, caches) misses it and the test fails for the machine, not
# the code. Speed is shown by the benchmarks; the properties here are about results.
# A property test with no count of its own runs Hypothesis's 100 examples in CI and a third
# of them everyday, as those with one do (helpers.examples).
DEFAULT_EXAMPLES = 100
settings.register_profile(
    "compass-bridge",
    deadline=None,
    max_examples=DEFAULT_EXAMPLES if THOROUGH else DEFAULT_EXAMPLES // EVERYDAY_SHARE,
)
settings.load_profile("compass-bridge")

# The collector's young generation at 10 000 objects rather than 700: the suite allocates
# (and keeps, in module caches) enough that the default thresholds ran ~2000 collections
# and 17 full ones over the in-memory tier, 0.9 s of its time; these run ~200 and two,
# 0.6 s (measured with gc.callbacks). Nothing here relies on a collection's timing.
gc.set_threshold(10_000, 20, 20)

_TESTS = Path(__file__).resolve().parent


def pytest_addoption(parser: pytest.Parser, pluginmanager: pytest.PytestPluginManager) -> None:
    if not pluginmanager.has_plugin("xdist"):
        # pyproject's addopts name xdist's options; without the plugin they mean nothing.
        group = parser.getgroup("xdist (not loaded)")
        group.addoption("--numprocesses", default=None, help="ignored: xdist is not loaded")
        group.addoption("--dist", default="no", help="ignored: xdist is not loaded")


def _stale_test_modules() -> list[Path]:
    """Test modules whose assertion-rewritten bytecode is missing or older than the source."""
    try:
        from _pytest.assertion.rewrite import PYC_TAIL
    except ImportError:  # pytest moved it: warm every time rather than guess the name
        return sorted(_TESTS.glob("test_*.py"))
    stale = []
    for src in sorted(_TESTS.glob("test_*.py")):
        pyc = src.parent / "__pycache__" / (src.name[:-3] + PYC_TAIL)
        if not pyc.exists() or pyc.stat().st_mtime < src.stat().st_mtime:
            stale.append(src)
    return stale


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session: pytest.Session) -> None:
    config = session.config
    if hasattr(config, "workerinput") or os.environ.get("COMPASS_BRIDGE_WARMING"):
        return
    workers = (
        config.getoption("numprocesses", None) if config.pluginmanager.has_plugin("xdist") else None
    )
    if not workers or config.getoption("collectonly"):
        return
    if not _stale_test_modules():
        return
    # The workers start after this hook (xdist's own sessionstart starts them).
    # (A failure here only costs the workers the time it would have saved them.)
    with contextlib.suppress(subprocess.SubprocessError, OSError):
        subprocess.run(
            [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
             "--numprocesses", "0", str(_TESTS)],
            cwd=config.rootpath,
            env={**os.environ, "COMPASS_BRIDGE_WARMING": "1"},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            timeout=120,
            check=False,
        )  # fmt: skip


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    # (xdist's controller) a worker's own options say dist "no": tell it the real mode.
    node.workerinput["compass_bridge_dist"] = node.config.getoption("dist")


def pytest_collection_finish(session: pytest.Session) -> None:
    # What collection built (modules, thousands of items, Hypothesis's strategies) lives to
    # the end: freezing it spares every full garbage collection from walking it again
    # (a second or two of the in-memory tier's time); nothing frozen was garbage.
    gc.collect()
    gc.freeze()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    workerinput = getattr(config, "workerinput", None)
    if workerinput is None or workerinput.get("compass_bridge_dist") != "worksteal":
        return
    n = int(workerinput["workercount"])
    slow = [it for it in items if it.get_closest_marker("slow") is not None]
    if not slow or n < 2:
        return
    rest = [it for it in items if it.get_closest_marker("slow") is None]
    # xdist's WorkStealingScheduling gives idle node i (of n) len(pending) // (n - i)
    # consecutive items; rebuild the collection share by share, slow tests first.
    sizes, left = [], len(items)
    for i in range(n):
        sizes.append(left // (n - i))
        left -= sizes[-1]
    shares: list[list[pytest.Item]] = [[] for _ in range(n)]
    for k, it in enumerate(slow):
        shares[k % n].append(it)
    out: list[pytest.Item] = []
    it_rest = iter(rest)
    for share, size in zip(shares, sizes, strict=True):
        out += share
        out += itertools.islice(it_rest, max(0, size - len(share)))
    out += it_rest
    items[:] = out


@pytest.fixture
def manager() -> Iterator[FakeServiceManager]:
    """A fake service manager (``$NOTIFY_SOCKET``) for a daemon subprocess; closed after."""
    m = FakeServiceManager()
    yield m
    m.close()


@pytest.fixture
def rigs() -> Iterator[Callable[..., Rig]]:
    """Started MAVLink rigs (tests/test_mavlink_rig.py: the daemon and its MAVLink output on
    a simulated compass), every one stopped at the end of the test. The calibrator's modules
    (test_calibrator.py and those importing its fixture) have rigs of their own, which
    override this one there."""
    from test_mavlink_rig import rig_factory

    yield from rig_factory()


@pytest.fixture
def restore_logging() -> Iterator[None]:
    """The root logger's handlers and level put back after the test.

    ``main()`` configures the root logger (``force=True``) for the process; an in-process
    call must not leave a handler writing to a finished test's captured stderr. The
    modules that call ``main()`` in-process ask for it with
    ``pytestmark = pytest.mark.usefixtures("restore_logging")``.
    """
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
