"""Test harness: the daemon as a subprocess under a fake service manager.

* :class:`FakeServiceManager` -- what systemd is to a ``Type=notify`` service:
  a real ``AF_UNIX`` datagram socket (abstract, so nothing is left on disk)
  handed over as ``$NOTIFY_SOCKET``; a thread records every message with the
  monotonic time it arrived.
* :class:`GroundStation` -- a UDP socket the bridge's MAVLink output sends to, decoding
  what arrives (both are :class:`benchmarks.procstat.DatagramReceiver`: a socket and its
  receiving thread, written once for the benchmarks and the tests).
* :class:`DaemonProcess` -- ``python -m bridge run --config FILE`` with
  ``$NOTIFY_SOCKET``, ``$WATCHDOG_USEC`` (and optional test hooks) set, stderr
  to a file; signals, bounded waits, exit code.

Every wait here has a deadline: nothing can hang a test run.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import waiting
from pymavlink.dialects.v20 import ardupilotmega as apm

from benchmarks.procstat import DatagramReceiver, free_port, udp_socket
from bridge.mavlink.dialect import Message as Packet
from bridge.types import ClosedOnExit

DEADLINE_S = 20.0


@dataclass(frozen=True, slots=True)
class Message:
    """One sd_notify datagram: its assignments and when it arrived (monotonic)."""

    t: float
    fields: Mapping[str, str] = field(default_factory=dict)

    def __contains__(self, key: object) -> bool:
        return key in self.fields

    def get(self, key: str, default: str | None = None) -> str | None:
        return self.fields.get(key, default)


class FakeServiceManager(DatagramReceiver):
    """A notify socket and the messages a service sent to it."""

    def __init__(self) -> None:
        self.name = f"compass-bridge-test-{os.getpid()}-{id(self):x}"
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind("\0" + self.name)
        sock.settimeout(0.05)
        super().__init__(sock, "fake-systemd")
        self._lock = threading.Lock()
        self._messages: list[Message] = []
        self.start()

    @property
    def notify_socket(self) -> str:
        """The ``$NOTIFY_SOCKET`` value (abstract: ``@name``)."""
        return "@" + self.name

    def handle(self, data: bytes) -> None:
        now = time.monotonic()
        fields = dict(
            line.split("=", 1) for line in data.decode("utf-8").split("\n") if "=" in line
        )
        with self._lock:
            self._messages.append(Message(now, fields))

    @property
    def messages(self) -> list[Message]:
        with self._lock:
            return list(self._messages)

    def since(self, index: int) -> list[Message]:
        return self.messages[index:]

    def pings_continue(self, proc: DaemonProcess, n: int = 3) -> None:
        """Wait (bounded) for ``n`` more WATCHDOG=1 from now on: ``proc`` is alive."""
        mark = len(self.messages)
        self.wait_for(
            lambda m: sum(x.get("WATCHDOG") == "1" for x in self.since(mark)) >= n,
            after=mark,
            proc=proc,
        )

    def wait_for(
        self,
        pred: Callable[[Message], bool],
        *,
        after: int = 0,
        timeout: float = DEADLINE_S,
        proc: DaemonProcess | None = None,
    ) -> tuple[int, Message]:
        """The first message from index ``after`` on that satisfies ``pred`` (index, message)."""
        end = time.monotonic() + timeout
        while True:
            msgs = self.messages
            for i in range(after, len(msgs)):
                if pred(msgs[i]):
                    return i, msgs[i]
            if proc is not None and proc.exited:
                raise AssertionError(f"daemon exited ({proc.returncode}):\n{proc.log()[-3000:]}")
            if time.monotonic() > end:
                tail = [m.fields for m in msgs[after:]][-10:]
                raise AssertionError(f"no matching sd_notify message in {timeout} s; last: {tail}")
            time.sleep(0.05)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 free right now."""
    return free_port(socket.SOCK_DGRAM)


def status_text(m: Message) -> str:
    """The ``STATUS=`` of a notify message ("" when it has none)."""
    return m.get("STATUS") or ""


def streaming_rate(m: Message) -> float:
    """The frame rate a "streaming ... at N Hz" STATUS reports, -1 for any other."""
    found = re.search(r"streaming .* at ([0-9.]+) Hz", status_text(m))
    return float(found.group(1)) if found else -1.0


