"""Service logging: one line per record, journald priority prefixes, rate-limited repeats."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
from harness import ManualClock

from bridge.logsetup import (
    RateLimiter,
    ServiceLogHandler,
    one_line,
    setup_logging,
    stream_is_journal,
    syslog_priority,
)


def _logger(handler: logging.Handler, name: str = "bridge.test") -> logging.Logger:
    lg = logging.getLogger(name)
    lg.handlers[:] = [handler]
    lg.propagate = False
    lg.setLevel(logging.DEBUG)
    return lg


def test_priorities_follow_syslog() -> None:
    assert syslog_priority(logging.CRITICAL) == 2
    assert syslog_priority(logging.ERROR) == 3
    assert syslog_priority(logging.WARNING) == 4
    assert syslog_priority(logging.INFO) == 6
    assert syslog_priority(logging.DEBUG) == 7
    assert syslog_priority(logging.INFO + 5) == 6  # custom levels fall to the one below


def test_journal_detection_compares_dev_and_inode(tmp_path: Path) -> None:
    with open(tmp_path / "a", "w") as a, open(tmp_path / "b", "w") as b:
        st = os.fstat(a.fileno())
        env = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert stream_is_journal(a, env)
        assert not stream_is_journal(b, env)  # inherited variable, stderr redirected elsewhere
        assert not stream_is_journal(a, {})
        assert not stream_is_journal(a, {"JOURNAL_STREAM": "garbage"})
    assert not stream_is_journal(io.StringIO(), env)  # no file descriptor at all


def test_one_line_per_record_with_traceback() -> None:
    out = io.StringIO()
    lg = _logger(ServiceLogHandler(out, journal=True))
    try:
        raise ValueError("bad\nthing")
    except ValueError:
        lg.exception("frame %s failed", "A\r\nB")
    lg.info("fine")
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("<3>ERROR bridge.test: frame A\\nB failed\\nTraceback")
    assert "ValueError: bad\\nthing" in lines[0]
    assert lines[1] == "<6>INFO bridge.test: fine"
    assert one_line("a\n\n") == "a"


def test_not_journal_has_timestamps_and_no_prefix() -> None:
    out = io.StringIO()
    lg = _logger(ServiceLogHandler(out, journal=False))
    lg.warning("port %s lost", "/dev/compass")
    line = out.getvalue().rstrip("\n")
    assert not line.startswith("<")
    assert line.endswith("WARNING bridge.test: port /dev/compass lost")
    assert line[:4].isdigit()  # asctime first


def test_repeats_are_rate_limited_and_summarised() -> None:
    out, clock = io.StringIO(), ManualClock(50.0)
    lg = _logger(ServiceLogHandler(out, journal=True, burst=3, interval_s=10.0, clock=clock))
    for i in range(50):
        lg.warning("port lost: %d", i)  # one call site
        if i < 2:
            lg.info("other %d", i)  # another call site, unaffected
        clock.t += 0.1
    lines = out.getvalue().splitlines()
    lost = [ln for ln in lines if "port lost" in ln]
    assert lost == [f"<4>WARNING bridge.test: port lost: {i}" for i in range(3)]
    assert sum("other" in ln for ln in lines) == 2
    clock.t += 10.0  # the window ends; the next record of any kind brings the summary
    lg.info("tick")
    tail = out.getvalue().splitlines()[len(lines) :]
    assert (
        tail[0]
        == "<4>WARNING bridge.test: 47 similar messages suppressed in 10 s (first: port lost: 3)"
    )
    assert tail[1] == "<6>INFO bridge.test: tick"
    lg.warning("port lost: %d", 99)  # a new window: let through again
    assert out.getvalue().splitlines()[-1].endswith("port lost: 99")


def test_the_rate_limit_is_per_event_kind() -> None:
    """Every event is logged by one call site (the bus): a flood of one kind must not hide
    another kind (it did: "5685 similar messages suppressed (first: calibration.accepted)")."""
    from bridge.events import Event, EventBus, Severity

    out, clock = io.StringIO(), ManualClock(50.0)
    handler = ServiceLogHandler(out, journal=True, burst=3, interval_s=10.0, clock=clock)
    bus_log = logging.getLogger("bridge.events")
    saved = bus_log.handlers[:], bus_log.propagate, bus_log.level
    _logger(handler, "bridge.events")
    try:
        bus = EventBus()
        for i in range(200):
            bus.emit(Event("calibration.accepted", f"accepted {i}", Severity.INFO))
            if i % 50 == 0:
                bus.emit(Event("link.lost", f"lost {i}", Severity.ERROR))
            clock.t += 0.01
        lines = out.getvalue().splitlines()
        assert sum("calibration.accepted" in ln for ln in lines) == 3
        assert [ln for ln in lines if "link.lost" in ln] == [
            f"<3>ERROR bridge.events: link.lost: lost {i}" for i in (0, 50, 100)
        ]
        clock.t += 10.0
        bus.emit(Event("link.restored", "back", Severity.NOTICE))
        tail = out.getvalue().splitlines()[len(lines) :]
        summaries = [ln for ln in tail if "suppressed" in ln]
        assert len(summaries) == 2  # one per kind, each naming its own
        assert any("197 similar" in ln and "calibration.accepted" in ln for ln in summaries)
        assert any("1 similar" in ln and "link.lost: lost 150" in ln for ln in summaries)
    finally:
        bus_log.handlers[:], bus_log.propagate = saved[0], saved[1]
        bus_log.setLevel(saved[2])


def test_suppressed_counts_are_flushed_at_close() -> None:
    out, clock = io.StringIO(), ManualClock(50.0)
    handler = ServiceLogHandler(out, journal=False, burst=1, interval_s=60.0, clock=clock)
    lg = _logger(handler)
    for _ in range(4):
        lg.error("disk full")
    handler.close()
    assert "3 similar messages suppressed" in out.getvalue().splitlines()[-1]


def test_limiter_bounds_its_memory() -> None:
    lim = RateLimiter(burst=1, interval_s=1.0)
    for i in range(5000):
        assert lim.admit(("site", i), now=float(i))
    assert len(lim._windows) <= 1024


def test_limiter_rejects_nonsense() -> None:
    with pytest.raises(ValueError):
        RateLimiter(burst=0)
    with pytest.raises(ValueError):
        RateLimiter(interval_s=0.0)


@pytest.mark.integration
def test_journal_prefixes_in_a_real_process_whose_stderr_is_the_stream(tmp_path: Path) -> None:
    """A child whose stderr matches $JOURNAL_STREAM writes <N> prefixes; redirected, it does not."""
    code = (
        "import logging, sys\n"
        "from bridge.logsetup import setup_logging\n"
        "setup_logging('INFO', sys.stderr)\n"
        "logging.getLogger('bridge.x').warning('hello')\n"
        "logging.getLogger('bridge.x').debug('hidden')\n"
    )
    log_path = tmp_path / "stderr.log"
    with open(log_path, "wb") as f:
        st = os.fstat(f.fileno())
        env = dict(os.environ, JOURNAL_STREAM=f"{st.st_dev}:{st.st_ino}")
        subprocess.run([sys.executable, "-c", code], stderr=f, env=env, timeout=60, check=True)
    assert log_path.read_text() == "<4>WARNING bridge.x: hello\n"
    other = tmp_path / "other.log"
    with open(other, "wb") as f:  # same variable, but stderr is another file
        subprocess.run([sys.executable, "-c", code], stderr=f, env=env, timeout=60, check=True)
    assert other.read_text().rstrip("\n").endswith(" WARNING bridge.x: hello")
    assert not other.read_text().startswith("<")


def test_setup_logging_replaces_root_handlers() -> None:
    root = logging.getLogger()
    saved_handlers, saved_level = root.handlers[:], root.level
    try:
        out = io.StringIO()
        h = setup_logging("DEBUG", out, env={})
        assert root.handlers == [h] and root.level == logging.DEBUG
        logging.getLogger("bridge.y").debug("x")
        assert out.getvalue().endswith("DEBUG bridge.y: x\n")
    finally:
        root.handlers[:] = saved_handlers
        root.setLevel(saved_level)
