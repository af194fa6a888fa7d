"""The fleet: ten bridges into one subscriber, and ``compass-bridge monitor``.

The ten bridges run as ten real Daemon objects in this one process, each with
its own simulated compass on its own pty, its own zenoh session and its own TCP
link to the subscriber. One process rather than ten: on a two-core machine ten
interpreters (each importing numpy and the zenoh runtime) would measure the
machine's start-up, not the bridge; every part that matters (serial reading,
pipeline, publisher thread, zenoh session and transport) is still per bridge.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from zenoh_rig import Bridge, Received, contiguous, free_port, peer, wait_until

from bridge.zenoh import schema
from bridge.zenoh.monitor import FleetView, MonitorOptions, document_keys, run_monitor

# ---------------------------------------------------------------------------
# The fleet test
# ---------------------------------------------------------------------------


@pytest.mark.integration
def test_ten_bridges_at_20hz_into_one_subscriber_lose_nothing(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    view = FleetView()

    def on_sample(sample: zenoh.Sample) -> None:
        rx(sample)
        view.update(str(sample.key_expr), sample.payload.to_bytes(), time.monotonic())

    with peer(listen=[f"tcp/127.0.0.1:{port}"]) as sub:
        _s = sub.declare_subscriber("fleet/**", on_sample)
        bridges = [
            Bridge(tmp_path, f"boat{i}", connect=[f"tcp/127.0.0.1:{port}"], rate_hz=20, seed=i)
            for i in range(10)
        ]
        try:
            for b in bridges:
                b.start()
            keys = [b.key("heading") for b in bridges]
            wait_until(lambda: all(rx.count(k) >= 10 for k in keys), 20.0, "all ten bridges")
            # Every bridge goes on delivering its device's frames to the subscriber: 3 s of
            # its 20 Hz more each (that none was skipped, its sequence numbers show below;
            # counted, not timed, so a busy machine cannot fail it).
            counts0 = [rx.count(k) for k in keys]
            wait_until(
                lambda: all(rx.count(k) >= c0 + 60 for k, c0 in zip(keys, counts0, strict=True)),
                30.0,
                "60 more headings from every bridge",
            )
            # The monitor's view of the same traffic: ten bridges, all streaming.
            rows = view.rows(time.monotonic())
            assert [r.bridge for r in rows] == sorted(b.prefix for b in bridges)
            assert all(r.link.startswith("streaming") for r in rows)
        finally:
            for b in bridges:
                b.stop()
        # Nothing lost: every heading a bridge published arrived, none skipped in between.
        for b in bridges:
            key = b.key("heading")
            published = b.output.counters.published["heading"]

            def drained(key: str = key, n: int = published) -> bool:
                return rx.count(key) >= n

            wait_until(drained, 5.0, f"{key} drained")
            seqs = [d["seq"] for d in rx.docs(key)]
            assert len(seqs) == published, f"{b.name}: {len(seqs)} of {published} arrived"
            assert contiguous(seqs), f"{b.name}: a gap in the device sequence"
            assert b.output.counters.put_errors == 0
            assert b.daemon.bridge.status().counters.lost_frames == 0


# ---------------------------------------------------------------------------
# FleetView (pure)
# ---------------------------------------------------------------------------


def _doc(name: str, **fields: object) -> bytes:
    base: dict[str, object] = {"schema": name, "version": schema.VERSIONS[name]}
    return json.dumps(base | fields).encode()


HEADING = {
    "seq": 1,
    "t_monotonic": 1.0,
    "t_unix": 2.0,
    "zenoh_time": None,
    "source": "host",
    "heading_deg": 123.45,
    "heading_reference": "magnetic",
    "heading_magnetic_deg": 123.45,
    "heading_true_deg": None,
    "declination_deg": None,
    "device_heading_deg": None,
    "flags": {"saturated": False, "degraded": False, "disturbed": True, "accelerating": False},
}
STATUS = {
    "t_unix": 2.0,
    "uptime_s": 5.0,
    "link": {"port": "/dev/ttyUSB0", "state": "streaming", "frame_rate_hz": 10.0, "counters": {}},
    "samples": 50,
    "pipeline_errors": 0,
    "calibration": {"state": "idle", "source": "stored", "fitness_mG": 4.25},
    "zenoh": {},
}


def test_fleet_view_rows_from_documents() -> None:
    v = FleetView()
    for i in range(5):  # 5 headings over 1 s
        assert v.update("fleet/a/compass/heading", _doc(schema.HEADING, **HEADING), 10.0 + i / 4)
    assert v.update("fleet/a/compass/status", _doc(schema.STATUS, **STATUS), 11.0)
    (row,) = v.rows(11.5)
    assert row.bridge == "fleet/a/compass"
    assert row.heading == "123.5M"  # one decimal, M = magnetic
    assert row.flags == "DIST"
    assert row.link == "streaming 10Hz"
    assert row.calibration == "stored 4.2mG"
    assert row.age == "0.5s"
    # 4 intervals, seen over the 1.5 s since the first: the rate decays when headings stop.
    assert float(row.rate) == pytest.approx(4.0 / 1.5, abs=0.05)
    assert v.rows(20.0)[0].age.endswith("!")  # stale data is marked
    lines = v.render(11.5)
    assert lines[0].split()[:3] == ["BRIDGE", "HDG", "PITCH"] and "fleet/a/compass" in lines[1]


def test_fleet_view_refuses_bad_documents_and_tracks_liveliness() -> None:
    v = FleetView()
    assert not v.update("fleet/a/compass/heading", b"{not json", 1.0)
    bad = dict(HEADING, heading_deg=400.0)
    assert not v.update("fleet/a/compass/heading", _doc(schema.HEADING, **bad), 1.0)
    assert v.rejected == 2
    # A valid document under the wrong leaf, or a foreign schema, is not shown.
    assert not v.update("fleet/a/compass/attitude", _doc(schema.HEADING, **HEADING), 1.0)
    assert not v.update("fleet/a/other", b'{"schema": "someone/else"}', 1.0)
    assert v.bridges() == []
    v.liveliness("fleet/b/compass", True, 2.0)
    assert v.rows(2.5)[0].age == "0.5s"
    v.liveliness("fleet/b/compass", False, 3.0)
    assert v.rows(3.0)[0].age == "gone"
    assert v.render(3.0)[1].split()[0] == "fleet/b/compass"


def test_fleet_view_flags_a_shared_key_prefix_and_follows_an_exact_one() -> None:
    v = FleetView()
    v.update("fleet/a/compass/heading", _doc(schema.HEADING, **HEADING), 1.0)
    v.instance("fleet/a/compass/@bridge/0000000000001-aaaa", True, 1.0)
    assert "DUP" not in v.rows(1.0)[0].flags
    v.instance("fleet/a/compass/@bridge/0000000000002-bbbb", True, 1.5)
    assert v.rows(1.5)[0].flags.startswith("DUP2")
    v.instance("fleet/a/compass/@bridge/0000000000002-bbbb", False, 2.0)
    assert "DUP" not in v.rows(2.0)[0].flags
    assert v.seen_documents() == 1
    # An exact prefix selects a bridge whose documents are one chunk below it.
    assert document_keys("fleet/boat7/compass") == ("fleet/boat7/compass", "fleet/boat7/compass/*")
    assert document_keys("fleet/**") == ("fleet/**",)


def test_fleet_view_flags_what_storage_refused() -> None:
    """NOSAVE: the calibration in use or the parameters set are not in the state directory
    (refused by storage, retried): they are lost at a restart until saved."""
    v = FleetView()
    for n, st in enumerate(
        (
            dict(STATUS, calibration={"state": "idle", "source": "mag", "save_error": "full"}),
            dict(STATUS, parameters={"save_error": "read-only file system"}),
            dict(STATUS, parameters={"save_error": None}),
        )
    ):
        v.update(f"fleet/{n}/compass/status", _doc(schema.STATUS, **st), 1.0)
    flags = {r.bridge: r.flags for r in v.rows(1.0)}
    assert flags == {
        "fleet/0/compass": "NOSAVE",
        "fleet/1/compass": "NOSAVE",
        "fleet/2/compass": "-",
    }


def test_fleet_view_shows_a_running_calibration() -> None:
    v = FleetView()
    st = dict(STATUS, calibration={"state": "running", "percent": 42.4, "source": "stored"})
    v.update("fleet/a/compass/status", _doc(schema.STATUS, **st), 1.0)
    assert v.rows(1.0)[0].calibration == "running 42%"


# ---------------------------------------------------------------------------
# The monitor command against real bridges
# ---------------------------------------------------------------------------


def monitor(*args: str, timeout: float = 20.0) -> subprocess.CompletedProcess[str]:
    """``compass-bridge monitor ...`` as a user runs it (a real process, bounded)."""
    return subprocess.run(
        [sys.executable, "-m", "bridge", "monitor", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.mark.integration
@pytest.mark.parametrize("host", ["127.0.0.1", "[::1]"])  # IPv4, and a link that is IPv6 only
def test_monitor_once_shows_a_running_bridge(tmp_path: Path, host: str) -> None:
    port = free_port()
    with Bridge(tmp_path, "m1", listen=[f"tcp/{host}:{port}"]) as b:
        wait_until(b.output.connected.is_set, what="the bridge's session")
        proc = monitor("--connect", f"tcp/{host}:{port}", "--once")
    # the bridge runs with no calibration (identity): flagged UNCAL, exit code 3
    assert proc.returncode == 3, proc.stderr
    (row,) = [line for line in proc.stdout.splitlines() if line.startswith(b.prefix)]
    cells = row.split()
    assert "UNCAL" in cells
    assert cells[1].endswith("M") and 0.0 <= float(cells[1][:-1]) < 360.0
    assert "streaming" in cells
    assert float(cells[4]) == pytest.approx(20.0, rel=0.25)  # HZ: headings received


@pytest.mark.integration
def test_monitor_once_without_bridges_exits_1() -> None:
    port = free_port()
    with peer(listen=[f"tcp/127.0.0.1:{port}"]):
        proc = monitor("--connect", f"tcp/127.0.0.1:{port}", "--once", "--duration", "0.5")
    assert proc.returncode == 1
    assert "(no compass bridge seen yet)" in proc.stdout


@pytest.mark.integration
def test_monitor_marks_a_bridge_that_goes_away(tmp_path: Path) -> None:
    port = free_port()
    out = io.StringIO()
    stop = threading.Event()
    opts = MonitorOptions(
        connect=(f"tcp/127.0.0.1:{port}",), interval=0.25, duration=15.0, tty=False
    )
    b = Bridge(tmp_path, "m2", listen=[f"tcp/127.0.0.1:{port}"]).start()
    result: list[int] = []
    th = threading.Thread(target=lambda: result.append(run_monitor(opts, out, stop=stop)))
    th.start()
    try:
        wait_until(lambda: "streaming" in out.getvalue(), what="the bridge in the table")
        b.stop()
        wait_until(lambda: "gone" in out.getvalue().rsplit("compass-bridge monitor", 1)[-1])
    finally:
        b.stop()
        stop.set()
        th.join(5.0)
    assert not th.is_alive() and result == [0]


@pytest.mark.integration
def test_monitor_refuses_bad_arguments() -> None:
    proc = monitor("fleet//x", "--once")
    assert proc.returncode == 2 and "not a key expression" in proc.stderr
    proc = monitor("--connect", "nonsense", "--once")
    assert proc.returncode == 2 and "not a zenoh endpoint" in proc.stderr


@pytest.mark.integration
def test_monitor_on_a_terminal_redraws_in_place() -> None:
    port = free_port()
    out = io.StringIO()
    with peer(listen=[f"tcp/127.0.0.1:{port}"]):
        opts = MonitorOptions(
            connect=(f"tcp/127.0.0.1:{port}",), interval=0.1, duration=0.35, tty=True
        )
        assert run_monitor(opts, out) == 0
    text = out.getvalue()
    frames = text.split("\x1b[H\x1b[2J")  # cursor home + clear screen before every frame
    assert frames[0] == "" and len(frames) >= 3
    assert all("BRIDGE" in f for f in frames[1:])
