"""The command line as a user (or systemd) runs it: real subprocesses, real signals, real ptys."""

from __future__ import annotations

import importlib.metadata
import itertools
import os
import re
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial
from helpers import cli_env, run_cli

import bridge
from bridge.cli import SHUTDOWN_TIMEOUT_S, main
from bridge.link.record import RecordingReader
from bridge.sim.pty import MOTIONS

HEADING_RE = re.compile(r"^hdg +(\d+\.\d) mag +pitch +(\S+) +roll +(\S+)")
STOP_BOUND_S = SHUTDOWN_TIMEOUT_S  # a clean stop must beat the forced exit


pytestmark = pytest.mark.usefixtures("restore_logging")  # main() runs in-process


def spawn(tmp_path: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "bridge", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=cli_env(tmp_path),
    )


def read_lines(proc: subprocess.Popen[str], want: int, deadline_s: float) -> list[str]:
    """Lines from ``proc``'s stdout until ``want`` heading lines arrived or the deadline passed."""
    assert proc.stdout is not None
    os.set_blocking(proc.stdout.fileno(), False)
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    buf, lines = "", list[str]()
    end = time.monotonic() + deadline_s
    while time.monotonic() < end and sum(bool(HEADING_RE.match(x)) for x in lines) < want:
        if not sel.select(timeout=max(0.0, min(0.2, end - time.monotonic()))):
            if proc.poll() is not None:
                break
            continue
        chunk = proc.stdout.read()
        if not chunk:
            if proc.poll() is not None:
                break
            continue
        buf += chunk
        *done, buf = buf.split("\n")
        lines += done
    sel.close()
    return lines


def stop(proc: subprocess.Popen[str], sig: signal.Signals) -> tuple[int, float, str]:
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=STOP_BOUND_S + 5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"no exit within {STOP_BOUND_S + 5} s of {sig.name}")
    return proc.returncode, time.monotonic() - t0, err


# --- run --simulate --------------------------------------------------------------------


def simulate_until_a_heading(tmp_path: Path, *args: str) -> str:
    """``run --simulate ARGS`` (its XDG_STATE_HOME is ``tmp_path / "xdg"``) until it shows
    a heading (20 s at most), then SIGTERM: it must exit 0; returns its stderr (the log)."""
    proc = spawn(tmp_path, "run", "--simulate", *args)
    try:
        read_lines(proc, want=1, deadline_s=20)
    finally:
        code, _, err = stop(proc, signal.SIGTERM)
    assert code == 0, err
    return err


@pytest.mark.integration
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.integration
def test_run_simulate_shows_changing_heading_and_stops_on_signal(
    tmp_path: Path, sig: signal.Signals
) -> None:
    proc = spawn(tmp_path, "run", "--simulate")
    try:
        lines = read_lines(proc, want=3, deadline_s=20)
    finally:
        code, took, err = stop(proc, sig)
    headings = [float(m.group(1)) for x in lines if (m := HEADING_RE.match(x))]
    assert len(headings) >= 3, (lines, err)
    # stdout is a pipe: one full line per update, no carriage-return redraws
    assert not any("\r" in x for x in lines)
    # the default simulated unit turns at 10 deg/s and a line comes once a second
    assert len(set(headings)) == len(headings), headings
    assert all(0.0 <= h < 360.0 for h in headings)
    # A first run shows a heading that turns as the unit turns: the simulator starts it
    # with its true calibration, so each second adds 10 deg (modulo 360, +- the noise),
    # and the first line says so, how to see the raw unit and how to calibrate it.
    steps = [(b - a) % 360.0 for a, b in itertools.pairwise(headings)]
    assert all(abs(d - 10.0) < 1.5 for d in steps), headings
    assert "calibrated with its true errors" in lines[0]
    assert "--set sim.calibrated=false" in lines[0] and "calibrate it" in lines[0]
    assert code == 0, err
    assert took < STOP_BOUND_S, f"stop took {took:.1f} s"
    assert "Traceback" not in err


@pytest.mark.integration
def test_run_simulate_can_show_the_uncalibrated_unit(tmp_path: Path) -> None:
    proc = spawn(tmp_path, "run", "--simulate", "--set", "sim.calibrated=false")
    try:
        lines = read_lines(proc, want=3, deadline_s=20)
    finally:
        code, _, err = stop(proc, signal.SIGTERM)
    assert code == 0, err
    assert "UNCALIBRATED" in lines[0] and "calibrate it yourself" in lines[0]
    headings = [float(m.group(1)) for x in lines if (m := HEADING_RE.match(x))]
    # the raw unit's hard iron makes its heading run unevenly: not 10 deg every second
    steps = [(b - a) % 360.0 for a, b in itertools.pairwise(headings)]
    assert any(abs(d - 10.0) > 3.0 for d in steps), headings


