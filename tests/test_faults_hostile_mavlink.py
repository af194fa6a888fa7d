"""Hostile and careless MAVLink input: truthful acknowledgements, intervals that do
not fit MESSAGE_INTERVAL, the parameter list as an amplifier, and a property test of the
handlers on random messages (the fast suite's share of the fuzzing; `python -m benchmarks
fuzz` drives a running daemon with 10^5 of them)."""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_mavlink_rig import DEADLINE_S, M, Rig, offline_daemon, wait_until

from bridge.app.paramspec import ParamTable
from bridge.mavlink.dispatch import MAX_INTERVAL_US
from bridge.mavlink.endpoints import Link
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings
from bridge.mavlink.paramproto import ListLimiter

REAL32 = M.MAV_PARAM_TYPE_REAL32
ACCEPTED, DENIED, FAILED = M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_DENIED, M.MAV_RESULT_FAILED


# ------------------------------------------------------------------ acknowledgements tell the truth


@pytest.mark.integration
def test_preflight_storage_write_answers_failed_when_nothing_could_be_saved(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    (tmp_path / "blocked").write_text("a file where the state directory should be\n")
    rig = rigs(tmp_path, state="blocked/state")
    g = rig.gcs("udp")
    g.set_param("BRG_SR_HUD", 2.0, REAL32)
    assert g.wait("STATUSTEXT", lambda m: "Parameters NOT saved" in m.text)
    # parameters, calibration file and flash: the first two cannot be written
    assert g.command(M.MAV_CMD_PREFLIGHT_STORAGE, 1, final=True).result == FAILED
    # reset, not saved (its write paced: IN_PROGRESS, then FAILED when the write fails)
    assert g.command(M.MAV_CMD_PREFLIGHT_STORAGE, 2, final=True).result == FAILED
    assert g.command(M.MAV_CMD_PREFLIGHT_STORAGE, 3).result == FAILED  # identity, not saved


@pytest.mark.integration
def test_preflight_storage_write_answers_accepted_when_everything_was_saved(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path)
    g = rig.gcs("udp")
    ack = g.command(M.MAV_CMD_PREFLIGHT_STORAGE, 1)
    if ack.result == M.MAV_RESULT_IN_PROGRESS:  # the compass flash write follows as an event
        ack = g.wait("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_PREFLIGHT_STORAGE)
    assert ack.result == ACCEPTED
    assert (tmp_path / "state" / "params.json").exists()
    assert (tmp_path / "state" / "calibration.json").exists()


# ------------------------------------------------------------------ MESSAGE_INTERVAL fits its field


@pytest.mark.integration
def test_intervals_that_do_not_fit_an_int32_are_refused_or_clamped(
    tmp_path: Path, rigs: Callable[..., Rig], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    rig = rigs(tmp_path)
    g = rig.gcs("udp")
    att, hud = M.MAVLINK_MSG_ID_ATTITUDE, M.MAVLINK_MSG_ID_VFR_HUD
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 3.6e9).result == DENIED
    assert g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, att).result == ACCEPTED
    assert g.wait("MESSAGE_INTERVAL").interval_us == 100_000  # unchanged
    # a legal but tiny rate: its interval does not fit MESSAGE_INTERVAL's int32
    assert g.set_param("BRG_SR_HUD", 0.0001, REAL32).param_value == pytest.approx(0.0001)
    assert g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, hud).result == ACCEPTED
    assert g.wait("MESSAGE_INTERVAL").interval_us == MAX_INTERVAL_US
    assert not [r for r in caplog.records if r.exc_info]  # no traceback anywhere


# ------------------------------------------------------------------ the parameter list amplifier


@pytest.mark.integration
def test_a_peer_gets_one_whole_list_per_interval(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path)
    now = [1000.0]
    rig.out.params.lists = ListLimiter(2.0, 8, clock=lambda: now[0])
    g = rig.gcs("udp")
    n = len(rig.daemon.bridge.params)
    g.flush()
    g.mav.param_request_list_send(1, 1)
    got = {g.wait("PARAM_VALUE").param_index for _ in range(n)}
    assert got == set(range(n))
    g.mav.param_request_list_send(1, 1)  # again at once: dropped and counted
    g.nothing("PARAM_VALUE", None, 0.5)
    assert wait_until(lambda: rig.out.counters.param_lists_refused == 1, DEADLINE_S)
    now[0] += 2.0  # the interval passed
    g.mav.param_request_list_send(1, 1)
    assert {g.wait("PARAM_VALUE").param_index for _ in range(n)} == set(range(n))


def test_many_peers_together_get_a_bounded_number_of_lists() -> None:
    now = [0.0]
    lim = ListLimiter(2.0, 8, clock=lambda: now[0])
    granted = sum(lim.allow(("10.0.0.1", port)) for port in range(1000))  # spoofed sources
    assert granted == 8 and lim.refused == 992
    now[0] += 2.0
    assert lim.allow(("10.0.0.1", 1)) and not lim.allow(("10.0.0.1", 1))


