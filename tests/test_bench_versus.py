"""``python -m benchmarks versus``: the figures are computed right; a short real run of both
programs on the simulated compass pairs every ATTITUDE with its frame. Never speed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from benchmarks import versus
from benchmarks.versus import LiveRun, ThreadCpu, figures, interleaved


def _run(program: str, cpu: float, p99: float, lat: list[float]) -> LiveRun:
    return LiveRun(
        program=program,
        cpu_pct=cpu,
        p50_ms=min(lat),
        p99_ms=p99,
        latencies_ms=lat,
        unmatched=0,
        attitude_hz=10.0,
        machine_busy_pct=50.0,
        loadavg="0.1 0.1 0.1",
        rss_mb=60.0,
        threads=[ThreadCpu(1, "reader", 0.1, 100, 0)],
    )


def test_figures_are_medians_and_their_ratios() -> None:
    runs = {
        "bridge": [_run("bridge", c, p, [p]) for c, p in ((1.0, 0.3), (3.0, 0.2), (2.0, 0.9))],
        "forwarder": [_run("forwarder", c, p, [p]) for c, p in ((4.0, 1.0), (5.0, 2.0))],
    }
    figs = {f.name: f for f in figures(runs)}
    assert figs["bridge_cpu"].value == 2.0  # the median of 1, 3, 2
    assert figs["bridge_cpu"].detail["runs"] == [1.0, 3.0, 2.0]
    assert figs["forwarder_cpu"].value == 4.5  # the median of two: their mean
    assert figs["bridge_p99"].value == 0.3
    assert figs["forwarder_p99"].value == 1.5
    assert figs["cpu_ratio"].value == pytest.approx(2.0 / 4.5)
    assert figs["cpu_ratio"].target == versus.TARGET_CPU_RATIO
    assert figs["cpu_ratio"].passed is False  # 0.44 > 0.35
    assert figs["p99_ratio"].value == pytest.approx(0.3 / 1.5)
    assert figs["p99_ratio"].passed is True  # 0.2 <= 0.4
    # Pooled: the 99th percentile of every run's latencies together.
    assert figs["bridge_p99"].detail["pooled_p99_ms"] == pytest.approx(0.9 - 0.02 * 0.6, 1e-3)
    assert figs["bridge_p99"].detail["samples"] == 3


def test_the_floor_is_set_against_the_forwarder_without_a_target() -> None:
    runs = {
        "bridge": [_run("bridge", 2.0, 0.8, [0.8])],
        "forwarder": [_run("forwarder", 5.0, 1.0, [1.0]), _run("forwarder", 5.0, 1.2, [1.2])],
        "floor": [_run("floor", 1.0, 0.5, [0.5]), _run("floor", 1.0, 0.4, [0.4])],
    }
    figs = {f.name: f for f in figures(runs)}
    assert figs["floor_p99_ratio"].value == pytest.approx(0.45 / 1.1)
    assert figs["floor_p99_ratio"].target is None
    assert figs["p99_ratio"].value == pytest.approx(0.8 / 1.1)  # the floor does not enter it
    assert figures({"floor": runs["floor"]})[-1].name == "floor_p99"  # no forwarder, no ratio


def test_one_program_alone_has_no_ratio() -> None:
    figs = figures({"bridge": [_run("bridge", 1.0, 0.5, [0.5])]})
    assert [f.name for f in figs] == ["bridge_cpu", "bridge_p99"]


def test_runs_interleave_and_the_first_program_alternates(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    order: list[str] = []
    subscribed: list[bool] = []

    def fake(program: str, duration_s: float, *, subscribe: bool = True) -> LiveRun:
        order.append(program)
        subscribed.append(subscribe)
        return _run(program, 1.0, 1.0, [1.0])

    monkeypatch.setattr(versus, "run_once", fake)
    runs = interleaved(3, 1.0, echo=False)
    assert order == ["bridge", "forwarder", "forwarder", "bridge", "bridge", "forwarder"]
    assert [len(v) for v in runs.values()] == [3, 3]
    assert all(subscribed)  # fleet software listens unless told otherwise
    interleaved(1, 1.0, echo=False, subscribe=False)
    assert subscribed[-2:] == [False, False]


@pytest.mark.integration
def test_short_run_of_both_programs_matches_every_attitude(tmp_path: Path) -> None:
    out = tmp_path / "versus.json"
    code = versus.main(["--rounds", "1", "--duration", "2", "--json", str(out)])
    doc = json.loads(out.read_text())
    figs = {f["name"]: f for f in doc["figures"]}
    assert set(figs) == {
        "bridge_cpu", "bridge_p99", "forwarder_cpu", "forwarder_p99", "cpu_ratio", "p99_ratio",
    }  # fmt: skip
    for p in ("bridge", "forwarder"):
        (run,) = doc["runs"][p]
        assert run["cpu_pct"] > 0.0 and run["rss_mb"] > 0.0 and run["unmatched"] == 0
        assert 0.0 < run["p50_ms"] <= run["p99_ms"] < 1000.0
        assert figs[f"{p}_p99"]["detail"]["samples"] >= 5
    # The bridge's Zenoh documents reach a subscriber (heading, attitude, imu at 10 Hz each,
    # status and events besides); the forwarder has no Zenoh.
    assert 25.0 <= doc["runs"]["bridge"][0]["zenoh_docs_hz"] <= 40.0
    assert doc["runs"]["forwarder"][0]["zenoh_docs_hz"] == 0.0
    # The forwarder sends one ATTITUDE a frame; the bridge at its shipped 10 Hz.
    assert doc["runs"]["forwarder"][0]["attitude_hz"] > 3 * doc["runs"]["bridge"][0]["attitude_hz"]
    ratio = figs["cpu_ratio"]["value"]
    assert math.isclose(
        ratio, figs["bridge_cpu"]["value"] / figs["forwarder_cpu"]["value"], rel_tol=1e-9
    )
    assert code == (0 if doc["passed"] else 1)


@pytest.mark.integration
def test_the_floor_sends_every_frame_s_attitude(tmp_path: Path) -> None:
    out = tmp_path / "floor.json"
    versus.main(["--only", "floor", "--rounds", "1", "--duration", "2", "--json", str(out)])
    (run,) = json.loads(out.read_text())["runs"]["floor"]
    # every datagram names the frame it came from (its yaw), one a frame at 100 Hz
    assert run["unmatched"] == 0 and run["attitude_hz"] > 80.0
    assert 0.0 < run["p50_ms"] <= run["p99_ms"] < 1000.0
