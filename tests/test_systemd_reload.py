"""SIGHUP reload in-process: only the parts whose settings changed restart.

The service runs the real daemon on a simulated compass behind a pty, with the
real outputs (Zenoh on loopback); each reload is requested exactly as the
SIGHUP handler does, and the parts are compared by identity afterwards.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from service_harness import free_port, toml_config, wait_for

from bridge.app.sample import Output
from bridge.config import Config, load_config
from bridge.daemon import Daemon, Service, build_outputs, plan_reload
from bridge.link.serial_link import LinkState
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass
from bridge.zenoh.output import ZenohOutput

DEADLINE_S = 15.0


def _wait(pred: Callable[[], bool], what: str, timeout: float = DEADLINE_S) -> None:
    wait_for(pred, what, timeout)  # this file's own, shorter deadline


class Running:
    def __init__(self, tmp: Path, link: Path) -> None:
        self.cfg_path = tmp / "bridge.toml"
        self.tmp, self.link = tmp, link
        self.zport = free_port()
        self.mport = free_port()  # a udpout's destination: nobody needs to listen there
        self.write()
        cfg = load_config(self.cfg_path, env={})

        def make_outputs(c: Config, daemon: Daemon) -> list[Output]:
            return build_outputs(c, daemon, console=False)

        self.service = Service(
            cfg, make_outputs, reload_config=lambda: load_config(self.cfg_path, env={}), env={}
        )
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.service.run, args=(self.stop,), daemon=True)
        self.thread.start()
        _wait(lambda: self.service.daemon.link.state is LinkState.STREAMING, "streaming")

    def write(
        self, *, rate_hz: int = 10, prefix: str = "test/a", extra: str = "", mavlink_id: int = 1
    ) -> None:
        zenoh = (
            f'[zenoh]\nenabled = true\nlisten = ["tcp/127.0.0.1:{self.zport}"]\n'
            f'key_prefix = "{prefix}"\nmulticast_scouting = false\n\n'
        )
        text = toml_config(
            str(self.link),
            self.tmp / "state",
            rate_hz=rate_hz,
            extra=extra,
            mavlink=[f"udpout:127.0.0.1:{self.mport}"],
        )
        text = text.replace("[mavlink]\n", f"[mavlink]\nsystem_id = {mavlink_id}\n")
        self.cfg_path.write_text(text.replace("[zenoh]\nenabled = false\n\n", zenoh))

    def reload(self) -> None:
        n = self.service.reloads + self.service.reloads_refused
        self.service.reload_requested.set()  # what the SIGHUP handler does
        _wait(lambda: self.service.reloads + self.service.reloads_refused > n, "the reload")

    def names(self) -> list[str]:
        """The outputs' names in the order the pipeline publishes to them."""
        return [o.name for o in self.service.daemon.bridge.pipeline.outputs]

    def output(self, name: str) -> Output:
        (out,) = [o for o in self.service.daemon.bridge.pipeline.outputs if o.name == name]
        return out

    def close(self) -> None:
        self.stop.set()
        self.thread.join(DEADLINE_S)
        assert not self.thread.is_alive()


@pytest.fixture
def running(tmp_path: Path) -> Iterator[Running]:
    with PtyCompass(make_firmware(3), tmp_path / "compass") as _sim:
        r = Running(tmp_path, tmp_path / "compass")
        try:
            yield r
        finally:
            r.close()


@pytest.mark.integration
def test_each_section_restarts_only_its_part(running: Running) -> None:
    svc = running.service
    daemon, link = svc.daemon, svc.daemon.link
    zenoh = running.output("zenoh")
    inner = svc.daemon.transport.inner
    reconnects = link.counters.reconnects

    # [zenoh] changed: that output restarts; the port is not touched.
    running.write(prefix="test/b")
    running.reload()
    assert svc.daemon is daemon and svc.daemon.link is link
    new_zenoh = running.output("zenoh")
    assert new_zenoh is not zenoh and isinstance(new_zenoh, ZenohOutput)
    assert new_zenoh.settings.key_prefix == "test/b"
    assert svc.daemon.transport.inner is inner
    samples = daemon.bridge.pipeline.samples
    _wait(lambda: daemon.bridge.pipeline.samples > samples + 5, "samples after the output swap")
    assert link.counters.reconnects == reconnects
    assert running.names() == ["mavlink", "zenoh", "status"]  # in place, not appended

    # [mavlink] changed: that output restarts, and still publishes first -- its ATTITUDE
    # does not wait for Zenoh's documents.
    mavlink = running.output("mavlink")
    running.write(prefix="test/b", mavlink_id=2)
    running.reload()
    assert running.output("mavlink") is not mavlink and running.output("zenoh") is new_zenoh
    assert running.names() == ["mavlink", "zenoh", "status"]

    # [device] changed: the port reopens with it; the outputs keep running.
    running.write(prefix="test/b", rate_hz=20, mavlink_id=2)
    running.reload()
    assert svc.daemon is daemon and running.output("zenoh") is new_zenoh
    assert link.rate_hz == 20
    # the new port is swapped in by the reader at its next read (asynchronously)
    _wait(lambda: svc.daemon.transport.inner is not inner, "the new transport")
    _wait(lambda: link.counters.reconnects == reconnects + 1, "the reconnect")
    _wait(lambda: link.state is LinkState.STREAMING, "streaming again")

    # [location] changed: a new WMM reference in place, nothing restarts.
    inner = svc.daemon.transport.inner
    running.write(
        prefix="test/b",
        rate_hz=20,
        extra="[location]\nlatitude = 52.0\nlongitude = 4.4\n",
        mavlink_id=2,
    )
    assert daemon.bridge.engine.reference is None
    running.reload()
    ref = daemon.bridge.engine.reference
    assert ref is not None and ref.declination_deg is not None and 0.0 < ref.declination_deg < 5.0
    assert svc.daemon.transport.inner is inner and running.output("zenoh") is new_zenoh

    # An invalid file is refused; the running configuration stays.
    cfg_before = svc.cfg
    running.cfg_path.write_text(running.cfg_path.read_text().replace("rate_hz = 20", "rate_hz = 7"))
    running.reload()
    assert svc.reloads_refused == 1 and svc.cfg is cfg_before
    assert svc.daemon is daemon and running.output("zenoh") is new_zenoh

    # [storage] has no in-place switch: the whole bridge restarts, in-process.
    running.write(prefix="test/b", rate_hz=20, extra="", mavlink_id=2)
    text = running.cfg_path.read_text().replace(
        str(running.tmp / "state"), str(running.tmp / "state2")
    )
    running.cfg_path.write_text(text)
    running.reload()
    assert svc.daemon is not daemon
    _wait(lambda: svc.daemon.link.state is LinkState.STREAMING, "the rebuilt bridge streaming")


def test_plan_names_the_parts() -> None:
    a = load_config(None, ["device.port=sim"], env={})
    assert plan_reload(a, a).unchanged
    b = load_config(None, ["device.port=sim", "mavlink.system_id=7"], env={})
    p = plan_reload(a, b)
    assert p.outputs == ("mavlink",) and not p.reopen_link and not p.rebuild
    c = load_config(None, ["device.port=sim", "device.protocol=nmea"], env={})
    assert plan_reload(a, c).rebuild == ("device",)
    d = load_config(
        None, ["device.port=sim", "location.latitude=1", "location.longitude=2"], env={}
    )
    p = plan_reload(a, d)
    assert p.location and p.reopen_link  # the simulated unit moves with [location]
    e = load_config(None, ["device.port=sim", "calibration.onboard=true"], env={})
    assert plan_reload(a, e).rebuild == ("calibration",)
