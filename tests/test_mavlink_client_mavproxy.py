"""MAVProxy, unmodified, against the daemon on the simulated compass.

MAVProxy runs as a subprocess with its default modules, as a user starts it
(``mavproxy.py --master=udpout:...``), and is driven by typing at its prompt.
It must connect without spurious warnings (a clear health bit for a sensor the
bridge does not have made it say "fence breach"), download the parameters
quickly (its ``param_ftp`` asks for ``@PARAM/param.pck`` first: the bridge's
"file not found" NAK sends it to PARAM_REQUEST_LIST at its next 1 Hz check,
where silence would cost its FTP time-out, about 12 s), set and read back
every parameter (MAVProxy sets REAL32 for a non-PX4 vehicle, bytewise INT32
for a PX4 one), and run ``magcal start`` to SUCCESS and its automatic accept.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from mavlink_clients import MavProxy, new_value, writable
from test_mavlink_calibration import FIELD, lead_in
from test_mavlink_rig import Rig, wait_until

from bridge.app.paramspec import REAL32
from bridge.sim.motion import Tumble

pytestmark = pytest.mark.integration  # real sockets, processes or threads

#: Words MAVProxy uses when it warns; none may appear while it talks to a healthy bridge.
WARNINGS = ("fence", "breach", "fail", "error", "unhealthy", "timed out", "traceback", "bad ")
#: How soon after "Detected vehicle" the parameter list must be complete: MAVProxy checks
#: once a second (FTP first, then the list); an unanswered FTP request would take ~12 s.
DOWNLOAD_S = 4.0


@pytest.fixture
def mavproxy(rigs: Callable[..., Rig]) -> Iterator[Callable[[Rig, Path], MavProxy]]:
    """Starts MAVProxy on a rig's udpin port; every one is ended before the rigs stop."""
    started: list[MavProxy] = []

    def start(rig: Rig, cwd: Path) -> MavProxy:
        mp = MavProxy(f"udpout:127.0.0.1:{rig.udp_port}", cwd)
        started.append(mp)
        return mp

    yield start
    for mp in started:
        mp.close()


def download(mp: MavProxy, rig: Rig) -> None:
    """'Detected vehicle', then the whole parameter list, soon."""
    detected, _ = mp.expect(r"Detected vehicle 1:1 on link 0")
    done, line = mp.expect(r"Received \d+ parameters")
    assert line.endswith(f"Received {len(rig.daemon.bridge.params)} parameters")
    assert done - detected < DOWNLOAD_S, mp.text()


def set_and_read_back_every_parameter(mp: MavProxy, rig: Rig) -> None:
    """``param set`` each writable parameter to a new value, then ``param fetch`` it."""
    store = rig.daemon.bridge.params
    wanted = {s.name: new_value(s, store.get(s.name)) for s in writable()}
    for spec in writable():
        value = wanted[spec.name]
        # as a user types it: an integer as an integer (MAVProxy int()s it for a PX4 INT32)
        text = repr(value) if spec.ptype == REAL32 else str(int(value))
        mp.send(f"param set {spec.name} {text}")
    assert wait_until(lambda: all(store.get(n) == v for n, v in wanted.items())), {
        n: (v, store.get(n)) for n, v in wanted.items() if store.get(n) != v
    }
    for name in wanted:
        mp.send(f"param fetch {name}")
    shown_lines = mp.expect_each({name: rf"^{name} = " for name in wanted})
    for name, value in wanted.items():
        line = shown_lines[name]
        shown = float(line.split(" = ", 1)[1])
        assert shown == pytest.approx(value, rel=1e-6, abs=1e-6), (name, line)


def assert_quiet(mp: MavProxy) -> None:
    noisy = [line for _, line in mp.lines if any(w in line.lower() for w in WARNINGS)]
    assert not noisy, mp.text()


