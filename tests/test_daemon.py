"""The daemon's frame path: link -> calibration -> attitude engine -> outputs.

In memory (tests/harness.py): the link machine plays datasheet sentences from a
device on a manual clock into the application (the real Bridge, pipeline,
engine and storage), no threads. On real pseudo-terminals (``integration``): a
feeder thread plays them into the master side of a pty and the whole daemon
opens the slave through pyserial exactly as it would a USB adapter; and the
replays, the console and the threaded outputs. Expected headings come from the
simulator's physics (ground truth attitude -> ADC counts), not from the engine
under test.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import threading
import time
import tty
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
from harness import LinePlayer, LinkHarness, bridge_on
from helpers import load_calibration
from waiting import wait_until

from bridge.app.bridge import Bridge
from bridge.app.sample import CompassSample, DaemonStatus, LatestSampleWorker
from bridge.config import Config, load_config
from bridge.console import ConsoleOutput
from bridge.core.calibration import Calibration
from bridge.core.geometry import angle_diff_deg, euler_to_dcm
from bridge.core.wmm import earth_field
from bridge.daemon import Daemon, build_daemon, run_daemon
from bridge.link.record import RecordingWriter
from bridge.link.serial_link import LinkCounters, LinkState
from bridge.sim.physics import SensorModel, UnitErrors
from bridge.storage import StateStore

# A field with no east component: magnetic north == true north, so the
# magnetic heading of a level unit is exactly the yaw of its attitude.
FIELD_NED_G = (0.21, 0.0, 0.43)
DEADLINE_S = 10.0


def nmea(body: str) -> bytes:
    """``$body*CS\\r\\n`` with the datasheet's XOR checksum (computed here, not by the codec)."""
    cs = 0
    for b in body.encode("ascii"):
        cs ^= b
    return f"${body}*{cs:02X}\r\n".encode("ascii")


def gmr_lines(
    errors: UnitErrors, yaws_deg: Sequence[float], *, pitch_deg: float = 0.0, roll_deg: float = 0.0
) -> list[bytes]:
    """$PGMRA lines of a unit at the given attitudes (seq from 0); on-board heading = yaw."""
    model = SensorModel(errors, FIELD_NED_G)
    rng = np.random.default_rng(0)
    out = []
    for seq, yaw in enumerate(yaws_deg):
        R = euler_to_dcm(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw))
        s = model.sample(R, rng)
        (mx, my, mz), (ax, ay, az) = s.mag_counts[0], s.acc_counts[0]
        body = (
            f"PGMRA,{seq},{yaw % 360:.1f},{pitch_deg:.1f},{roll_deg:.1f},"
            f"{mx},{my},{mz},{ax},{ay},{az},06"
        )
        out.append(nmea(body))
    return out


class PtyFeeder:
    """Plays lines into a pty master (looping) until stopped; drains what the host writes."""

    def __init__(self, lines: Sequence[bytes], period: float = 0.02) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no line discipline on the way in: bytes arrive as sent
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.lines = list(lines)
        self.period = period
        self.host_bytes = bytearray()
        self._stop = threading.Event()
        self._extra: list[bytes] = []
        self._thread = threading.Thread(target=self._run, daemon=True)

    def inject(self, data: bytes) -> None:
        """Send ``data`` once, between two lines."""
        self._extra.append(data)

    def _run(self) -> None:
        deadline = time.monotonic() + 4 * DEADLINE_S
        i = 0
        while not self._stop.is_set() and time.monotonic() < deadline:
            with contextlib.suppress(BlockingIOError, OSError):
                self.host_bytes += os.read(self.master, 4096)
            data = (self._extra.pop(0) if self._extra else b"") + self.lines[i % len(self.lines)]
            i += 1
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self.master, data)
            self._stop.wait(self.period)

    def __enter__(self) -> PtyFeeder:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        os.close(self.master)
        os.close(self.slave)


class Collect:
    """A real Output that keeps every sample (the test's consumer)."""

    name = "collect"
    due_at = -math.inf  # every sample, as it comes: the compass link never reads in bursts

    def __init__(self) -> None:
        self.samples: list[CompassSample] = []

    def start(self) -> None:
        pass

    def publish(self, sample: CompassSample) -> None:
        self.samples.append(sample)

    def close(self, timeout: float) -> None:
        pass

    def wait_for(self, n: int, deadline_s: float = DEADLINE_S) -> list[CompassSample]:
        end = time.monotonic() + deadline_s
        while len(self.samples) < n and time.monotonic() < end:
            time.sleep(0.02)
        assert len(self.samples) >= n, f"only {len(self.samples)} samples within {deadline_s} s"
        return list(self.samples)


