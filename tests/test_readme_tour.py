"""The README's tour as a newcomer runs it: a fresh home directory, the commands as written.

* The first screen: README's sample lines are the simulator's real output with its
  default seed (numbers to the display's last digit, ±0.3 for the noise of the
  frame's timing), before (``sim.calibrated=false``) and with a calibration.
* ``--reset``: the one documented command that gives a fresh tour back.
* One terminal (a pty, an interactive bash with job control): the calibration step's
  daemon, started with ``&``, says its first lines and then nothing while the calibrate
  tool draws; ``fg`` shows what waited and the live line.
* After a calibration the heading is within tenths of a degree of the simulated truth
  (the figure the console's ``off`` shows; on the fast rig, the tumble takes 90 s live).
"""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
PROGRAM = str(Path(sys.executable).with_name("compass-bridge"))
LIVE_RE = re.compile(r"^(hdg|waiting for)")
NUMBER = re.compile(r"[+-]?\d+\.\d")


def _tour_section(n: int) -> str:
    start = README.index(f"### {n}. ")
    end = README.find("\n### ", start + 1)
    return README[start:end]


def _blocks(section: str, lang: str | None = None) -> list[str]:
    """The fenced code blocks of ``section`` (of language ``lang`` if given), in order."""
    found = re.findall(r"^```(\w*)\n(.*?)^```", section, re.S | re.M)
    return [body for kind, body in found if lang is None or kind == lang]


def _fresh_env(home: Path) -> dict[str, str]:
    """A new user's environment: an empty home, no XDG_STATE_HOME, no systemd state."""
    env = {k: v for k, v in os.environ.items() if k not in ("XDG_STATE_HOME", "STATE_DIRECTORY")}
    home.mkdir(parents=True, exist_ok=True)
    env["HOME"] = str(home)
    env.pop("JOURNAL_STREAM", None)
    return env


def _run_lines(env: dict[str, str], *args: str, lines: int = 4, timeout: float = 60.0) -> list[str]:
    """``compass-bridge run --simulate ...`` piped: its first stdout lines, then SIGINT."""
    proc = subprocess.Popen(
        [PROGRAM, "run", "--simulate", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )
    out: list[str] = []
    try:
        assert proc.stdout is not None
        end = time.monotonic() + timeout
        while len(out) < lines and time.monotonic() < end:
            if select.select([proc.stdout], [], [], 0.2)[0]:
                line = proc.stdout.readline()
                if not line:
                    break
                out.append(line.rstrip("\n"))
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    return out


def _screen(env: dict[str, str], *args: str, frames: int, timeout: float = 60.0) -> list[str]:
    """``run --simulate ...`` on a terminal (200 columns), as the README's reader sees it:
    every line it drew, the live line's ten redraws a second split apart, until one
    shows more than ``frames`` frames; then Ctrl-C."""
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 200, 0, 0))
    proc = subprocess.Popen(
        [PROGRAM, "run", "--simulate", *args],
        stdout=slave,
        stderr=subprocess.PIPE,
        env=env,
        cwd=REPO,
    )
    os.close(slave)
    text = ""
    try:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            seen = [_frames(x) for x in re.split(r"[\r\n]", text)[:-1] if LIVE_RE.match(x)]
            if seen and max(seen) > frames:
                break
            if select.select([master], [], [], 0.2)[0]:
                try:
                    text += os.read(master, 65536).decode(errors="replace")
                except OSError:
                    break
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        os.close(master)
    assert proc.returncode == 0, err
    return [x.rstrip() for x in re.split(r"[\r\n]+", text) if x.strip()]


def _same_line(readme: str, real: str) -> None:
    """Equal text; numbers within 0.3 (the frame's timing moves the last digit)."""
    assert NUMBER.sub("#", readme) == NUMBER.sub("#", real), f"\nREADME: {readme}\nreal:   {real}"
    for a, b in zip(NUMBER.findall(readme), NUMBER.findall(real), strict=True):
        assert abs(float(a) - float(b)) <= 0.3 + 1e-9, f"\nREADME: {readme}\nreal:   {real}"


def _frames(line: str) -> int:
    m = re.search(r"frames (\d+)", line)
    assert m is not None, line
    return int(m.group(1))


def _off_deg(text: str) -> float:
    """How far off the simulated truth the (first) live line of ``text`` says it is."""
    m = re.search(r"off +([+-]\d+\.\d)", text)
    assert m is not None, text
    return float(m.group(1))


def _match_live(readme_line: str, env: dict[str, str], *args: str) -> list[str]:
    """The real live line of the same frame count as the README's (the sample's moment),
    on a terminal; returns what the run drew. Ten redraws a second sample ten frames a
    second: a frame count the timing skipped is looked for in another run (at most 3)."""
    want = _frames(readme_line)
    for _ in range(3):
        real = _screen(env, *args, frames=want)
        same = [x for x in real if LIVE_RE.match(x) and _frames(x) == want]
        if same:
            _same_line(readme_line, same[0])
            return real
    pytest.fail(f"no line with frames {want} in three runs; the last drew:\n" + "\n".join(real))