@pytest.mark.integration
def test_run_simulate_keeps_its_calibration_apart_from_the_service(tmp_path: Path) -> None:
    """--simulate must not load (or later overwrite) a real unit's calibration in the state dir."""
    from bridge.storage import StateStore

    real_state = tmp_path / "state"
    StateStore(real_state).save("calibration", {"not": "for the simulator"})
    err = simulate_until_a_heading(tmp_path, "--log-level", "INFO")
    assert str(tmp_path / "xdg" / "compass-bridge" / "sim") in err
    assert str(real_state) not in err


@pytest.mark.integration
def test_run_with_a_bad_config_exits_2_naming_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[device]\nport = "sim"\nbaud = 1234\n')
    res = run_cli(tmp_path, "run", "--config", str(bad))
    assert res.returncode == 2
    assert res.stderr.strip() == (
        "config error: device.baud: must be one of 4800, 9600, 19200, 38400, 57600, 115200, "
        "230400, got 1234"
    )
    assert res.stdout == ""


@pytest.mark.integration
def test_version() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "bridge", "--version"], capture_output=True, text=True, timeout=30
    )
    assert res.returncode == 0
    assert res.stdout.strip() == f"compass-bridge {bridge.__version__}"
    # The package metadata (pyproject.toml) and the code agree.
    assert importlib.metadata.version("compass-bridge") == bridge.__version__


