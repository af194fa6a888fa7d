"""How the daemon wires its Zenoh output: built from ``[zenoh]``, the MAVLink mirror
republishing what the bridge sends, and a reload (SIGHUP) moving the output to its new
settings. A real bridge and real zenoh sessions on 127.0.0.1 (tests/zenoh_rig.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import zenoh
from service_harness import GroundStation
from zenoh_rig import Bridge, Received, contiguous, free_port, peer, wait_until

from bridge.config import load_config
from bridge.daemon import Daemon, build_daemon, build_outputs
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration  # real sockets, processes or threads


# ---------------------------------------------------------------------------
# Wiring: the daemon builds the output from [zenoh]
# ---------------------------------------------------------------------------


def test_the_daemon_builds_the_zenoh_output_from_the_configuration(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "w.tty"
    base = [f"device.port={link}", "device.rate_hz=20", f"storage.dir={tmp_path / 'state'}"]
    off = load_config(
        None, [*base, "zenoh.enabled=false", "mavlink.endpoints=[]"], env={}, hostname="w1"
    )
    assert build_outputs(off, build_daemon(off), console=False) == []
    rx = Received()
    with (
        PtyCompass(make_firmware(3), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        GroundStation() as gcs,
    ):
        cfg = load_config(
            None,
            [
                *base,
                f"zenoh.connect=['tcp/127.0.0.1:{port}']",
                f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
                "zenoh.key_prefix=wired/<hostname>/compass",
                "zenoh.heading_rate_hz=5",
                "zenoh.attitude_rate_hz=0",  # every frame (the default caps it at 10 Hz)
                "zenoh.mavlink_mirror=true",
                f"mavlink.endpoints=['udpout:127.0.0.1:{gcs.port}']",
            ],
            env={},
            hostname="w1",
        )
        _s = s.declare_subscriber("wired/**", rx)
        _m = s.declare_subscriber("mavlink/**", rx)
        daemon = build_daemon(cfg, ())
        daemon.bridge.pipeline.set_outputs(build_outputs(cfg, daemon, console=False))
        assert sorted(o.name for o in daemon.bridge.pipeline.outputs) == ["mavlink", "zenoh"]
        daemon.start()
        try:
            key = "wired/w1/compass"
            wait_until(lambda: rx.count(f"{key}/attitude") >= 20, what="attitudes")
            # The mirror found the MAVLink output the configuration built.
            wait_until(lambda: rx.count("mavlink/1/1/HEARTBEAT") >= 1, what="a mirrored HEARTBEAT")
            # 3 s of the device's frames, counted by its own sequence numbers (not timed: a
            # busy machine delays them, it does not change how many there are)
            a0 = rx.count(f"{key}/attitude")
            wait_until(lambda: rx.count(f"{key}/attitude") >= a0 + 60, what="60 more attitudes")
        finally:
            daemon.stop()
    seqs = [d["seq"] for d in rx.docs(f"{key}/attitude")][a0:]
    assert contiguous(seqs)  # every frame of the 20 Hz device
    first, last = seqs[0], seqs[-1]
    span = last - first + 1
    headings = [d for d in rx.docs(f"{key}/heading") if first <= d["seq"] <= last]
    # capped by zenoh.heading_rate_hz: 5 of the device's 20 frames a second (within 1 Hz)
    assert len(headings) == pytest.approx(span * 5.0 / 20.0, abs=span / 20.0)


# ---------------------------------------------------------------------------
# MAVLink mirror
# ---------------------------------------------------------------------------


def test_mavlink_mirror_republishes_what_the_bridge_sends(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with (
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        GroundStation() as gcs,
    ):
        _s = s.declare_subscriber("mavlink/**", rx)
        with Bridge(
            tmp_path,
            "mm",
            connect=[f"tcp/127.0.0.1:{port}"],
            mavlink_port=gcs.port,
            mavlink_mirror=True,
        ) as b:
            assert b.mavlink is not None
            sysid, compid = b.mavlink.identity.system_id, b.mavlink.identity.component_id
            base = f"mavlink/{sysid}/{compid}"
            wait_until(
                lambda: rx.count(f"{base}/HEARTBEAT") >= 2 and rx.count(f"{base}/ATTITUDE") >= 10,
                what="mirrored HEARTBEAT and ATTITUDE",
            )
        # Every message type the ground station got over UDP was mirrored too.
        mirrored = {k.rsplit("/", 1)[1] for k in rx.samples}
        assert gcs.kinds() <= mirrored, gcs.kinds() - mirrored
        hb = rx.docs(f"{base}/HEARTBEAT")[-1]
        assert str(rx.get(f"{base}/HEARTBEAT")[-1].encoding) == "application/json"
        assert hb["header"]["system_id"] == sysid and hb["header"]["component_id"] == compid
        assert hb["header"]["message_id"] == 0
        assert hb["message"]["type"] == "HEARTBEAT"
        assert hb["message"]["mavtype"] == {"type": "MAV_TYPE_GENERIC"}  # standalone role
        assert hb["message"]["autopilot"] == {"type": "MAV_AUTOPILOT_GENERIC"}
        att = rx.docs(f"{base}/ATTITUDE")[-1]["message"]
        assert att["type"] == "ATTITUDE"
        assert all(isinstance(att[f], float) for f in ("roll", "pitch", "yaw"))
        assert -3.1416 <= att["yaw"] <= 3.1416


# ---------------------------------------------------------------------------
# Reload (SIGHUP): the service swaps outputs; zenoh follows
# ---------------------------------------------------------------------------


def _service(cfg: Any, reload_to: Any) -> Any:
    from bridge.daemon import Service

    def make_outputs(c: Any, d: Daemon) -> list[Any]:
        return build_outputs(c, d, console=False)

    return Service(cfg, make_outputs, reload_config=lambda: reload_to, env={})


def _wired_config(tmp_path: Path, link: Path, *extra: str) -> Any:
    return load_config(
        None,
        [
            f"device.port={link}",
            "device.rate_hz=20",
            f"storage.dir={tmp_path / 'state'}",
            *extra,
        ],
        env={},
        hostname="r1",
    )


def test_after_a_mavlink_reload_the_mirror_follows_the_new_output(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "r.tty"
    rx = Received()
    with (
        PtyCompass(make_firmware(5), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
        GroundStation() as gcs,
    ):
        common = (
            f"zenoh.connect=['tcp/127.0.0.1:{port}']",
            f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
            "zenoh.mavlink_mirror=true",
            f"mavlink.endpoints=['udpout:127.0.0.1:{gcs.port}']",
        )
        cfg1 = _wired_config(tmp_path, link, *common)
        cfg2 = _wired_config(tmp_path, link, *common, "mavlink.system_id=7")
        svc = _service(cfg1, cfg2)
        _m = s.declare_subscriber("mavlink/**", rx)
        svc.daemon.start()
        try:
            zenoh_out = next(o for o in svc.daemon.bridge.pipeline.outputs if o.name == "zenoh")
            wait_until(lambda: rx.count("mavlink/1/1/HEARTBEAT") >= 1, what="system 1")
            assert svc.reload()
            # Only the MAVLink output restarted; the zenoh output re-attached its mirror.
            assert (
                next(o for o in svc.daemon.bridge.pipeline.outputs if o.name == "zenoh")
                is zenoh_out
            )
            wait_until(lambda: rx.count("mavlink/7/1/HEARTBEAT") >= 2, 6.0, "system 7")
        finally:
            svc.daemon.stop()


def test_a_zenoh_reload_moves_the_bridge_to_its_new_prefix(tmp_path: Path) -> None:
    port = free_port()
    link = tmp_path / "r.tty"
    seen: list[tuple[str, bool]] = []
    rx = Received()
    with (
        PtyCompass(make_firmware(6), str(link)),
        peer(listen=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        common = (
            f"zenoh.connect=['tcp/127.0.0.1:{port}']",
            f"zenoh.listen=['tcp/127.0.0.1:{free_port()}']",
            "mavlink.endpoints=[]",
        )
        cfg1 = _wired_config(tmp_path, link, *common, "zenoh.key_prefix=old/<hostname>")
        cfg2 = _wired_config(tmp_path, link, *common, "zenoh.key_prefix=new/<hostname>")
        svc = _service(cfg1, cfg2)

        def on_token(sample: zenoh.Sample) -> None:
            seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        _l = s.liveliness().declare_subscriber("**", on_token, history=True)
        _s = s.declare_subscriber("*/r1/heading", rx)
        svc.daemon.start()
        try:
            wait_until(lambda: rx.count("old/r1/heading") >= 3, what="the old prefix")
            assert svc.reload()
            wait_until(lambda: rx.count("new/r1/heading") >= 3, 6.0, "the new prefix")
            wait_until(lambda: ("old/r1", False) in seen, 5.0, "the old token to vanish")
            assert ("new/r1", True) in seen
        finally:
            svc.daemon.stop()
