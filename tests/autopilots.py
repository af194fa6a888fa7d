"""The real autopilots for tests: ArduPilot Rover SITL and PX4 SITL (SIH), started and read.

Imported by the test modules that run a bridge beside a real autopilot
(``from autopilots import ...``). Both autopilots live in ``../shared/autopilots/``
beside the checkout (CI has them at the same place); a test that cannot find
one FAILS (:func:`autopilot_dir`), it never skips.

* :func:`start_ardupilot` / :func:`start_px4` start one in a scratch directory
  (the test's ``tmp_path``) on an instance nobody else uses: an instance is
  claimed with an ``fcntl`` lock file in the system temporary folder
  (:class:`InstanceClaim`), held until the autopilot is stopped, and only when
  every fixed port of that instance is free -- so pytest-xdist workers and other
  developers' runs on the same machine never collide. The UDP ports the test
  itself listens on are chosen by the kernel (bound to port 0).
* :class:`Observer` is a pymavlink peer on one of the autopilot's links with an
  inbox (the ground station's view: ATTITUDE, STATUSTEXT, COMMAND_ACK); every
  wait is bounded.
* ``stop()`` ends the process (SIGTERM, then SIGKILL), releases the instance and,
  for PX4, removes its ``px4-sock-N`` from the temporary folder.
* :func:`dataflash` reads ArduPilot's log (pymavlink), :func:`ulog` PX4's (pyulog).
* :func:`check_all` runs every check on one autopilot run.

The bridge beside them (a companion daemon feeding its heading) is tests/companion_bridge.py.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import random
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")  # before mavutil picks its dialect module
from pymavlink import mavutil

from benchmarks.procstat import free_port

mavutil.set_dialect("ardupilotmega")
M: Any = mavutil.mavlink

#: ``../shared`` beside the checkout, as on a developer's machine and in CI. ``.ci/run`` tests
#: a scratch copy of the tree elsewhere, so it names the checkout's ``../shared`` in
#: ``COMPASS_BRIDGE_SHARED``.
SHARED = Path(
    os.environ.get("COMPASS_BRIDGE_SHARED")
    or Path(__file__).resolve().parent.parent.parent / "shared"
)
AUTOPILOTS = SHARED / "autopilots"
DEADLINE_S = 30.0  #: the longest any single wait on an autopilot may take
#: How long after a change the scenarios read the bridge's new heading (in force by then).
SETTLE_S = 0.3
_LOCK_DIR = Path(tempfile.gettempdir())
#: ArduPilot's home in the tests (Canberra, the SITL default), yaw in degrees true.
ARDUPILOT_HOME = (-35.363261, 149.165230, 584.0, 120.0)

#: EKF3 takes its yaw from VISION_POSITION_ESTIMATE only (the README's set); the rest is
#: what a Rover on the bench needs to log from boot.
ARDUPILOT_FEED_PARAMS: dict[str, float] = {
    "VISO_TYPE": 1,
    "EK3_SRC1_YAW": 6,
    "EK3_SRC1_POSXY": 3,
    "EK3_SRC1_VELXY": 3,
    "EK3_SRC1_POSZ": 1,
    "COMPASS_ENABLE": 0,
    "COMPASS_USE": 0,
    "COMPASS_USE2": 0,
    "COMPASS_USE3": 0,
    "SERIAL1_PROTOCOL": 2,
    "ARMING_CHECK": 0,
    "LOG_DISARMED": 1,
}
#: PX4 EKF2 takes its yaw from ODOMETRY only (the README's set).
PX4_FEED_PARAMS: dict[str, float] = {
    "EKF2_EV_CTRL": 8,
    "EKF2_MAG_TYPE": 5,
    "SYS_HAS_MAG": 0,
    "EKF2_EV_DELAY": 10,
}


def autopilot_dir(name: str) -> Path:
    """``../shared/autopilots/<name>``; fails the test (never skips) when it is not there."""
    d = AUTOPILOTS / name
    if not d.is_dir():
        pytest.fail(f"the real autopilot {name!r} is missing: expected it in {d}")
    return d


# ------------------------------------------------------------------------------ instances


def _port_free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


class InstanceClaim:
    """One autopilot instance number held for this process with an ``fcntl`` lock.

    The lock file is ``<tmp>/compass-bridge-<kind>-<n>.lock``; the lock goes with the
    file descriptor, so a crashed test run frees its instances by itself.
    """

    def __init__(self, kind: str, n: int, fd: int) -> None:
        self.kind, self.n, self._fd = kind, n, fd

    def release(self) -> None:
        """Give the instance back (idempotent)."""
        if self._fd >= 0:
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = -1


def claim_instance(
    kind: str,
    instances: Sequence[int],
    ports: Callable[[int], Iterable[tuple[int, int]]],
    timeout: float = DEADLINE_S,
) -> InstanceClaim:
    """The first of ``instances`` (tried from a random start) whose lock is ours and whose
    ``ports`` ((port, SOCK_DGRAM|SOCK_STREAM) pairs) are all free; waits (bounded) while
    every one is busy."""
    deadline = time.monotonic() + timeout
    start = random.randrange(len(instances))
    order = list(instances[start:]) + list(instances[:start])
    while True:
        for n in order:
            path = _LOCK_DIR / f"compass-bridge-{kind}-{n}.lock"
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            if all(_port_free(p, k) for p, k in ports(n)):
                return InstanceClaim(kind, n, fd)
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
        if time.monotonic() > deadline:
            pytest.fail(f"no free {kind} instance among {list(instances)} in {timeout} s")
        time.sleep(0.2)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nobody uses right now (the kernel's choice)."""
    return free_port(socket.SOCK_DGRAM)