# --- usage errors, in process (fast) ------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        ([], "required: COMMAND"),
        (["frobnicate"], "invalid choice"),
        (["run"], "run needs --config FILE"),
        (["run", "--simulate", "--log-level", "LOUD"], "invalid choice"),
        (["simulate"], "--link"),
    ],
)
def test_usage_errors_exit_2(
    argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    assert needle in capsys.readouterr().err


def test_missing_config_file_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--config", str(tmp_path / "nope.toml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("config error: ") and "nope.toml: cannot read" in err


def test_config_prints_the_effective_configuration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[device]\nbaud = 9600\n[zenoh]\nkey_prefix = "v/<hostname>"\n')
    assert main(["config", "--config", str(cfg), "--set", "device.rate_hz=20"]) == 0
    out = capsys.readouterr().out
    # each value with its origin (a TOML comment): the file, --set, or the default
    assert re.search(rf"^baud = 9600 +# {re.escape(str(cfg))}$", out, re.M), out
    assert re.search(r"^rate_hz = 20 +# --set$", out, re.M), out
    assert re.search(r"^protocol = \"gmr\" +# default$", out, re.M), out
    assert "<hostname>" not in out and 'key_prefix = "v/' in out
    assert main(["config", "--set", "sim.motion=spin"]) == 2
    assert "config error: sim.motion: must be one of" in capsys.readouterr().err


def test_sim_motions_match_the_simulator() -> None:
    from bridge.config import SIM_MOTIONS

    assert set(SIM_MOTIONS) == set(MOTIONS)


# --- simulate / record wiring -------------------------------------------------------


@pytest.mark.integration
def test_simulate_serves_a_pty_and_record_taps_it(tmp_path: Path) -> None:
    link = tmp_path / "compass"
    sim = spawn(tmp_path, "simulate", "--link", str(link), "--seed", "3", "--motion", "still")
    try:
        end = time.monotonic() + 20
        while not link.exists() and time.monotonic() < end and sim.poll() is None:
            time.sleep(0.05)
        assert link.exists(), "simulator never created its link"
        with serial.Serial(str(link), 115200, timeout=0.2) as port:
            got = b""
            while b"$PGMRA," not in got and time.monotonic() < end:
                got += port.read(256)
        assert b"$PGMRA," in got
        out = tmp_path / "tap.cbrec"
        rec = run_cli(tmp_path, "record", "--port", str(link), "--out", str(out), "--duration", "1")
        assert rec.returncode == 0, rec.stderr
    finally:
        code, took, err = stop(sim, signal.SIGTERM)
    assert code == 0 and took < STOP_BOUND_S, err
    with RecordingReader(out) as reader:
        data = b"".join(c.data for c in reader.chunks())
        assert reader.header.port == str(link) and reader.header.baud == 115200
    assert data.count(b"$PGMRA,") >= 5  # 10 Hz for a second, minus the edges


def test_a_subcommand_refuses_options_it_does_not_have(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["run", "--simulate", "--units", "2"]) == 2  # a benchmark's option, not run's
    assert "unrecognized arguments: --units 2" in capsys.readouterr().err


@pytest.mark.integration
def test_simulate_unplugs_on_sigusr1_and_sends_noise_on_sigusr2(tmp_path: Path) -> None:
    from bridge.protocol.gmr import GmrDecoder

    link = tmp_path / "compass"
    sim = spawn(
        tmp_path, "simulate", "--link", str(link), "--unplug-s", "0.5", "--garbage-bytes", "400"
    )
    try:
        end = time.monotonic() + 20
        while not link.exists() and time.monotonic() < end and sim.poll() is None:
            time.sleep(0.05)
        first = os.path.realpath(link)
        # SIGUSR2: line noise arrives on the port, counted by a real decoder, frames keep coming
        with serial.Serial(str(link), 115200, timeout=0.2) as port:
            dec = GmrDecoder("host")
            port.read(200)
            sim.send_signal(signal.SIGUSR2)
            frames = 0
            while time.monotonic() < end and (dec.counters.dropped.total == 0 or frames < 3):
                frames += len(dec.feed(port.read(256)))
            assert dec.counters.dropped.total > 0 and frames >= 3
            # SIGUSR1: the cable is pulled; reading the old pty fails
            sim.send_signal(signal.SIGUSR1)
            with pytest.raises(serial.SerialException):
                while time.monotonic() < end:
                    port.read(256)
        # ... and a new pty appears at the same path
        while time.monotonic() < end and (not link.exists() or os.path.realpath(link) == first):
            time.sleep(0.05)
        assert os.path.realpath(link) != first
        with serial.Serial(str(link), 115200, timeout=0.2) as port:
            got = b""
            while b"$PGMRA," not in got and time.monotonic() < end:
                got += port.read(256)
        assert b"$PGMRA," in got
    finally:
        code, _, err = stop(sim, signal.SIGTERM)
    assert code == 0, err


def test_simulate_takes_a_hard_iron_change() -> None:
    from bridge.cli import build_parser

    p = build_parser()
    args = p.parse_args(["simulate", "--link", "/tmp/x", "--hard-iron-change", "10,-20,30@45"])
    assert args.hard_iron_change == ((0.01, -0.02, 0.03), 45.0)
    assert p.parse_args(["simulate", "--link", "/tmp/x"]).hard_iron_change is None
    for bad in ("10,20@5", "a,b,c@1", "1,2,3@-1"):
        with pytest.raises(SystemExit):
            p.parse_args(["simulate", "--link", "/tmp/x", "--hard-iron-change", bad])


@pytest.mark.integration
def test_run_simulate_honours_a_config_files_storage_dir(tmp_path: Path) -> None:
    """A --config file's [storage] dir is the simulator's state directory (said in the log);
    without one the simulator keeps its own per-user directory."""
    mine = tmp_path / "mine"
    cfg = tmp_path / "sim.toml"
    cfg.write_text(f'[storage]\ndir = "{mine}"\n\n[zenoh]\nenabled = false\n')
    err = simulate_until_a_heading(tmp_path, "--config", str(cfg), "-v")
    assert f"simulated compass: state directory {mine}" in err
    assert str(tmp_path / "xdg") not in err


@pytest.mark.integration
def test_a_southern_latitude_parses_as_a_location(tmp_path: Path) -> None:
    """``--location -35.36,149.16``: a value starting with a minus sign is not an option."""
    from bridge.cli import build_parser

    link = tmp_path / "compass"
    sim = spawn(tmp_path, "simulate", "--link", str(link), "--location", "-35.36,149.16")
    try:
        end = time.monotonic() + 20
        while not link.exists() and time.monotonic() < end and sim.poll() is None:
            time.sleep(0.05)
        assert link.exists(), sim.stderr.read() if sim.stderr and sim.poll() is not None else ""
    finally:
        code, _, err = stop(sim, signal.SIGTERM)
    assert code == 0, err
    # and the parser gets the numbers (the glued form, too)
    from bridge.tools.argtypes import glue_negative_values

    argv = glue_negative_values(["simulate", "--link", "x", "--location", "-35.36,-149.16,5"])
    args = build_parser().parse_args(argv)
    assert args.location == (-35.36, -149.16, 5.0)
    assert glue_negative_values(["run", "--set", "-x"]) == ["run", "--set", "-x"]
