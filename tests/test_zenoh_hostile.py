"""Zenoh commands as guarded as MAVLink ones, and one bridge per key prefix.

Real bridges (simulated compass on a pty, the daemon, the Zenoh output) and real zenoh
sessions on 127.0.0.1:

* oversized or malformed arguments (a big payload, a long selector, deep nesting, an
  integer beyond a float, a structure where a number belongs) get a clear
  ``bad arguments``, are not echoed back, and leave the bridge answering;
* ``fixed_yaw`` over Zenoh goes through the same plausibility checks as MAVLink's;
* two bridges with the same key prefix: the one started second publishes nothing and
  answers nothing under it, both say so, commands are refused while they share it,
  and ``monitor`` flags the prefix; once one is gone the other has it alone.
"""

from __future__ import annotations

import io
import json
import logging
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from zenoh_rig import NO_SCOUTING, Bridge, Received, _command, _query, free_port, peer, wait_until

from bridge.tools.status import run_status
from bridge.zenoh import schema
from bridge.zenoh.commands import MAX_ARGUMENT_BYTES, parse_command_args
from bridge.zenoh.monitor import MonitorOptions, run_monitor

pytestmark = pytest.mark.integration


def _raw(session: zenoh.Session, key: str, payload: bytes) -> list[dict[str, Any]]:
    out = []
    for r in session.get(key, payload=payload, timeout=3.0):
        assert r.ok is not None
        out.append(schema.parse(r.ok.payload.to_bytes(), schema.COMMAND_RESULT))
    return out