# ------------------------------------------------------------------------------ the observer


#: An observer's socket receive buffer: several seconds of an autopilot's telemetry.
OBSERVER_RCVBUF = 8 << 20


class Observer:
    """A pymavlink peer on one of an autopilot's links, with an inbox and bounded waits.

    A background thread reads everything into per-type lists with arrival times
    (``time.monotonic()``), so a test can read a message history afterwards
    (:meth:`history`) as well as wait for one message (:meth:`wait`).
    """

    def __init__(self, url: str, sysid: int = 255, compid: int = 190) -> None:
        self.conn = mavutil.mavlink_connection(
            url, source_system=sysid, source_component=compid, dialect="ardupilotmega"
        )
        self.mav = self.conn.mav
        # The autopilot streams its own telemetry at hundreds of messages a second, each
        # parsed in Python by the thread below: while the suite's other processes hold the
        # cores that thread falls behind, and a default receive buffer (~200 datagrams)
        # overflows in a second -- a loss in the test's ground station, not on the route.
        # Room for several seconds (SO_RCVBUFFORCE, 33 on Linux, lets root pass rmem_max).
        sock = self.conn.port if isinstance(self.conn.port, socket.socket) else None
        if sock is not None:
            for opt in (33, socket.SO_RCVBUF):
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, opt, OBSERVER_RCVBUF)
                    break
        self._inode = os.fstat(sock.fileno()).st_ino if sock is not None else None
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._seen: list[tuple[float, Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="observer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                continue
            if m is None or m.get_type() == "BAD_DATA":
                continue
            with self._cond:
                self._seen.append((time.monotonic(), m))
                self._cond.notify_all()

    def socket_drops(self) -> int:
        """Datagrams the kernel dropped at this peer's socket, its receive buffer full
        (``drops`` of its line in /proc/net/udp; 0 for a link that is no UDP socket)."""
        if self._inode is None:
            return 0
        for table in ("/proc/net/udp", "/proc/net/udp6"):
            with contextlib.suppress(OSError):
                for line in Path(table).read_text().splitlines()[1:]:
                    f = line.split()
                    if len(f) >= 13 and f[9] == str(self._inode):
                        return int(f[-1])
        return 0

    def send_heartbeat(self) -> None:
        """Announce ourselves as a ground station (the autopilot then streams to us)."""
        self.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def history(
        self, kind: str, cond: Callable[[Any], bool] | None = None, since: float = -1.0
    ) -> list[tuple[float, Any]]:
        """Every ``kind`` message (matching ``cond``) that arrived at or after ``since``."""
        with self._lock:
            return [
                (t, m)
                for t, m in self._seen
                if t >= since and m.get_type() == kind and (cond is None or cond(m))
            ]

    def wait(
        self,
        kind: str | tuple[str, ...],
        cond: Callable[[Any], bool] | None = None,
        timeout: float = DEADLINE_S,
        since: float = -1.0,
        poke: Callable[[], None] | None = None,
    ) -> Any:
        """The first ``kind`` message (matching ``cond``) that arrived at or after ``since``;
        fails the test after ``timeout``. ``poke`` is called about once a second meanwhile
        (re-send a request the autopilot may not have heard)."""
        kinds = (kind,) if isinstance(kind, str) else kind
        deadline = time.monotonic() + timeout
        next_poke = time.monotonic() + 1.0
        checked = 0
        with self._cond:
            while True:
                for i in range(checked, len(self._seen)):
                    t, m = self._seen[i]
                    if t >= since and m.get_type() in kinds and (cond is None or cond(m)):
                        return m
                checked = len(self._seen)
                now = time.monotonic()
                if now > deadline:
                    pytest.fail(f"no {kinds} from the autopilot within {timeout} s")
                if poke is not None and now >= next_poke:
                    next_poke = now + 1.0
                    self._cond.release()
                    try:
                        poke()
                    finally:
                        self._cond.acquire()
                self._cond.wait(0.1)

    def until_quiet(
        self,
        kind: str,
        cond: Callable[[Any], bool],
        since: float,
        quiet_s: float,
        done: Callable[[list[Any]], bool],
        limit_s: float = DEADLINE_S,
    ) -> list[tuple[float, Any]]:
        """The ``kind`` messages (matching ``cond``) that arrived from ``since`` on, once
        ``done`` holds for them or none has come for ``quiet_s`` (a client's time-out:
        what it then has is all it will get), and after ``limit_s`` at most."""
        end = time.monotonic() + limit_s
        got: list[tuple[float, Any]] = []
        checked = 0
        with self._cond:
            while True:
                for t, m in self._seen[checked:]:
                    if t >= since and m.get_type() == kind and cond(m):
                        got.append((t, m))
                checked = len(self._seen)
                now = time.monotonic()
                last = got[-1][0] if got else since
                if done([m for _, m in got]) or now - last >= quiet_s or now >= end:
                    return got
                self._cond.wait(min(0.1, max(0.0, last + quiet_s - now)))

    def command(
        self, target: tuple[int, int], command: int, *params: float, timeout: float = 10.0
    ) -> Any:
        """COMMAND_LONG to ``target``; its COMMAND_ACK (re-sent once a second until answered)."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        since = time.monotonic()

        def send() -> None:
            self.mav.command_long_send(target[0], target[1], command, 0, *p)

        send()
        return self.wait(
            "COMMAND_ACK", lambda m: m.command == command, timeout, since=since, poke=send
        )

    def set_message_interval(self, target: tuple[int, int], msgid: int, hz: float) -> None:
        """Ask the autopilot to stream ``msgid`` to us at ``hz`` (accepted, or the test fails)."""
        ack = self.command(target, M.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, 1e6 / hz)
        assert ack.result == M.MAV_RESULT_ACCEPTED, ack

    def close(self) -> None:
        """Stop reading and close the connection."""
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


# ------------------------------------------------------------------------------ processes


@dataclass
class Autopilot:
    """A running autopilot process (see :func:`start_ardupilot`, :func:`start_px4`)."""

    kind: str
    proc: subprocess.Popen[bytes]
    claim: InstanceClaim
    workdir: Path
    console: Path  #: its stdout and stderr
    system_id: int
    observer: Observer
    #: The UDP port the bridge listens on for the autopilot's companion link
    #: (``udpin:127.0.0.1:<port>``).
    companion_port: int
    #: ArduPilot's SERIAL2 (``gcs2=True``): a second ground station's ``udpin`` port.
    gcs2_port: int = 0
    cleanup: list[Callable[[], None]] = field(default_factory=list)

    @property
    def target(self) -> tuple[int, int]:
        """The autopilot's (system, component)."""
        return (self.system_id, 1)

    def console_text(self) -> str:
        """What the process printed so far."""
        return self.console.read_text(errors="replace") if self.console.exists() else ""

    def alive(self) -> bool:
        """Still running."""
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM (SIGKILL after ``timeout``), then release the instance; idempotent."""
        with contextlib.suppress(Exception):
            self.observer.close()
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    self.proc.kill()
                self.proc.wait(timeout)
        for fn in self.cleanup:
            with contextlib.suppress(Exception):
                fn()
        self.cleanup.clear()
        self.claim.release()

    def logs(self, pattern: str) -> list[Path]:
        """The log files under the work directory matching ``pattern`` (oldest first)."""
        return sorted(self.workdir.glob(pattern), key=lambda p: p.stat().st_mtime)


#: The SITL instance numbers (-I) the tests claim ArduPilot on.
ARDUPILOT_INSTANCES = tuple(range(10, 40))


def ardupilot_ports(n: int) -> list[tuple[int, int]]:
    # SITL's own fixed ports for instance n: simulated RC input (UDP) and the TCP serial
    # ports it would open for SERIAL0..2 were they not redirected (checked all the same).
    base = 10 * n
    return [
        (5501 + base, socket.SOCK_DGRAM),
        (5502 + base, socket.SOCK_DGRAM),
        (5503 + base, socket.SOCK_DGRAM),
        *[(5760 + base + k, socket.SOCK_STREAM) for k in range(3)],
    ]


def start_ardupilot(
    workdir: Path,
    params: Mapping[str, float] | None = None,
    *,
    home: tuple[float, float, float, float] = ARDUPILOT_HOME,
    instances: Sequence[int] = ARDUPILOT_INSTANCES,
    gcs2: bool = False,
) -> Autopilot:
    """ArduPilot Rover SITL in ``workdir`` at real-time speed.

    ``params`` (applied after the stock ``rover.parm``, on a wiped parameter store)
    default to :data:`ARDUPILOT_FEED_PARAMS`. SERIAL0 goes to the returned
    :class:`Observer` (a ground station), SERIAL1 to ``companion_port`` (the
    bridge's ``udpin``), SERIAL2 with ``gcs2`` to ``gcs2_port`` (MAVLink 2).
    Returns once the observer has its first HEARTBEAT.
    """
    home_dir = autopilot_dir("ardupilot")
    workdir.mkdir(parents=True, exist_ok=True)
    values = dict(ARDUPILOT_FEED_PARAMS if params is None else params)
    gcs2_port = free_udp_port() if gcs2 else 0
    if gcs2:
        values["SERIAL2_PROTOCOL"] = 2
    extra = workdir / "extra.parm"
    extra.write_text("".join(f"{k} {v:g}\n" for k, v in values.items()))
    claim = claim_instance("ardupilot", instances, ardupilot_ports)
    gcs_port, companion_port = free_udp_port(), free_udp_port()
    observer = Observer(f"udpin:127.0.0.1:{gcs_port}")
    console = workdir / "ardupilot.console"
    with open(console, "wb") as out:
        proc = subprocess.Popen(
            [
                str(home_dir / "ardurover"),
                "-w",
                "-I",
                str(claim.n),
                "--model",
                "rover",
                "--speedup",
                "1",
                "--defaults",
                f"{home_dir / 'rover.parm'},{extra}",
                "--home",
                ",".join(f"{v:g}" for v in home),
                "--serial0",
                f"udpclient:127.0.0.1:{gcs_port}",
                "--serial1",
                f"udpclient:127.0.0.1:{companion_port}",
                "--serial2",
                f"udpclient:127.0.0.1:{gcs2_port}" if gcs2 else "none",
                *[a for k in (5, 6, 7, 8) for a in (f"--serial{k}", "none")],
            ],
            cwd=workdir,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    ap = Autopilot(
        "ardupilot", proc, claim, workdir, console, 1, observer, companion_port, gcs2_port
    )
    try:
        observer.wait("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        observer.send_heartbeat()
    except BaseException:
        ap.stop()
        raise
    return ap


def _px4_ports(n: int) -> list[tuple[int, int]]:
    # px4-rc.mavlink's local UDP ports for instance n (the GCS, onboard, payload, gimbal
    # and SIH display links) and those it sends to that tests listen on (onboard, gimbal).
    return [(p + n, socket.SOCK_DGRAM) for p in (18570, 14580, 14280, 13030, 19450, 14540, 13280)]


def start_px4(
    workdir: Path,
    params: Mapping[str, float] | None = None,
    *,
    home: tuple[float, float, float] | None = None,
    instances: Sequence[int] = tuple(range(10)),
) -> Autopilot:
    """PX4 SITL (SIH) in ``workdir`` on a free instance.

    ``params`` (default :data:`PX4_FEED_PARAMS`) are given as ``PX4_PARAM_<NAME>``
    environment variables, which PX4's start-up script sets before any module
    starts (``rcS``), so no restart is needed. The :class:`Observer` is a ground
    station on the GCS link (``udpout`` to 18570 + N); the bridge listens on the
    onboard link's remote port 14540 + N (``companion_port``). Returns once the
    observer has PX4's first HEARTBEAT.
    """
    home_dir = autopilot_dir("px4")
    workdir.mkdir(parents=True, exist_ok=True)
    claim = claim_instance("px4", instances, _px4_ports)
    n = claim.n
    env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_")}
    for k, v in dict(PX4_FEED_PARAMS if params is None else params).items():
        env[f"PX4_PARAM_{k}"] = f"{v:g}"
    if home is not None:
        env["PX4_HOME_LAT"], env["PX4_HOME_LON"], env["PX4_HOME_ALT"] = (f"{v}" for v in home)
    console = workdir / "px4.console"
    with open(console, "wb") as out:
        proc = subprocess.Popen(
            [str(home_dir / "px4-sitl"), str(workdir), str(n)],
            cwd=workdir,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    observer = Observer(f"udpout:127.0.0.1:{18570 + n}")
    sock = Path(tempfile.gettempdir()) / f"px4-sock-{n}"
    ap = Autopilot("px4", proc, claim, workdir, console, n + 1, observer, 14540 + n)
    ap.cleanup.append(lambda: sock.unlink(missing_ok=True))
    try:
        observer.wait(
            "HEARTBEAT",
            lambda m: m.get_srcComponent() == 1,
            timeout=DEADLINE_S,
            poke=observer.send_heartbeat,
        )
    except BaseException:
        ap.stop()
        raise
    return ap


# ------------------------------------------------------------------------------ logs


def dataflash(path: Path, types: Sequence[str]) -> dict[str, list[Any]]:
    """ArduPilot's dataflash log: every message of ``types``, by type, in log order."""
    log = mavutil.mavlink_connection(str(path))
    out: dict[str, list[Any]] = {t: [] for t in types}
    try:
        while True:
            m = log.recv_match(type=list(types))
            if m is None:
                break
            out[m.get_type()].append(m)
    finally:
        log.close()
    return out


def ulog(path: Path, topics: Sequence[str]) -> dict[str, dict[str, Any]]:
    """PX4's ulog: for each of ``topics`` (first instance) its fields as numpy arrays."""
    from pyulog import ULog

    u = ULog(str(path), list(topics))
    out: dict[str, dict[str, Any]] = {}
    for d in u.data_list:
        if d.multi_id == 0 and d.name not in out:
            out[d.name] = d.data
    return out


def check_all(subject: Any, checks: Sequence[Callable[[Any], None]]) -> None:
    """Run every check on one autopilot run and fail with all that failed.

    A module's scenario runs once, in one test: pytest-xdist (work stealing) would start
    a module-scoped fixture again on every worker that took one of its tests. Each check
    still reports on its own (its name and its assertion), and they all run.
    """
    failed: list[str] = []
    for check in checks:
        try:
            check(subject)
        except AssertionError as e:
            failed.append(f"{check.__name__}: {e}")
        except pytest.fail.Exception as e:
            failed.append(f"{check.__name__}: {e}")
    if failed:
        pytest.fail("\n\n".join(failed), pytrace=False)
