"""Remote calibration over Zenoh and its access control: off by default, the calibrator
driven by ``cmd/calibration/*``, an untrusted peer denied. A real bridge and real zenoh
sessions with set ids on 127.0.0.1 (tests/zenoh_rig.py); every wait is bounded.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh
from zenoh_rig import (
    TRUSTED_ZID,
    UNTRUSTED_ZID,
    Bridge,
    Received,
    _command,
    _query,
    free_port,
    peer,
    wait_until,
)

pytestmark = pytest.mark.integration  # real sockets, processes or threads


# ---------------------------------------------------------------------------
# Remote calibration and access control
# ---------------------------------------------------------------------------


def test_remote_calibration_is_off_by_default(tmp_path: Path) -> None:
    port = free_port()
    with (
        Bridge(tmp_path, "c1", listen=[f"tcp/127.0.0.1:{port}"]) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        assert _query(s, b.key("cmd/calibration/start"), 1.0) == []
        assert not b.daemon.bridge.calibrator.snapshot().running


def test_remote_calibration_drives_the_calibrator(tmp_path: Path) -> None:
    port = free_port()
    rx = Received()
    with (
        Bridge(
            tmp_path,
            "c2",
            listen=[f"tcp/127.0.0.1:{port}"],
            motion="tumble",
            remote_calibration=True,
        ) as b,
        peer(connect=[f"tcp/127.0.0.1:{port}"]) as s,
    ):
        _e = s.declare_subscriber(b.key("events"), rx)
        wait_until(lambda: bool(_query(s, b.key("status"), 0.5)), what="the bridge")
        # A fleet-wide wildcard query reaches the command queryables but starts nothing.
        _query(s, "fleet/**", 1.0)
        assert b.daemon.bridge.calibrator.snapshot().mode is None

        (bad,) = _command(s, b.key("cmd/calibration/start"), {"what": "everything"})
        assert bad["ok"] is False and "what must be one of" in bad["message"]

        (started,) = _command(s, b.key("cmd/calibration/start"), {"what": "mag"})
        assert started["ok"] is True
        assert started["detail"]["result"] == "in_progress"
        assert b.daemon.bridge.calibrator.snapshot().running
        (again,) = _command(s, b.key("cmd/calibration/start"))
        assert again["ok"] is False and again["detail"]["result"] == "denied"

        (cancelled,) = _command(s, b.key("cmd/calibration/cancel"))
        assert cancelled["ok"] is True
        assert not b.daemon.bridge.calibrator.snapshot().running
        # The calibrator's own events reached the bus, in order.
        wait_until(
            lambda: "calibration.cancelled" in [d["kind"] for d in rx.docs(b.key("events"))],
            what="the cancel event",
        )
        kinds = [d["kind"] for d in rx.docs(b.key("events"))]
        assert kinds.index("calibration.started") < kinds.index("calibration.cancelled")


def test_access_control_denies_cmd_to_an_untrusted_peer(tmp_path: Path) -> None:
    # docs/zenoh.md's recipe, with peers told apart by zenoh id (on a real network:
    # usernames or certificate common names).
    acl = tmp_path / "zenoh-acl.json5"
    acl.write_text(
        json.dumps(
            {
                "access_control": {
                    "enabled": True,
                    "default_permission": "allow",
                    "rules": [
                        {
                            "id": "no-remote-calibration",
                            "permission": "deny",
                            "flows": ["ingress"],
                            "messages": ["query"],
                            "key_exprs": ["fleet/*/compass/cmd/**"],
                        }
                    ],
                    "subjects": [{"id": "viewers", "zids": [UNTRUSTED_ZID]}],
                    "policies": [{"rules": ["no-remote-calibration"], "subjects": ["viewers"]}],
                }
            }
        )
    )
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with (
        Bridge(
            tmp_path,
            "c3",
            listen=[endpoint],
            motion="tumble",
            remote_calibration=True,
            config_file=str(acl),
        ) as b,
        peer(connect=[endpoint], zid=UNTRUSTED_ZID) as viewer,
        peer(connect=[endpoint], zid=TRUSTED_ZID) as operator,
    ):
        for s in (viewer, operator):

            def reachable(s: zenoh.Session = s) -> bool:
                return bool(_query(s, b.key("status"), 0.5))

            wait_until(reachable, what="the bridge")
        # The viewer still sees the bridge, but its command never reaches the calibrator.
        assert _command(viewer, b.key("cmd/calibration/start")) == []
        assert b.daemon.bridge.calibrator.snapshot().mode is None
        (reply,) = _command(operator, b.key("cmd/calibration/start"))
        assert reply["ok"] is True and b.daemon.bridge.calibrator.snapshot().running
        assert _command(viewer, b.key("cmd/calibration/cancel")) == []
        assert b.daemon.bridge.calibrator.snapshot().running  # the viewer's cancel did nothing
        (reply,) = _command(operator, b.key("cmd/calibration/cancel"))
        assert reply["ok"] is True and not b.daemon.bridge.calibrator.snapshot().running