def test_mavproxy_calibrates_and_sets_every_parameter(
    tmp_path: Path, rigs: Callable[..., Rig], mavproxy: Callable[[Rig, Path], MavProxy]
) -> None:
    rig = rigs(
        tmp_path,
        fast=True,
        ideal=True,
        motion=lead_in(Tumble(3, rate_dps=90.0, reference_ned=FIELD.ned_G)),
    )
    mp = mavproxy(rig, tmp_path)
    download(mp, rig)
    before = rig.daemon.bridge.engine.calibration

    # docs/mavlink.md's on-board switch and a float, as a user types them
    mp.send("param set BRG_CAL_ONBOARD 1")
    mp.send("param set BRG_SR_HUD 2.5")
    assert wait_until(lambda: rig.daemon.bridge.params.get("BRG_SR_HUD") == 2.5)
    assert rig.daemon.bridge.params.get("BRG_CAL_ONBOARD") == 1.0
    mp.send("param fetch BRG_CAL_ONBOARD")
    assert mp.expect(r"^BRG_CAL_ONBOARD = ")[1] == "BRG_CAL_ONBOARD = 1.0000000"
    mp.send("param show BRG_SR_HUD")
    assert mp.expect(r"^BRG_SR_HUD\s")[1].split() == ["BRG_SR_HUD", "2.5"]
    mp.send("param set BRG_CAL_ONBOARD 0")  # the host's fit for the magcal below
    assert wait_until(lambda: rig.daemon.bridge.params.get("BRG_CAL_ONBOARD") == 0.0)

    # magcal start (broadcast, autosave 1) -> SUCCESS -> MAVProxy accepts on its own
    mp.send("magcal start")
    assert mp.expect(r"Got COMMAND_ACK: DO_START_MAG_CAL: ")[1].endswith("ACCEPTED")
    _, report = mp.expect(r"Calibration of compass \d+ ", timeout=60.0)
    # MAVProxy's console shows no MAG_CAL_PROGRESS: a STATUSTEXT says every 20 % that it works
    steps = [
        int(m.group(1))
        for _, line in mp.lines
        if (m := re.search(r"AP: Mag calibration (\d+)%: keep turning it", line))
    ]
    assert steps == sorted(set(steps)) and set(steps) <= {20, 40, 60, 80}, mp.text()
    assert len(steps) >= 3 and steps[-1] >= 60, mp.text()
    assert report.startswith("Calibration of compass 0 SUCCESS: fitness ")
    assert mp.expect(r"Got COMMAND_ACK: DO_ACCEPT_MAG_CAL: ")[1].endswith("ACCEPTED")
    assert rig.daemon.bridge.engine.calibration != before
    # accepted: the report is no longer repeated, so MAVProxy does not accept again
    mp.collect(2.5)
    assert sum("Calibration of compass" in line for _, line in mp.lines) == 1, mp.text()

    set_and_read_back_every_parameter(mp, rig)
    assert_quiet(mp)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_mavproxy_sets_every_parameter_of_each_flavour(
    tmp_path: Path,
    rigs: Callable[..., Rig],
    mavproxy: Callable[[Rig, Path], MavProxy],
    flavour: str,
) -> None:
    """PX4: MAVProxy decodes and sets the integers bytewise (INT32); ArduPilot: REAL32."""
    rig = rigs(tmp_path, ideal=True, mavlink={"autopilot": flavour})
    mp = mavproxy(rig, tmp_path)
    download(mp, rig)
    set_and_read_back_every_parameter(mp, rig)
    # an integer parameter reads as the integer, not as the float its bytes would make
    mp.send("param show AHRS_ORIENTATION")
    shown = mp.expect(r"^AHRS_ORIENTATION\s")[1].split()[1]
    assert float(shown) == rig.daemon.bridge.params.get("AHRS_ORIENTATION")
    # write them all (docs/mavlink.md): IN_PROGRESS at once (the compass flash's PAR,SET
    # follows, and the params.json write if the last set was less than a second ago), then
    # ACCEPTED with every value set in the file
    mp.send("long PREFLIGHT_STORAGE 1")
    assert mp.expect(r"Got COMMAND_ACK: PREFLIGHT_STORAGE: ")[1].endswith("IN_PROGRESS")
    assert mp.expect(r"Got COMMAND_ACK: PREFLIGHT_STORAGE: ")[1].endswith("ACCEPTED")
    envelope = json.loads((tmp_path / "state" / "params.json").read_text())
    values = rig.daemon.bridge.params.values()
    stored = envelope["payload"]["set"]
    assert stored and all(stored[n] == values[n] for n in stored), stored
    assert_quiet(mp)