@pytest.mark.integration
def test_the_first_screen_is_the_simulators_real_output(tmp_path: Path) -> None:
    section = _tour_section(1)
    command, calibrated, uncalibrated = (b.strip() for b in _blocks(section))
    assert command == ".venv/bin/compass-bridge run --simulate"
    intro, state, live = calibrated.splitlines()
    real = _match_live(live, _fresh_env(tmp_path / "home"))
    assert real[0] == intro
    assert real[1] == state  # "~/.local/state/compass-bridge/sim, holding nothing yet"
    off = _off_deg(live)
    assert abs(off) < 0.5  # calibrated with its true errors

    # before anyone calibrates it: tens of degrees off the truth
    real = _match_live(
        uncalibrated.strip(), _fresh_env(tmp_path / "home2"), "--set", "sim.calibrated=false"
    )
    assert real[0].startswith("Simulated compass (seed 1), UNCALIBRATED")
    off = _off_deg(uncalibrated)
    assert abs(off) > 20.0
    assert "here 50 degrees off" in section and abs(off) == pytest.approx(50, abs=1)


@pytest.mark.integration
def test_reset_gives_the_fresh_tour_back(tmp_path: Path) -> None:
    from bridge.app.calibration.store import CalibrationStore
    from bridge.core.calibration import Calibration
    from bridge.storage import StateStore

    env = _fresh_env(tmp_path / "home")
    state = tmp_path / "home" / ".local" / "state" / "compass-bridge" / "sim"
    # what an earlier tour leaves: a calibration and a parameter a ground station set
    docs = StateStore(state)
    when = 1_750_000_000.0
    CalibrationStore(docs).save(Calibration(), source="mag", accepted_unix=when)
    docs.save("params", {"set": {"BRG_HDG_REF": 1.0}})
    later = _run_lines(env, lines=2)
    assert later[0] == (
        "Simulated compass (seed 1) with the calibration stored in "
        "~/.local/state/compass-bridge/sim."
    )
    stamp = time.strftime("%Y-%m-%d %H:%M", time.localtime(when))
    assert f"holding a calibration (mag, {stamp}) and BRG_HDG_REF = 1." in later[1]
    assert later[1].endswith(". A fresh start: compass-bridge run --simulate --reset")

    fresh = _run_lines(env, "--reset", lines=3)
    assert "holding nothing yet" in fresh[1], fresh
    assert not any(p.name.endswith(".json") for p in state.iterdir())
    first = _blocks(_tour_section(1))[1].splitlines()
    assert fresh[0] == first[0] and fresh[1] == first[1]