def config(tmp_path: Path, port: str, *overrides: str) -> Config:
    return load_config(
        None,
        [f"device.port={port}", f"storage.dir={tmp_path / 'state'}", *overrides],
        env={},
        hostname="test",
    )


@pytest.fixture
def running() -> Iterator[Callable[[Daemon], Daemon]]:
    started: list[Daemon] = []

    def start(d: Daemon) -> Daemon:
        started.append(d.start())
        return d

    yield start
    for d in started:
        d.stop(timeout=3.0)


def in_memory(
    cfg: Config, lines: Sequence[bytes], period: float = 0.02, **bridge: object
) -> tuple[LinkHarness, LinePlayer, Collect, Bridge]:
    """The application on the harness: ``lines`` played round and round into its link."""
    dev = LinePlayer(list(lines), period)
    protocol = cfg.device.protocol
    h = LinkHarness(
        dev,
        start=False,
        protocol=protocol,
        rate_hz=cfg.device.rate_hz if protocol == "gmr" else None,
        stale_after=cfg.device.stale_after,
    )
    app = bridge_on(h, cfg, **bridge)
    out = Collect()
    app.pipeline.set_outputs([out])
    h.start()
    return h, dev, out, app


def run_samples(h: LinkHarness, out: Collect, n: int) -> list[CompassSample]:
    assert h.run_until(lambda: len(out.samples) >= n, 10.0), f"only {len(out.samples)} samples"
    return list(out.samples)


# --- the GMR path -------------------------------------------------------------------


@pytest.mark.integration
def test_host_heading_follows_the_attitude(
    tmp_path: Path, running: Callable[[Daemon], Daemon]
) -> None:
    yaws = [0.0, 45.0, 90.0, 135.0, 200.0, 300.0]
    with PtyFeeder(gmr_lines(UnitErrors.ideal(), yaws, pitch_deg=10.0, roll_deg=-20.0)) as pty:
        out = Collect()
        d = running(build_daemon(config(tmp_path, pty.path), [out]))
        samples = out.wait_for(2 * len(yaws))
        assert d.link.state is LinkState.STREAMING
    assert d.bridge.calibration_source == "none (identity)"
    for s in samples:
        assert s.source == "host" and s.heading_reference == "magnetic"
        assert s.seq is not None and s.device_heading_deg is not None
        truth = yaws[s.seq]
        assert abs(float(angle_diff_deg(s.heading_deg, truth))) < 0.5, (s.seq, s.heading_deg)
        assert s.pitch_deg == pytest.approx(10.0, abs=0.5)
        assert s.roll_deg == pytest.approx(-20.0, abs=0.5)
        assert s.heading_true_deg is None  # no [location]: no declination
    assert {s.seq for s in samples} == set(range(len(yaws)))


def _hard_iron_unit() -> UnitErrors:
    return UnitErrors(
        hard_iron_G=np.array([0.08, -0.05, 0.03]), acc_offset_g=np.array([0.02, 0, 0])
    )


def _max_error(samples: Sequence[CompassSample], yaws: Sequence[float]) -> float:
    return max(abs(float(angle_diff_deg(s.heading_deg, yaws[s.seq or 0]))) for s in samples)