def test_oversized_and_malformed_arguments_get_bad_arguments(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    port = free_port()
    with (
        Bridge(tmp_path, "h1", listen=[f"tcp/127.0.0.1:{port}"], remote_calibration=True) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        start = b.key("cmd/calibration/start")
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        deep = b'{"what": ' + b"[" * 2000 + b"]" * 2000 + b"}"
        cases: list[tuple[bytes, str]] = [
            (b"x" * 100_000, "payload of 100000 bytes"),
            (json.dumps({"what": "m" * 4000}).encode(), "text of 4000 characters"),
            (deep, "nested too deeply"),
            (b'{"what": "fixed_yaw", "yaw_deg": 1' + b"0" * 400 + b"}", "out of range"),
            (b'{"what": "fixed_yaw", "yaw_deg": 1e999}', "out of range"),
            (b'{"what": {"a": 1}}', "not a structure"),
            (b"[1, 2]", "must be a JSON object"),
            (b"\xff\xfe", "not JSON"),
            (json.dumps({f"k{i}": i for i in range(40)}).encode(), "more than 16 arguments"),
        ]
        for payload, why in cases:
            (answer,) = _raw(s, start, payload)
            assert answer["ok"] is False, (why, answer)
            assert answer["message"].startswith("bad arguments:") and why in answer["message"]
            assert len(json.dumps(answer)) < 2000  # nothing big echoed back
        # A long selector is refused as well, unread.
        (answer,) = [
            schema.parse(r.ok.payload.to_bytes(), schema.COMMAND_RESULT)
            for r in s.get(f"{start}?what={'m' * 5000}", timeout=3.0)
            if r.ok is not None
        ]
        assert answer["ok"] is False and "selector parameters" in answer["message"]
        assert b.output.counters.bad_arguments == len(cases) + 1
        assert not b.daemon.bridge.calibrator.snapshot().running  # nothing started
        # Still answering, and nothing of it went into the log whole or as a traceback.
        (ok,) = _command(s, b.key("cmd/calibration/cancel"))
        assert ok["ok"] is True
    assert not [r for r in caplog.records if r.exc_info]
    assert max(len(r.getMessage()) for r in caplog.records) < 2000


def test_fixed_yaw_over_zenoh_is_checked_before_it_becomes_a_calibration(tmp_path: Path) -> None:
    port = free_port()
    with (
        Bridge(
            tmp_path,
            "h2",
            listen=[f"tcp/127.0.0.1:{port}"],
            motion="still",
            remote_calibration=True,
            config=["location.latitude=47.397", "location.longitude=8.546"],  # Zurich
        ) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        start = b.key("cmd/calibration/start")
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        wait_until(lambda: b.daemon.bridge.pipeline.samples > 30, what="frames to average")
        before = b.daemon.bridge.engine.calibration
        for args, why in [
            ({"what": "fixed_yaw", "yaw_deg": 1e9}, "bad yaw"),
            ({"what": "fixed_yaw", "yaw_deg": 10, "latitude_deg": -89.9, "longitude_deg": 8.5},
             "implausible"),
            ({"what": "fixed_yaw", "yaw_deg": 10, "latitude_deg": 95, "longitude_deg": 8.5},
             "bad position"),
        ]:  # fmt: skip
            (answer,) = _command(s, start, args)
            assert answer["ok"] is False and why in answer["message"], answer
        assert b.daemon.bridge.engine.calibration == before
        assert not (b.state_dir / "calibration.json").exists()


def test_parse_command_args_is_bounded() -> None:
    assert parse_command_args(
        b'{"what": "mag", "retry": true}', "onboard=1", [("onboard", "1")]
    ) == {
        "onboard": 1,
        "what": "mag",
        "retry": True,
    }
    assert parse_command_args(None, "what=level", [("what", "level")]) == {"what": "level"}
    with pytest.raises(ValueError, match="payload of"):
        parse_command_args(b" " * (MAX_ARGUMENT_BYTES + 1), "", ())
    with pytest.raises(ValueError, match="out of range"):
        parse_command_args(b'{"yaw_deg": ' + b"9" * 19 + b"}", "", ())
    with pytest.raises(ValueError, match="not a number"):
        parse_command_args(b'{"yaw_deg": NaN}', "", ())


def test_two_bridges_on_one_key_prefix(tmp_path: Path) -> None:
    port = free_port()
    (tmp_path / "b").mkdir()
    with peer(listen=[f"tcp/127.0.0.1:{port}"], mode="router") as hub:
        events = Received()
        _sub = hub.declare_subscriber("fleet/**", events)
        first = Bridge(
            tmp_path, "twin", connect=[f"tcp/127.0.0.1:{port}"], listen=(),
            remote_calibration=True, seed=1, mode="client",
        ).start()  # fmt: skip
        second: Bridge | None = None
        try:
            wait_until(first.output.connected.is_set, what="the first bridge")
            wait_until(lambda: events.count(first.key("heading")) > 5, what="its headings")
            second = Bridge(
                tmp_path / "b", "twin", connect=[f"tcp/127.0.0.1:{port}"], listen=(),
                remote_calibration=True, seed=2, mode="client",
            )  # fmt: skip
            second.start()
            got: list[Any] = []
            second.daemon.bridge.events.subscribe(got.append)
            firsts: list[Any] = []
            first.daemon.bridge.events.subscribe(firsts.append)
            # Both see each other; the second yields: it never publishes under the prefix.
            wait_until(lambda: first.output._shared_with != [], what="the first to see it")
            wait_until(lambda: second.output._shared_with != [], what="the second to see it")
            assert second.output.counters.published.get("heading", 0) == 0
            assert not second.output.connected.is_set()
            # A command reaches only the first, which refuses it while the prefix is shared.
            (answer,) = _command(hub, first.key("cmd/calibration/start"), {"what": "mag"})
            assert answer["ok"] is False and "shared with another bridge" in answer["message"]
            assert not first.daemon.bridge.calibrator.snapshot().running
            assert not second.daemon.bridge.calibrator.snapshot().running

            # The first's status says so; monitor flags the prefix.
            def dup_in_status() -> bool:
                docs = events.docs(first.key("status"))
                return bool(docs and docs[-1]["zenoh"].get("duplicate_prefix"))

            wait_until(dup_in_status, what="duplicate_prefix in the status")
            out = io.StringIO()
            opts = MonitorOptions(
                keyexpr=first.prefix, connect=(f"tcp/127.0.0.1:{port}",), once=True,
                duration=2.5, tty=False, overrides=NO_SCOUTING,
            )  # fmt: skip
            # Meanwhile the second's publisher sleeps until the claim changes (it spun,
            # waking on its past status period, while it yielded).
            thread = second.output._thread
            assert thread is not None and thread.ident is not None
            cpu = time.pthread_getcpuclockid(thread.ident)
            cpu0, wall0 = time.clock_gettime(cpu), time.monotonic()
            assert run_monitor(opts, out) == 1  # a shared prefix is not OK (docs/zenoh.md)
            spent = time.clock_gettime(cpu) - cpu0
            assert spent < 0.05 * (time.monotonic() - wall0), spent
            (row,) = [ln for ln in out.getvalue().splitlines() if ln.startswith(first.prefix)]
            assert "DUP2" in row, out.getvalue()
            said = io.StringIO()
            assert run_status(opts, said, timeout=3.0) == 1
            assert "key prefix shared with 1 other bridge" in said.getvalue(), said.getvalue()
            # The first bridge goes: the second has the prefix and publishes.
            first.stop()
            wait_until(second.output.connected.is_set, what="the second to take over")
            n = events.count(second.key("heading"))
            wait_until(lambda: events.count(second.key("heading")) > n + 5, what="its headings")
        finally:
            first.stop()
            if second is not None:
                second.stop()
