"""``compass-bridge status`` against a running bridge (simulated compass, zenoh on loopback)."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from zenoh_rig import free_port, status_of_a_streaming_bridge

from bridge.tools.status import BridgeAnswers, format_human, run_status, summarise
from bridge.zenoh.monitor import MonitorOptions


@pytest.mark.integration
def test_status_reports_a_streaming_bridge_for_scripts_and_people(tmp_path: Path) -> None:
    b, port, code, doc, text = status_of_a_streaming_bridge(tmp_path, "boat7")
    (rec,) = doc["bridges"]
    assert rec["bridge"] == b.prefix
    assert rec["link"]["state"] == "streaming"
    assert 10.0 <= rec["link"]["frame_rate_hz"] <= 30.0  # the device's 20 Hz
    assert rec["counters"]["frames"] >= 40 and rec["counters"]["lost_frames"] == 0
    assert rec["calibration"]["source"] == "none (identity)"
    # The simulated unit is uncalibrated and has no [location]: disturbance flag known, not set.
    assert rec["quality"]["disturbed"] is False
    assert isinstance(rec["quality"]["heading_deg"], float)
    # streaming, but with no calibration in use: UNCALIBRATED, exit code 3 (not OK)
    assert rec["healthy"] is True and rec["calibrated"] is False
    assert rec["verdict"] == "UNCALIBRATED" and code == 3
    assert doc["asked"] == f"fleet/**/status via tcp/127.0.0.1:{port}"
    assert rec["drift"]["mode"] == "detect" and rec["drift"]["detected"] is False
    assert text.startswith(f"asked fleet/**/status via tcp/127.0.0.1:{port}: 1 bridge answered\n")
    assert f"{b.prefix}: UNCALIBRATED" in text and "streaming on" in text and "frames/s" in text


@pytest.mark.integration
def test_no_bridge_answering_exits_1(tmp_path: Path) -> None:
    opts = MonitorOptions(keyexpr="fleet/**", connect=(f"tcp/127.0.0.1:{free_port()}",))
    out = io.StringIO()
    assert run_status(opts, out, timeout=0.5) == 1
    assert out.getvalue().startswith(
        f"no compass bridge answered fleet/**/status via {opts.connect[0]} within 0.5 s"
    )


def test_summary_of_a_stale_link_is_not_healthy() -> None:
    a = BridgeAnswers(
        "fleet/x/compass",
        status={"link": {"state": "stale", "port": "/dev/ttyUSB0", "frame_rate_hz": 0.0},
                "calibration": {"source": "stored", "age_s": 7200.0, "state": "idle"}},
    )  # fmt: skip
    rec = summarise(a)
    assert rec["healthy"] is False
    text = format_human([rec])
    assert "NOT OK" in text and "stale" in text and "2.0 h old" in text
    assert "unknown (no heading heard)" in text


def test_a_drifted_calibration_is_said_on_its_own_line() -> None:
    drift = {"mode": "detect", "state": "drift", "detected": True, "change_mG": 41.6,
             "offset_change_mG": [40.0, -10.0, 5.0], "heading_error_deg": 11.2,
             "sigma_mG": 1.3, "learned_mG": 0.0, "steps": 0}  # fmt: skip
    a = BridgeAnswers(
        "fleet/x/compass",
        status={"link": {"state": "streaming", "port": "/dev/ttyUSB0", "frame_rate_hz": 100.0},
                "calibration": {"source": "stored", "age_s": 60.0, "state": "idle",
                                "drift": drift}},
        heading={"heading_deg": 12.0, "flags": {"disturbed": False, "saturated": False}},
    )  # fmt: skip
    rec = summarise(a)
    assert rec["drift"] == drift and rec["healthy"] is True  # a heading still streams
    text = format_human([rec])
    assert "drift        DRIFT, 42 mG change, heading error up to 11.2 deg, mode detect" in text
    ok = summarise(BridgeAnswers("fleet/y/compass", status={"calibration": {
        "drift": {**drift, "state": "ok", "detected": False, "learned_mG": 38.0, "steps": 4,
                  "mode": "learn"}}}))  # fmt: skip
    assert "drift        ok, 38 mG learned in 4 steps, mode learn" in format_human([ok])


def test_a_calibration_storage_refused_is_said_and_a_paced_one_is_saving() -> None:
    """The status document's save_error is said beside the calibration (it is lost at the
    next restart until storage takes it) and on the first line, the verdict as it was; a
    paced one is "saving"; one never ours to save (the simulator's) says neither."""

    def said(cal: dict[str, object]) -> tuple[str, str]:
        """(the first line, the calibration line) for a status with calibration ``cal``."""
        a = BridgeAnswers(
            "fleet/x/compass",
            status={"link": {"state": "streaming", "port": "/dev/ttyUSB0", "frame_rate_hz": 10.0},
                    "calibration": {"state": "idle", "age_s": 5.0, **cal}},
            heading={"heading_deg": 12.0, "flags": {"disturbed": False, "saturated": False}},
        )  # fmt: skip
        rec = summarise(a)
        assert rec["calibration"]["save_error"] == cal.get("save_error")
        lines = format_human([rec]).splitlines()
        return lines[0], next(line for line in lines if line.startswith("  calibration"))

    first, refused = said({"source": "mag", "saved": False, "saving": False,
                           "save_error": "[Errno 28] No space left on device"})  # fmt: skip
    assert first == "fleet/x/compass: OK; calibration NOT SAVED"  # the verdict stays
    assert "NOT SAVED, lost at a restart until storage takes it: [Errno 28] No space" in refused
    first, paced = said({"source": "parameters", "saved": False, "saving": True,
                         "save_error": None})  # fmt: skip
    assert first == "fleet/x/compass: OK"
    assert paced.endswith(", saving") and "NOT SAVED" not in paced
    first, simulator = said({"source": "simulator (the unit's true errors)",
                             "saved": False, "saving": False, "save_error": None})  # fmt: skip
    assert first == "fleet/x/compass: OK"
    assert "NOT SAVED" not in simulator and "saving" not in simulator


def test_parameters_storage_refused_is_said_on_its_own_line() -> None:
    def text(parameters: dict[str, object] | None) -> str:
        status: dict[str, object] = {
            "link": {"state": "streaming", "port": "sim", "frame_rate_hz": 10.0}
        }
        if parameters is not None:
            status["parameters"] = parameters
        return format_human([summarise(BridgeAnswers("fleet/x/compass", status=status))])

    said = text({"save_error": "[Errno 30] Read-only file system"})
    assert (
        "  parameters   NOT SAVED, lost at a restart until storage takes them: "
        "[Errno 30] Read-only file system"
    ) in said
    assert said.splitlines()[0] == "fleet/x/compass: OK; parameters NOT SAVED"
    assert "parameters" not in text({"save_error": None})
    assert "parameters" not in text(None)  # an older bridge's status: nothing said