def test_host_heading_follows_the_attitude_in_memory(tmp_path: Path) -> None:
    yaws = [0.0, 45.0, 90.0, 135.0, 200.0, 300.0]
    lines = gmr_lines(UnitErrors.ideal(), yaws, pitch_deg=10.0, roll_deg=-20.0)
    h, dev, out, app = in_memory(config(tmp_path, "/dev/ttyUSB0"), lines)
    samples = run_samples(h, out, 2 * len(yaws))
    assert h.state is LinkState.STREAMING
    assert app.calibration_source == "none (identity)"
    for s in samples:
        assert s.source == "host" and s.heading_reference == "magnetic"
        assert s.seq is not None and s.device_heading_deg is not None
        assert abs(float(angle_diff_deg(s.heading_deg, yaws[s.seq]))) < 0.5, (s.seq, s.heading_deg)
        assert s.pitch_deg == pytest.approx(10.0, abs=0.5)
        assert s.roll_deg == pytest.approx(-20.0, abs=0.5)
        assert s.heading_true_deg is None  # no [location]: no declination
    assert {s.seq for s in samples} == set(range(len(yaws)))
    # Each sample carries the instant its frame was read, on the link's clock.
    assert [s.t for s in samples[:3]] == pytest.approx([h.clock.t - 0.02 * i for i in (11, 10, 9)])
    # The handshake was written to the device: VER, RATE, PAR,GET.
    assert bytes(dev.host_bytes).startswith(b"$PGMRQ,VER*")


def test_stored_calibration_is_applied(tmp_path: Path) -> None:
    unit = _hard_iron_unit()
    yaws = [10.0, 100.0, 190.0, 280.0]
    lines = gmr_lines(unit, yaws)
    # Without calibration the hard iron bends the heading by tens of degrees ...
    h, _, raw, _ = in_memory(config(tmp_path, "/dev/ttyUSB0"), lines)
    assert _max_error(run_samples(h, raw, 8), yaws) > 10.0
    # ... with the true calibration stored in the state directory it is gone.
    StateStore(tmp_path / "state").save("calibration", unit.true_calibration().to_dict())
    h, _, cal, app = in_memory(config(tmp_path, "/dev/ttyUSB0"), lines)
    assert app.calibration_source == "stored"
    assert _max_error(run_samples(h, cal, 8), yaws) < 0.5


