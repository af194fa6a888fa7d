"""The wiring: one function builds the running bridge, and a reload changes each part
through a method of the part that owns it.

In memory: the simulated compass's port is built but never opened, no thread runs;
a reload is :meth:`bridge.daemon.runner.Service.reload` on a configuration given
in the test (what SIGHUP does with the file; tests/test_systemd_reload.py runs it
against a live bridge).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from bridge.app.sample import CompassSample, Output
from bridge.app.settings import SettingsChange
from bridge.calibration.sessions.state import Result
from bridge.config import Config, config_from_mapping
from bridge.daemon import Daemon, Service, build_daemon, make_simulator
from bridge.daemon.wiring import make_transport
from bridge.link.transport import SimTransport
from bridge.mavlink import MavlinkSettings

SIM_CALIBRATED = "simulator (the unit's true errors)"


def config(state: Path, **sections: Mapping[str, Any]) -> Config:
    raw: dict[str, Any] = {
        "device": {"port": "sim", "rate_hz": 10},
        "storage": {"dir": str(state)},
        **sections,
    }
    return config_from_mapping(raw, env={}, hostname="t")


class Stub:
    """An output that only records its life (a stand-in for the MAVLink adapter)."""

    def __init__(self, name: str, built_for: Config) -> None:
        self.name = name
        self.built_for = built_for
        self.started = self.closed = False
        self.due_at = -math.inf  # as an output sending every sample

    def start(self) -> None:
        self.started = True

    def publish(self, sample: CompassSample) -> None:
        """Nothing to send."""

    def close(self, timeout: float) -> None:
        self.closed = True


class Calls:
    """Records the calls of one bound method and lets them through."""

    def __init__(self, owner: object, name: str, monkeypatch: pytest.MonkeyPatch) -> None:
        self.args: list[tuple[Any, ...]] = []
        real: Callable[..., Any] = getattr(owner, name)

        def spy(*args: Any) -> Any:
            self.args.append(args)
            return real(*args)

        monkeypatch.setattr(owner, name, spy)


class Reloads:
    """A service on the simulated port, never run: each :meth:`to` is one SIGHUP."""

    def __init__(self, cfg: Config) -> None:
        self.next = cfg

        def make_outputs(c: Config, daemon: Daemon) -> list[Output]:
            return [Stub("mavlink", c)]

        self.service = Service(cfg, make_outputs, reload_config=lambda: self.next, env={})

    def to(self, cfg: Config) -> None:
        self.next = cfg
        assert self.service.reload()


@pytest.fixture
def reloads(tmp_path: Path) -> Iterator[Reloads]:
    r = Reloads(config(tmp_path / "state"))
    yield r
    r.service.daemon.stop(timeout=1.0)


def test_a_location_reload_goes_through_the_engine_settings(
    reloads: Reloads, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = reloads.service.daemon
    set_field = Calls(d.bridge.settings, "set_field", monkeypatch)
    reopen = Calls(d, "reopen", monkeypatch)
    heard: list[SettingsChange] = []
    d.bridge.settings.subscribe(heard.append)
    assert d.bridge.calibrator.field is None

    # [location] on the simulated port: the unit moves there too, so the port reopens
    reloads.to(config(tmp_path / "state", location={"latitude": 52.0, "longitude": 4.4}))

    assert reloads.service.daemon is d  # in place: nothing rebuilt
    [(field, source)] = set_field.args
    assert source == "reload" and field is d.bridge.settings.field
    assert [(c.aspect, c.source) for c in heard] == [("reference", "reload")]
    # the owner's subscribers follow: the calibrator's fits are scaled to the new field
    assert d.bridge.calibrator.field is field
    ref = d.bridge.engine.reference
    assert ref is not None and ref.declination_deg is not None and 0.0 < ref.declination_deg < 5.0
    assert len(reopen.args) == 1


def test_a_device_reload_goes_through_the_daemon_and_the_port(
    reloads: Reloads, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = reloads.service.daemon
    old_unit = d.simulator
    assert old_unit is not None
    reopen = Calls(d, "reopen", monkeypatch)
    replace = Calls(d.transport, "replace", monkeypatch)
    set_field = Calls(d.bridge.settings, "set_field", monkeypatch)

    new = config(
        tmp_path / "state",
        device={"port": "sim", "rate_hz": 20, "stale_after": 1.5},
        sim={"seed": 7},
    )
    reloads.to(new)

    assert reloads.service.daemon is d and reloads.service.cfg is new
    [(device, transport, unit)] = reopen.args
    assert device == new.device
    # the new simulated unit is the one behind the new port, and the daemon's from now on
    assert unit is d.simulator and unit is not old_unit
    [(swapped,)] = replace.args
    assert swapped is transport and isinstance(swapped, SimTransport)
    assert swapped.firmware is unit
    assert d.link.rate_hz == 20 and d.link.stale_after == 1.5
    assert set_field.args == []  # [location] did not change


def test_an_output_reload_restarts_that_output_through_the_pipeline(
    reloads: Reloads, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = reloads.service.daemon
    pipeline = d.bridge.pipeline
    [old, tap] = pipeline.outputs
    assert isinstance(old, Stub)
    set_outputs = Calls(pipeline, "set_outputs", monkeypatch)
    reopen = Calls(d, "reopen", monkeypatch)

    new = config(tmp_path / "state", mavlink={"system_id": 9})
    reloads.to(new)

    [(outputs,)] = set_outputs.args
    assert tuple(pipeline.outputs) == tuple(outputs)
    [fresh, kept] = pipeline.outputs  # the restarted one in its own place, as before the reload
    assert isinstance(fresh, Stub) and fresh.built_for is new and fresh.started
    assert old.closed and kept is tap
    assert reopen.args == []  # the port is not touched


def test_the_built_bridge_follows_the_heading_and_calibration_sections(tmp_path: Path) -> None:
    cfg = config(
        tmp_path / "state",
        heading={"reference": "true", "tilt": "accelerometer"},
        calibration={"learn": "learn"},
        location={"latitude": 47.4, "longitude": 8.5},
        mavlink={"autopilot": "px4"},
    )
    d = build_daemon(cfg)
    try:
        assert d.bridge.engine.heading_reference == "true"
        assert d.bridge.engine.tilt_policy is None  # the accelerometer, frame by frame
        assert d.bridge.drift.mode == "learn" and d.bridge.params.get("BRG_CAL_LEARN") == 2
        assert MavlinkSettings.from_config(cfg).autopilot == "px4"
    finally:
        d.stop(timeout=1.0)
    d = build_daemon(config(tmp_path / "state2"))
    try:
        assert d.bridge.engine.heading_reference == "magnetic"
        assert d.bridge.engine.tilt_policy is d.bridge.tilt  # "auto"
        assert d.bridge.drift.mode == "detect"
    finally:
        d.stop(timeout=1.0)


def test_the_parts_are_wired_to_each_other_not_to_copies(tmp_path: Path) -> None:
    d = build_daemon(config(tmp_path / "state"))
    try:
        b = d.bridge
        svc = b.services
        assert svc.device is d.link and b.device is d.link
        assert svc.settings is b.settings and b.settings.engine is b.engine
        assert (svc.params, svc.calibrator, svc.drift, svc.events) == (
            b.params,
            b.calibrator,
            b.drift,
            b.events,
        )
        assert d.transport.inner is not None and d.link.name == d.transport.name
        # a parameter set through the services reaches the calibration controller
        assert svc.params.set("BRG_CAL_ONBOARD", 1).accepted and b.calibrator.onboard
        assert b.status().port == d.link.name
    finally:
        d.stop(timeout=1.0)


def test_the_calibration_controller_commands_the_compass_the_link_talks_to(
    tmp_path: Path,
) -> None:
    # A heading-only compass sends no raw vectors: the controller, wired to that link,
    # refuses to calibrate it (without the link it would start a host session).
    d = build_daemon(config(tmp_path / "state", device={"port": "sim", "protocol": "nmea"}))
    try:
        out = d.bridge.calibrator.start_mag()
        assert out.result is Result.FAILED and "heading-only" in out.message
    finally:
        d.stop(timeout=1.0)


def test_a_simulated_unit_starts_with_its_true_calibration_when_asked(tmp_path: Path) -> None:
    cfg = config(tmp_path / "state", sim={"calibrated": True, "seed": 4})
    d = build_daemon(cfg)
    try:
        assert d.simulator is not None
        assert d.bridge.engine.calibration == d.simulator.sensor.errors.true_calibration()
        assert d.bridge.calibration_source == SIM_CALIBRATED
        assert "calibrated with its true errors" in d.intro
    finally:
        d.stop(timeout=1.0)
    # the raw unit unless asked; and a caller's own port on "sim" has no unit to ask
    raw = build_daemon(config(tmp_path / "state2", sim={"seed": 4}))
    own = build_daemon(cfg, transport=make_transport(cfg))
    try:
        assert raw.bridge.calibration_source != SIM_CALIBRATED and "UNCALIBRATED" in raw.intro
        assert own.simulator is None and own.intro == ""
        assert own.bridge.calibration_source != SIM_CALIBRATED
        unit = make_simulator(cfg)
        given = build_daemon(cfg, transport=make_transport(cfg, unit), simulator=unit)
        assert given.bridge.calibration_source == SIM_CALIBRATED and given.simulator is unit
        given.stop(timeout=1.0)
    finally:
        raw.stop(timeout=1.0)
        own.stop(timeout=1.0)


def test_a_real_port_has_no_simulator(tmp_path: Path) -> None:
    cfg = config(tmp_path / "state", device={"port": "/dev/ttyUSB-none"})
    assert make_simulator(cfg) is None
    d = build_daemon(cfg)
    try:
        assert d.simulator is None and d.intro == ""
        assert d.link.name == "/dev/ttyUSB-none"
    finally:
        d.stop(timeout=1.0)