def wait_for(pred: Callable[[], bool], what: str, timeout: float = DEADLINE_S) -> None:
    """Poll ``pred`` until true; AssertionError naming ``what`` after ``timeout`` (this
    harness's deadline by default: :func:`waiting.wait_for`)."""
    waiting.wait_for(pred, what, timeout, step=0.05)


def toml_config(
    port: str,
    storage: Path,
    *,
    mavlink: Sequence[str] = (),
    zenoh: bool = False,
    extra: str = "",
    baud: int = 115200,
    rate_hz: int = 10,
) -> str:
    """A configuration for tests (loopback only, zenoh off unless asked)."""
    endpoints = ", ".join(f'"{e}"' for e in mavlink)
    return (
        f'[device]\nport = "{port}"\nbaud = {baud}\nrate_hz = {rate_hz}\nstale_after = 1.0\n\n'
        f"[mavlink]\nendpoints = [{endpoints}]\n\n"
        f"[zenoh]\nenabled = {'true' if zenoh else 'false'}\n\n"
        f'[storage]\ndir = "{storage}"\n\n{extra}'
    )


class DaemonProcess(ClosedOnExit):
    """``compass-bridge run`` in a subprocess, as systemd would start it; a ``with`` block
    kills it on the way out if it still runs (:meth:`close`)."""

    def __init__(
        self,
        config: Path,
        manager: FakeServiceManager | None,
        log_path: Path,
        *,
        watchdog_usec: int | None = 1_000_000,
        hanging_reader: bool = False,
        env: Mapping[str, str] | None = None,
        preexec_fn: Callable[[], None] | None = None,
        args: Sequence[str] = ("-v",),
    ) -> None:
        e = dict(os.environ if env is None else env)
        for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM"):
            e.pop(k, None)
        if manager is not None:
            e["NOTIFY_SOCKET"] = manager.notify_socket
        if watchdog_usec is not None:
            e["WATCHDOG_USEC"] = str(watchdog_usec)
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in wait()/kill()
        # The hung-driver stand-in (tests/hanging_reader.py) is the real CLI with a port
        # that wedges on SIGUSR2; the package itself has no such hook.
        launcher = (
            [str(Path(__file__).with_name("hanging_reader.py"))]
            if hanging_reader
            else ["-m", "bridge"]
        )
        self.proc = subprocess.Popen(
            [sys.executable, *launcher, *args, "run", "--config", str(config)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=self._log,
            env=e,
            preexec_fn=preexec_fn,
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def exited(self) -> bool:
        return self.proc.poll() is not None

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout: float = DEADLINE_S) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            out = self.log()
            if text in out:
                return out
            if self.exited:
                break
            time.sleep(0.05)
        raise AssertionError(f"{text!r} not in the daemon's log:\n{self.log()[-3000:]}")

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is not None:
                self._log.close()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()

    def close(self) -> None:
        """:meth:`kill`: whatever a test did, its daemon does not outlive it."""
        self.kill()

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise


class GroundStation(DatagramReceiver):
    """A UDP listener that decodes what the bridge sends (pymavlink, MAVLink 2)."""

    def __init__(self) -> None:
        super().__init__(udp_socket(0.1))
        self.port = int(self.sock.getsockname()[1])
        self.mav = apm.MAVLink(None)
        self.lock = threading.Lock()
        self.seen: list[tuple[float, str, Packet]] = []
        self.start()

    def handle(self, data: bytes) -> None:
        now = time.monotonic()
        for msg in self.mav.parse_buffer(data) or []:
            with self.lock:
                self.seen.append((now, msg.get_type(), msg))

    def count(self, kind: str, since: float = float("-inf"), until: float = float("inf")) -> int:
        with self.lock:
            return sum(1 for t, k, _ in self.seen if k == kind and since <= t < until)

    def kinds(self) -> set[str]:
        """Every message type received so far."""
        with self.lock:
            return {k for _, k, _ in self.seen}

    def last(self, kind: str) -> Packet | None:
        with self.lock:
            found = [m for _, k, m in self.seen if k == kind]
        return found[-1] if found else None
