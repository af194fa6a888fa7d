"""A small, fast run of the accuracy benchmark: the best method must reach the noise floor."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.accuracy import BenchConfig, format_report, main, run

SMALL = BenchConfig(
    units=2, seed=5, samples=500, eval_samples=400, spread_stops=60, timing_samples=0
)


@pytest.fixture(scope="module")
def small_result() -> dict[str, object]:
    return run(SMALL)


def test_best_method_beats_the_symmetric_ellipsoid_and_reaches_the_floor(
    small_result: dict[str, object],
) -> None:
    summary = small_result["summary"]
    assert isinstance(summary, dict)
    for tilt in ("0", "30", "60"):
        floor, best, sym = (summary[m][tilt] for m in ("floor", "ellipsoid_aligned", "ellipsoid"))
        assert best["n"] == floor["n"] == 2 * 400
        # the symmetric fit leaves the non-orthogonality/misalignment: degrees, not tenths
        assert sym["rms_deg"] > 3.0 * best["rms_deg"]
        assert best["rms_deg"] <= 1.3 * floor["rms_deg"]
        assert best["max_deg"] <= 1.3 * floor["max_deg"]
        # the floor itself is sensor noise: 0.5 mG on 0.22 G horizontal, 1 mg tilt noise
        assert 0.1 < floor["rms_deg"] < 0.3


def test_every_unit_reports_its_fits_and_spreads(small_result: dict[str, object]) -> None:
    units = small_result["units"]
    assert isinstance(units, list) and len(units) == 2
    for u in units:
        assert u["reports"]["ellipsoid_aligned"]["status"] == "MAG_CAL_SUCCESS"
        assert "accelerometer: six-face" in u["reports"]["ellipsoid_aligned"]["notes"]
        spread = u["static_field_spread"]
        assert spread["scalar"]["half_pp_nT"] < 100.0 < spread["minmax"]["half_pp_nT"]


def test_clipping_unit_is_flagged_and_its_saturated_frames_unused() -> None:
    # 70-80 % hard iron: an axis reaches the +0.64 G rail of the datasheet's ADC
    # (2458 + 2560 counts/G tops out at 4095).
    cfg = BenchConfig(
        units=2,
        seed=1,
        samples=500,
        eval_samples=300,
        spread_stops=40,
        timing_samples=0,
        hard_iron_frac=(0.7, 0.8),
    )
    res = run(cfg)
    units = res["units"]
    clipped = [u for u in units if u["clips"]]
    assert clipped, "expected a clipping unit at this hard iron"
    for u in clipped:
        assert u["headroom_counts"] <= 0.0
        assert u["saturated_tumble"] > 0
        rep = u["reports"]["ellipsoid_aligned"]
        assert rep["n_rejected"] >= u["saturated_tumble"]
        # still calibrated to the floor on the frames that are not saturated
        for tilt in ("0", "60"):
            best = u["heading"]["ellipsoid_aligned"][tilt]
            floor = u["heading"]["floor"][tilt]
            assert best["rms_deg"] <= 1.3 * floor["rms_deg"]


def test_command_line_prints_targets_and_writes_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "acc.json"
    rc = main(
        [
            "--units",
            "1",
            "--samples",
            "400",
            "--eval-samples",
            "200",
            "--timing-samples",
            "2000",
            "--json",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    targets = data["targets"]
    assert rc == (0 if all(t["pass"] for t in targets) else 1)
    assert text.count("PASS") + text.count("FAIL") == len(targets) == 9
    assert data["timing"]["samples"] == 2000 and data["timing"]["median_ms"] > 0.0
    assert "ellipsoid_aligned (best)" in text
    with pytest.raises(SystemExit) as exc:  # argparse refuses a zero unit count
        main(["--units", "0"])
    assert exc.value.code == 2


def test_hand_held_conditions_put_the_live_fit_beside_the_floor() -> None:
    cfg = BenchConfig(
        units=1,
        seed=4,
        samples=300,
        eval_samples=100,
        spread_stops=20,
        timing_samples=0,
        shakes_g=(0.05,),
        holds=200,
    )
    res = run(cfg)
    (cond,) = res["handheld"]["conditions"]
    (unit,) = cond["units"]
    assert unit["complete"] and 40.0 < unit["seconds"] < 150.0  # ArduPilot's two steps
    pooled = cond["pooled"]
    floor, series, samples = pooled["floor"], pooled["series"], pooled["samples"]
    # the live fit is at the floor on the same frames; the kept samples alone are not
    assert series["rms_deg"] <= 1.3 * floor["rms_deg"]
    assert samples["rms_deg"] > 3.0 * floor["rms_deg"]
    assert unit["reports"]["series"]["heading_error_deg"] > 0.0
    names = [t["name"] for t in res["targets"]]
    assert "hand-held 0.05 g: heading RMS <= 1.3x floor" in names
    assert any(n.startswith("hand-held 0.05 g: announced heading error") for n in names)
    text = format_report(res)
    assert "hand-held tumble" in text and " series " in text and " samples " in text


def test_end_to_end_config_runs_the_simulated_daemon_with_its_shake(tmp_path: Path) -> None:
    from benchmarks.e2e import E2eConfig, _config_text
    from bridge.config import load_config

    text = _config_text(tmp_path / "state", 14600, 0.05, E2eConfig(rate_hz=50.0, seed=4))
    conf = tmp_path / "b.toml"
    conf.write_text(text)
    cfg = load_config(conf, env={}, hostname="h")
    assert (cfg.device.port, cfg.device.rate_hz) == ("sim", 50)
    assert (cfg.sim.motion, cfg.sim.shake_g, cfg.sim.seed) == ("tumble", 0.05, 4)
    assert cfg.mavlink.endpoints == ("udpin:127.0.0.1:14600",)
    assert not cfg.zenoh.enabled and cfg.location is not None