@pytest.mark.integration
def test_reset_says_what_it_removed_and_needs_simulate(tmp_path: Path) -> None:
    env = _fresh_env(tmp_path / "home")
    state = tmp_path / "home" / ".local" / "state" / "compass-bridge" / "sim"
    from bridge.storage import StateStore

    StateStore(state).save("params", {"set": {"BRG_SR_ATT": 5.0}})
    StateStore(state).save("params", {"set": {"BRG_SR_ATT": 4.0}})  # and its .prev copy
    (state / "notes.txt").write_text("mine")
    proc = subprocess.Popen(
        [PROGRAM, "run", "--simulate", "--reset"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stderr is not None
    first = proc.stderr.readline()  # the reset's line comes before anything else
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert first == f"reset {state}: params.json, params.json.prev\n", first + err
    assert (state / "notes.txt").read_text() == "mine"  # only the bridge's own documents go
    bad = subprocess.run(
        [PROGRAM, "run", "--reset", "--config", str(REPO / "config" / "compass-bridge.toml")],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
    )
    assert bad.returncode == 2 and "--reset goes with --simulate" in bad.stderr


# --- one terminal -------------------------------------------------------------------------


class Terminal:
    """An interactive bash with job control on a pty, 200 columns wide: what a user types in."""

    def __init__(self, env: dict[str, str], cwd: Path) -> None:
        import fcntl
        import pty
        import struct
        import termios

        env = dict(env, PS1="$ ", TERM="xterm", HISTFILE="/dev/null")
        self.pid, self.fd = pty.fork()
        if self.pid == 0:  # pragma: no cover - the child
            os.chdir(cwd)
            os.execve("/bin/bash", ["bash", "--norc", "--noprofile", "-i"], env)
        fcntl.ioctl(self.fd, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 200, 0, 0))
        self.out = ""

    def type(self, text: str) -> None:
        os.write(self.fd, text.encode())

    def read_until(self, pattern: str, timeout: float = 60.0, start: int = 0) -> int:
        """Read until ``pattern`` appears after ``start``; its index in :attr:`out`."""
        rx = re.compile(pattern)
        end = time.monotonic() + timeout
        while True:
            m = rx.search(self.out, start)
            if m:
                return m.start()
            if time.monotonic() > end:
                pytest.fail(
                    f"{pattern!r} not on the terminal within {timeout} s:\n{self.out[-4000:]}"
                )
            if select.select([self.fd], [], [], 0.1)[0]:
                try:
                    self.out += os.read(self.fd, 65536).decode(errors="replace")
                except OSError:
                    pytest.fail(f"the terminal closed:\n{self.out[-4000:]}")

    def close(self) -> None:
        try:
            os.kill(self.pid, signal.SIGKILL)
            os.waitpid(self.pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
        os.close(self.fd)


@pytest.fixture
def terminal(tmp_path: Path) -> Iterator[Terminal]:
    t = Terminal(_fresh_env(tmp_path / "home"), REPO)
    try:
        yield t
    finally:
        t.type("\x03kill %1 2>/dev/null; exit\n")
        time.sleep(0.5)
        t.close()


@pytest.mark.integration
def test_the_calibration_step_runs_in_one_terminal(terminal: Terminal) -> None:
    (commands,) = [b for b in _blocks(_tour_section(3), "sh")]
    daemon, tool = commands.replace("\\\n    ", "").strip().splitlines()
    assert daemon.endswith(" &") and tool.startswith(".venv/bin/compass-bridge calibrate")
    tool += " --timeout 60"  # the test stops it long before
    t = terminal
    t.read_until(r"\$ ")
    t.type(daemon.replace(".venv/bin/compass-bridge", PROGRAM) + "\n")
    # its first lines: what the simulated unit is, where its state is
    t.read_until(r"State \(calibration, parameters set over MAVLink\): ~/\.local/state/")
    t.type(tool.replace(".venv/bin/compass-bridge", PROGRAM) + "\n")
    looking = t.read_until(r"looking for a bridge \(system 1, component 1\) on udpout:")
    found = t.read_until(r"bridge found on udpout:127\.0\.0\.1:14551", start=looking)
    t.read_until(r"turn the compass slowly", start=found)
    bar = t.read_until(r"calibrating \[", start=found)
    t.read_until(r"calibrating \[#+", timeout=60.0, start=bar)  # progress: it tumbles
    t.read_until(r"sphere coverage: [1-9]\d*/80", start=bar)
    time.sleep(3.0)  # more of the tool's redraws, in which the bridge must say nothing
    t.read_until(r"calibrating \[", start=len(t.out) - 10)
    drawn = t.out[looking:]
    # the daemon's output (live line, log lines) never lands in the tool's display
    assert not re.search(r"(^|\r)hdg |WARNING|INFO|\[streaming", drawn), drawn[-3000:]
    t.type("\x03")  # Ctrl-C goes to the foreground job, the tool: it cancels
    t.read_until(r"\$ ", start=bar)  # the tool ended: the shell's prompt
    t.type("fg\n")
    fg = len(t.out)
    live = t.read_until(
        r"\rhdg +\d+\.\d mag .*\[sim truth +\d+\.\d mag, off +[+-]\d+\.\d\]", start=fg
    )
    assert "[streaming" in t.out[live:] or t.read_until(r"\[streaming", start=live)
    t.type("\x03")  # now the bridge is in the foreground: Ctrl-C stops it
    t.read_until(r"\$ ", start=live)


def test_one_mavproxy_command_line_across_the_docs() -> None:
    texts = [README, *(p.read_text() for p in sorted((REPO / "docs").glob("*.md")))]
    lines = {
        line.strip()
        for text in texts
        for line in text.splitlines()
        if "mavproxy.py --master" in line
    }
    assert lines == {".venv/bin/mavproxy.py --master=udpin:127.0.0.1:14550"}, lines


def test_the_prompt_the_docs_explain_is_mavproxys_for_each_flavour() -> None:
    """MAVProxy's prompt is pymavlink's mode string of the bridge's HEARTBEAT."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    from bridge.mavlink.telemetry import Identity, heartbeat

    doc = (REPO / "docs" / "mavlink.md").read_text()
    prompts = {}
    for flavour in ("generic", "ardupilot", "px4"):
        hb = heartbeat(Identity(1, 1, "standalone", flavour), 4)  # MAV_STATE_ACTIVE
        prompts[flavour] = mavutil.mode_string_v10(hb)
    assert prompts == {
        "generic": "Mode(0x00000000)",
        "ardupilot": "Mode(0x00000000)",
        "px4": "UNKNOWN",
    }
    assert (
        "`Mode(0x00000000)>` with the `generic` and\n`ardupilot` flavours and `UNKNOWN>` with `px4`"
        in doc
    )
    assert "Its prompt reads `Mode(0x00000000)>`" in README
