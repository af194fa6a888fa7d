"""What the real-client tests share: MAVProxy as a subprocess, and values to set.

Imported by ``test_mavlink_client_*.py`` (``from mavlink_clients import ...``).

* :class:`MavProxy` runs ``mavproxy.py`` from the test's virtualenv against a
  rig, reads everything it prints (stdout and stderr) in a thread, and types
  at its prompt. It is started the way a user starts it, without
  ``--daemon``/``--non-interactive`` (those stop it reading its stdin); its
  ``--cmd`` runs before the link is up, so commands are typed after
  "Detected vehicle". Every wait has a deadline.
* :func:`signed_mav` is a pymavlink sender that signs what it packs (MAVLink 2 signing).
* :func:`new_value` picks, for any writable parameter, a valid value other
  than the current one (a float one that is not a whole number, so an integer
  reading would show).
"""

from __future__ import annotations

import os
import queue
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import pytest

from benchmarks.fuzz_hostile import signed
from bridge.app.paramspec import REAL32, SPECS, ParamSpec

DEADLINE_S = 20.0
#: MAVProxy's script, installed beside this Python (the README's test command installs it).
MAVPROXY = str(Path(sys.executable).with_name("mavproxy.py"))
#: MAVProxy's prompts ("MAV> ", "Mode(0x00000000)> "), printed in front of whatever comes next.
_PROMPTS = re.compile(r"^(?:[A-Za-z0-9_()]*> )+")


def f32(v: float) -> float:
    """``v`` rounded to float32, as it travels in PARAM_VALUE."""
    return float(struct.unpack("<f", struct.pack("<f", v))[0])


def writable() -> list[ParamSpec]:
    """Every parameter a ground station may set, in index order (COMPASS_AUTODEC comes
    before COMPASS_DEC, so the declination set after it sticks)."""
    return [s for s in SPECS if not s.read_only]


def new_value(spec: ParamSpec, current: float) -> float:
    """A valid value for ``spec`` other than ``current``."""
    if spec.choices:
        return float(next(c for c in spec.choices if c != current))
    if spec.ptype != REAL32:
        return float(current + 1 if current + 1 <= spec.maximum else current - 1)
    step = 0.375 * min(1.0, (spec.maximum - spec.minimum) / 4.0)
    return f32(current + step if current + step <= spec.maximum else current - step)


class MavProxy:
    """``mavproxy.py --master=URL`` in ``cwd``: its output lines, and its prompt."""

    def __init__(self, master: str, cwd: Path, *extra: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [MAVPROXY, f"--master={master}", "--no-state", *extra],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
            cwd=cwd,
        )
        self.lines: list[tuple[float, str]] = []  #: (seconds since start, line)
        self._queue: queue.Queue[tuple[float, str]] = queue.Queue()
        self._reader = threading.Thread(target=self._read, name="mavproxy-out", daemon=True)
        self._reader.start()
        self._seen = 0

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            text = _PROMPTS.sub("", line.rstrip("\n"))
            self._queue.put((time.monotonic() - self.t0, text))

    def _drain(self, timeout: float) -> None:
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            return
        self.lines.append(item)
        while True:
            try:
                self.lines.append(self._queue.get_nowait())
            except queue.Empty:
                return

    def send(self, command: str) -> None:
        """Type ``command`` at the prompt."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(
        self, pattern: str | Callable[[str], bool], timeout: float = DEADLINE_S
    ) -> tuple[float, str]:
        """The first line not consumed yet that matches ``pattern`` (a regular expression
        searched in the line, or a predicate); earlier lines stay in :attr:`lines`."""
        test = pattern if callable(pattern) else re.compile(pattern).search
        return self._expect_all({repr(pattern): test}, timeout)[repr(pattern)]

    def expect_each(self, patterns: dict[str, str], timeout: float = DEADLINE_S) -> dict[str, str]:
        """For each key, the first line not consumed yet that matches its pattern, in
        whatever order MAVProxy printed them: its answers to several requests in flight
        need not come back in the order asked (a ``param fetch`` prints the first
        PARAM_VALUE of that name to arrive, which may be a ``param set``'s late echo)."""
        tests = {key: re.compile(pattern).search for key, pattern in patterns.items()}
        return {key: line for key, (_, line) in self._expect_all(tests, timeout).items()}

    def _expect_all(
        self, tests: Mapping[str, Callable[[str], object]], timeout: float
    ) -> dict[str, tuple[float, str]]:
        """For each named test, the first line not consumed yet that it matches (a line
        answers one test); then every line up to the last of them counts as consumed."""
        found: dict[str, int] = {}
        scanned = self._seen
        deadline = time.monotonic() + timeout
        while True:
            for i in range(scanned, len(self.lines)):
                key = next(
                    (k for k, t in tests.items() if k not in found and t(self.lines[i][1])), None
                )
                if key is not None:
                    found[key] = i
            scanned = len(self.lines)
            if len(found) == len(tests):
                self._seen = max(found.values()) + 1
                return {key: self.lines[i] for key, i in found.items()}
            if time.monotonic() > deadline:
                missing = ", ".join(k for k in tests if k not in found)
                pytest.fail(f"MAVProxy printed no {missing} within {timeout} s:\n{self.text()}")
            if self.proc.poll() is not None and self._queue.empty():
                pytest.fail(f"MAVProxy exited ({self.proc.returncode}):\n{self.text()}")
            self._drain(0.05)

    def collect(self, seconds: float) -> None:
        """Read what it prints for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._drain(0.05)

    def text(self) -> str:
        """Everything printed so far."""
        return "\n".join(f"{t:6.2f} {line}" for t, line in self.lines)

    def close(self) -> None:
        """End it (SIGINT first, as a user's Ctrl-C; killed if that is not enough)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(3.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(3.0)
        self._reader.join(2.0)
        while not self._queue.empty():
            self.lines.append(self._queue.get_nowait())


def signed_mav(key: bytes, sysid: int, link_id: int = 0) -> Any:
    """A pymavlink sender as system ``sysid`` (component 190) that signs everything it
    packs with ``key`` on ``link_id``, its timestamp taken from the wall clock now (the
    hostile benchmark's signer, :func:`benchmarks.fuzz_hostile.signed`)."""
    return signed(sysid, key, link_id)