# ------------------------------------------------------------------ handlers on random messages


class _Link(Link):
    """A link that keeps what it is given (the handlers' answers): a peer without an
    endpoint (nothing here frames, queues or writes)."""

    def __init__(self) -> None:
        self.name = "kept"
        self.sent: list[Any] = []

    def send(self, packet: Any) -> None:
        self.sent.append(packet)

    def send_many(self, packets: Sequence[Any]) -> None:
        self.sent.extend(packets)


@pytest.fixture(scope="module")
def offline_output(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MavlinkOutput]:
    """An output on a daemon that is never started (its services; no endpoints, no threads)."""
    tmp = tmp_path_factory.mktemp("hostile")
    cfg, daemon = offline_daemon(tmp, "hostile")
    out = MavlinkOutput(MavlinkSettings.from_config(cfg), daemon.bridge.services)
    yield out
    daemon.bridge.stop(1.0)


_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, 1.0, -1.0, 2.0, 255.0, 256.0, 2.0**31, -(2.0**31), math.nan]),
)
_HANDLED = [
    M.MAV_CMD_DO_START_MAG_CAL,
    M.MAV_CMD_DO_ACCEPT_MAG_CAL,
    M.MAV_CMD_DO_CANCEL_MAG_CAL,
    M.MAV_CMD_FIXED_MAG_CAL_YAW,
    M.MAV_CMD_PREFLIGHT_CALIBRATION,
    M.MAV_CMD_PREFLIGHT_STORAGE,
    M.MAV_CMD_SET_MESSAGE_INTERVAL,
    M.MAV_CMD_GET_MESSAGE_INTERVAL,
    M.MAV_CMD_REQUEST_MESSAGE,
    M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
]
_NAMES = [s.name for s in ParamTable().specs]
_ENC = M.MAVLink(None, 255, 190)


def _decoded(msg: Any) -> Any:
    """The message as it arrives (packed and parsed: the handlers see received messages)."""
    (out,) = M.MAVLink(None).parse_buffer(msg.pack(_ENC))
    return out


@st.composite
def _messages(draw: st.DrawFn) -> Any:
    kind = draw(st.sampled_from(["command", "param_set", "param_read", "list", "ftp", "position"]))
    target = draw(st.sampled_from([(1, 1), (0, 0), (1, 0), (2, 1), (1, 200)]))
    if kind == "command":
        cmd = draw(st.one_of(st.sampled_from(_HANDLED), st.integers(0, 65535)))
        params = [draw(_floats) for _ in range(7)]
        return M.MAVLink_command_long_message(*target, cmd, 0, *params)
    if kind == "param_set":
        name = draw(st.one_of(st.sampled_from(_NAMES), st.text("ABCZ_019", max_size=16)))
        ptype = draw(st.integers(0, 12))
        return M.MAVLink_param_set_message(*target, name.encode(), draw(_floats), ptype)
    if kind == "param_read":
        name = draw(st.one_of(st.sampled_from(_NAMES), st.text("ABCZ_", max_size=16)))
        return M.MAVLink_param_request_read_message(
            *target, name.encode(), draw(st.integers(-32768, 32767))
        )
    if kind == "list":
        return M.MAVLink_param_request_list_message(*target)
    if kind == "ftp":
        payload = draw(st.binary(min_size=0, max_size=251))
        return M.MAVLink_file_transfer_protocol_message(
            0, *target, list(payload + bytes(251 - len(payload)))
        )
    lat, lon = draw(st.integers(-(2**31), 2**31 - 1)), draw(st.integers(-(2**31), 2**31 - 1))
    return M.MAVLink_global_position_int_message(0, lat, lon, 0, 0, 0, 0, 0, 0)


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(msg=_messages())
@pytest.mark.integration
def test_random_messages_never_escape_the_handlers(offline_output: MavlinkOutput, msg: Any) -> None:
    out = offline_output
    link = _Link()
    out._handle(_decoded(msg), link)  # raises nothing, whatever the message
    for answer in link.sent:  # every answer is a well-formed message
        _decoded(answer)
    # the parameters stay valid by their own rules
    params = out.services.params
    for spec in params.specs:
        v = params.get(spec.name)
        assert math.isfinite(v)
        if spec.ptype != REAL32 and not spec.read_only:
            assert v == int(v)
    cal = out.services.settings.calibration
    assert all(math.isfinite(x) for x in cal.mag.offset)
    out.services.calibrator.cancel()  # the next example starts from no session


def test_a_bytewise_integer_nan_pattern_is_a_number_not_a_crash() -> None:
    """A bytewise INT32 whose bit pattern is a float NaN still decodes (to a big integer)."""
    from bridge.mavlink.paramproto import ParamEncoding

    nan_bits = struct.unpack("<f", struct.pack("<I", 0x7FC00001))[0]
    v = ParamEncoding("px4").decode(nan_bits, M.MAV_PARAM_TYPE_INT32)
    assert v == float(0x7FC00001) or math.isfinite(v)