def test_corrupt_calibration_falls_back_to_identity(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    (state / "calibration.json").write_text('{"schema": "compass-bridge/calibration", "payl')
    cal, source = load_calibration(str(state))
    assert cal == Calibration() and source == "none (identity)"
    # A checksummed document whose payload is not a calibration: also identity.
    StateStore(state).save("calibration", {"mag": {"offset": [0, 0]}})
    cal, source = load_calibration(str(state))
    assert cal == Calibration() and source == "none (identity)"
    # A document wrapping the calibration with its report is accepted.
    good = _hard_iron_unit().true_calibration()
    StateStore(state).save("calibration", {"calibration": good.to_dict(), "report": {}})
    assert load_calibration(str(state)) == (good, "stored")


def test_declination_from_location(tmp_path: Path) -> None:
    lat, lon = 47.4, 8.5
    decl = earth_field(lat, lon, 0.0).declination_deg
    cfg = config(tmp_path, "/dev/ttyUSB0", f"location.latitude={lat}", f"location.longitude={lon}")
    h, _, out, _ = in_memory(cfg, gmr_lines(UnitErrors.ideal(), [30.0]))
    s = run_samples(h, out, 3)[-1]
    assert s.declination_deg == pytest.approx(decl, abs=1e-6)
    assert s.heading_true_deg == pytest.approx((s.heading_deg + decl) % 360.0, abs=1e-6)
    assert s.heading_reference == "magnetic"


def test_noise_on_the_line_is_counted_and_dropped(tmp_path: Path) -> None:
    yaws = [0.0, 90.0]
    h, dev, out, app = in_memory(
        config(tmp_path, "/dev/ttyUSB0"), gmr_lines(UnitErrors.ideal(), yaws)
    )
    run_samples(h, out, 2)
    dev.inject(b"\x00\xffgarbage$PGMRA,1,2,3*00\r\n")  # binary junk + a bad checksum
    dev.inject(nmea("PGMRA,5,999.0,0.0,0.0,1,2,3,4,5,6,06"))  # heading out of range
    assert h.run_until(lambda: h.counters.bad_lines_total >= 2, 1.0)
    run_samples(h, out, len(out.samples) + 4)  # and it keeps going
    assert app.pipeline.errors == 0
    assert all(
        abs(float(angle_diff_deg(s.heading_deg, yaws[s.seq or 0]))) < 0.5 for s in out.samples
    )


def test_a_silent_compass_is_lost_and_restored_on_the_bus(tmp_path: Path) -> None:
    """The pipeline hears the link's state changes: lost when the stream stops, restored."""
    h, dev, out, app = in_memory(
        config(tmp_path, "/dev/ttyUSB0"), gmr_lines(UnitErrors.ideal(), [0.0])
    )
    kinds: list[str] = []
    app.events.subscribe(lambda e: kinds.append(e.kind))
    # Whoever follows the state (Zenoh's status) hears every change, evented or not.
    states: list[LinkState] = []
    app.services.link_states.add(states.append)
    run_samples(h, out, 3)
    dev.silent = True  # the compass stops
    assert h.run_until(lambda: h.state is LinkState.STALE, 5.0)
    dev.silent = False
    assert h.run_until(lambda: h.state is LinkState.STREAMING, 5.0)
    assert app.status().state is LinkState.STREAMING
    assert any("lost" in k for k in kinds) and any("restored" in k for k in kinds), kinds
    assert states == [LinkState.STREAMING, LinkState.STALE, LinkState.STREAMING]


def test_an_unplugged_adapter_is_counted_and_the_stream_comes_back(tmp_path: Path) -> None:
    """USB unplugged and back: the status counts the reconnect; samples carry on."""
    h, _, out, app = in_memory(
        config(tmp_path, "/dev/ttyUSB0"), gmr_lines(UnitErrors.ideal(), [0.0, 90.0])
    )
    kinds: list[str] = []
    app.events.subscribe(lambda e: kinds.append(e.kind))
    states: list[LinkState] = []
    app.services.link_states.add(states.append)
    run_samples(h, out, 3)
    h.unplug()
    h.at(2.5, h.replug)
    assert app.status().state is LinkState.ABSENT
    n = len(out.samples)
    h.run_for(2.0)
    assert len(out.samples) == n  # nothing while it is away
    run_samples(h, out, n + 5)
    status = app.status()
    assert status.state is LinkState.STREAMING and status.counters.reconnects == 1
    assert status.counters.open_failures >= 3
    assert any("lost" in k for k in kinds) and any("restored" in k for k in kinds), kinds
    # The link's state followers hear the changes no event is emitted for too (the port
    # opening again): Zenoh's status goes out on them.
    lost = states.index(LinkState.ABSENT)
    assert LinkState.OPENING in states[lost:] and states[-1] is LinkState.STREAMING, states


class Stuck(LatestSampleWorker):
    """An output whose I/O hangs (a dead network peer) until released."""

    def __init__(self) -> None:
        super().__init__("stuck", 0.01)
        self.release = threading.Event()
        self.emitted = 0

    def emit(self, sample: CompassSample | None) -> None:
        self.emitted += 1
        self.release.wait(DEADLINE_S)


@pytest.mark.integration
def test_a_stuck_output_does_not_stall_the_others(
    tmp_path: Path, running: Callable[[Daemon], Daemon]
) -> None:
    with PtyFeeder(gmr_lines(UnitErrors.ideal(), [0.0, 90.0]), period=0.01) as pty:
        stuck, out = Stuck(), Collect()
        running(build_daemon(config(tmp_path, pty.path), [stuck, out]))
        out.wait_for(30)
        assert stuck.emitted == 1  # still inside its first emit
        assert stuck.skipped >= 20  # it only ever holds the latest sample
        stuck.release.set()


class Wedged(Collect):
    """An output that breaks the contract: its publish() blocks (a bug, a wedged lock)."""

    name = "wedged"

    def __init__(self) -> None:
        super().__init__()
        self.entered = threading.Event()
        self.release = threading.Event()

    def publish(self, sample: CompassSample) -> None:
        super().publish(sample)
        if len(self.samples) == 5:
            self.entered.set()
            self.release.wait(DEADLINE_S)


@pytest.mark.integration
def test_pipeline_runs_in_the_reader_and_a_wedged_frame_stops_its_clock(
    tmp_path: Path, running: Callable[[Daemon], Daemon]
) -> None:
    """The per-frame path runs in the link's reader thread (no queue, no second thread), and
    ``pipeline_alive_at`` -- what the service watchdog reads -- stays at the arrival of a frame
    that never comes out, then moves again once it does."""
    with PtyFeeder(gmr_lines(UnitErrors.ideal(), [0.0, 90.0]), period=0.01) as pty:
        out = Wedged()
        d = running(build_daemon(config(tmp_path, pty.path), [out]))
        assert out.entered.wait(DEADLINE_S)
        stuck_at = d.bridge.pipeline.alive_at
        time.sleep(0.3)
        assert d.bridge.pipeline.alive_at == stuck_at  # frozen while the frame is inside
        assert time.monotonic() - stuck_at >= 0.3
        out.release.set()
        out.wait_for(10)
        assert time.monotonic() - d.bridge.pipeline.alive_at < 0.1  # idle between frames: alive now
        assert d.bridge.pipeline.errors == 0


# --- heading-only compasses -----------------------------------------------------------


def test_nmea_heading_is_forwarded_with_declination(tmp_path: Path) -> None:
    lat, lon = -33.9, 151.2  # Sydney: declination about +13 deg
    decl = earth_field(lat, lon, 0.0).declination_deg
    lines = [nmea("HCHDM,123.4,M"), nmea("HEHDT,200.0,T")]
    cfg = config(
        tmp_path,
        "/dev/ttyUSB0",
        "device.protocol=nmea",
        f"location.latitude={lat}",
        f"location.longitude={lon}",
    )
    h, _, out, _ = in_memory(cfg, lines)
    samples = run_samples(h, out, 6)
    assert h.machine.protocol == "nmea"
    hdm = next(s for s in samples if s.heading_magnetic_deg == pytest.approx(123.4))
    assert hdm.source == "device" and hdm.attitude is None
    assert hdm.heading_true_deg == pytest.approx(123.4 + decl, abs=1e-6)
    hdt = next(s for s in samples if s.heading_true_deg == pytest.approx(200.0))
    assert hdt.heading_magnetic_deg == pytest.approx(200.0 - decl, abs=1e-6)
    assert hdt.heading_deg == hdt.heading_magnetic_deg  # magnetic is published when known


def test_hdg_variation_is_used_without_location(tmp_path: Path) -> None:
    cfg = config(tmp_path, "/dev/ttyUSB0", "device.protocol=nmea")
    h, dev, out, _ = in_memory(cfg, [nmea("HCHDG,100.0,,,4.5,W")])
    s = run_samples(h, out, 2)[-1]
    assert s.heading_magnetic_deg == pytest.approx(100.0)
    assert s.heading_true_deg == pytest.approx(95.5)  # west variation is negative
    assert dev.host_bytes == b""  # a heading-only compass gets no commands


def test_os5000_pitch_roll_forwarded(tmp_path: Path) -> None:
    cfg = config(tmp_path, "/dev/ttyUSB0", "device.protocol=os5000")
    h, _, out, _ = in_memory(cfg, [nmea("C271.5P-3.0R12.5T21.0")])
    s = run_samples(h, out, 2)[-1]
    assert (s.heading_deg, s.pitch_deg, s.roll_deg) == (271.5, -3.0, 12.5)
    assert s.heading_true_deg is None


# --- replay and the run loop ------------------------------------------------------------


@pytest.mark.integration
def test_replay_runs_to_the_end_and_exits_zero(tmp_path: Path) -> None:
    rec = tmp_path / "run.cbrec"
    lines = gmr_lines(UnitErrors.ideal(), [float(y) for y in range(0, 360, 30)])
    with RecordingWriter(rec, "/dev/ttyUSB0", 115200, start_wall=0.0) as w:
        for i, line in enumerate(lines):
            w.write(i * 0.01, line)
    cfg = config(tmp_path, f"replay:{rec}")
    stop = threading.Event()
    done: list[int] = []
    t = threading.Thread(target=lambda: done.append(run_daemon(cfg, stop)), daemon=True)
    t.start()
    t.join(DEADLINE_S)
    stop.set()  # only matters if it failed to end by itself
    assert done == [0]


@pytest.mark.integration
@pytest.mark.parametrize("realtime", [True, False])
def test_replay_pace_follows_device_replay_realtime(
    tmp_path: Path, running: Callable[[Daemon], Daemon], realtime: bool
) -> None:
    """A recording spanning 2.4 s: at its pace with replay_realtime, at once without."""
    rec = tmp_path / "run.cbrec"
    lines = gmr_lines(UnitErrors.ideal(), [float(y) for y in range(0, 360, 15)])
    with RecordingWriter(rec, "/dev/ttyUSB0", 115200, start_wall=0.0) as w:
        for i, line in enumerate(lines):
            w.write(i * 0.1, line)
    out = Collect()
    cfg = config(tmp_path, f"replay:{rec}", f"device.replay_realtime={str(realtime).lower()}")
    t0 = time.monotonic()
    running(build_daemon(cfg, [out]))
    samples = out.wait_for(len(lines))
    took = time.monotonic() - t0
    assert len(samples) >= len(lines)
    span = samples[-1].t - samples[0].t
    if realtime:
        assert span >= 2.0, span  # recorded span 2.3 s between first and last frame
    else:
        assert span < 1.0 and took < DEADLINE_S, span


@pytest.mark.integration
def test_a_replay_as_fast_as_it_decodes_is_not_held_for_due_times(
    tmp_path: Path, running: Callable[[Daemon], Daemon]
) -> None:
    # An output that could send only now and then (here: never) lets the link read in
    # bursts, holding the port up to MAX_BURST_S between reads -- which would pace a
    # replay meant to go at once (40 kB: ten reads, two seconds held).
    rec = tmp_path / "run.cbrec"
    lines = gmr_lines(UnitErrors.ideal(), [float(y % 360) for y in range(0, 600 * 7, 7)])
    with RecordingWriter(rec, "/dev/ttyUSB0", 115200, start_wall=0.0) as w:
        for i, line in enumerate(lines):
            w.write(i * 0.01, line)
    out = Collect()
    out.due_at = math.inf  # an output that sends on its own clock
    cfg = config(tmp_path, f"replay:{rec}", "device.replay_realtime=false")
    running(build_daemon(cfg, [out]))
    samples = out.wait_for(len(lines))
    assert samples[-1].t - samples[0].t < 1.0


# --- console line ------------------------------------------------------------------------


def _status(state: LinkState = LinkState.STREAMING) -> DaemonStatus:
    return DaemonStatus("sim", state, LinkCounters(attitude_frames=7), 7, 0, "given")


def _sample(heading: float) -> CompassSample:
    return CompassSample(0.0, "host", heading, "magnetic", heading, None, None, 1.5, -2.0)


@pytest.mark.integration
def test_console_line_pipe_mode() -> None:
    stream = io.StringIO()
    con = ConsoleOutput(_status, stream, tty=False, interval=0.05)
    con.start()
    con.publish(_sample(87.25))
    deadline = time.monotonic() + DEADLINE_S
    while stream.getvalue().count("\n") < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    con.close(2.0)
    lines = stream.getvalue().splitlines()
    assert len(lines) >= 2 and "\r" not in stream.getvalue()
    assert "hdg  87.2 mag" in lines[-1] or "hdg  87.3 mag" in lines[-1]
    assert "pitch   +1.5" in lines[-1] and "roll   -2.0" in lines[-1]
    assert "streaming" in lines[-1]


@pytest.mark.integration
def test_console_line_tty_mode_rewrites_in_place() -> None:
    stream = io.StringIO()
    con = ConsoleOutput(lambda: _status(LinkState.STALE), stream, tty=True, interval=0.02)
    con.start()
    deadline = time.monotonic() + DEADLINE_S
    while stream.getvalue().count("\r") < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    con.close(2.0)
    text = stream.getvalue()
    assert text.count("\r") >= 3 and text.endswith("\n") and text.count("\n") == 1
    assert "waiting for the compass on sim" in text and "stale" in text


class Record(LatestSampleWorker):
    """A publish-driven output that records what it emitted."""

    def __init__(self) -> None:
        super().__init__("record", 0.02)
        self.emitted: list[CompassSample | None] = []

    def emit(self, sample: CompassSample | None) -> None:
        self.emitted.append(sample)


def _wait(cond: Callable[[], bool]) -> None:
    wait_until(cond, DEADLINE_S)  # the test asserts what it needs after


@pytest.mark.integration
def test_publish_driven_output_emits_each_new_sample_once() -> None:
    out = Record()
    out.start()
    first, second = _sample(10.0), _sample(20.0)
    out.publish(first)
    _wait(lambda: len(out.emitted) >= 1)
    time.sleep(0.2)  # ten intervals: a stale sample must not be sent again
    assert out.emitted == [first]
    out.publish(second)
    _wait(lambda: len(out.emitted) >= 2)
    out.close(2.0)
    assert out.emitted == [first, second]
