"""``python -m benchmarks``: the table of benchmarks, each handed its own command line; run
from a checkout (the benchmarks are not installed with the package)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks.__main__ import BENCHMARKS, build_parser, main
from benchmarks.figures import Figure, finish, report, write_json
from benchmarks.soak import (
    GroundStation,
    Sample,
    after_warmup,
    floor_change,
    slope_per_hour,
    warmup_s,
)
from benchmarks.soak import figures as soak_figures
from benchmarks.soak import run as soak_run

ROOT = Path(__file__).resolve().parent.parent


pytestmark = pytest.mark.usefixtures("restore_logging")  # main() runs in-process


def test_a_benchmark_is_required(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "required: BENCH" in capsys.readouterr().err


def test_bench_accuracy_is_wired(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["accuracy", "--help"]) == 0
    assert "usage: python -m benchmarks accuracy" in capsys.readouterr().out
    assert main(["accuracy", "--units", "0"]) == 2  # its own validation, its own code


def test_bench_drift_is_there() -> None:
    assert build_parser().parse_args(["drift"]).bench == "drift"
    assert set(BENCHMARKS) == {
        "accuracy",
        "pipeline",
        "fuzz",
        "drift",
        "tilt",
        "versus",
        "reads",
        "soak",
    }


@pytest.mark.integration
def test_run_from_a_checkout_as_a_module() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert all(name in r.stdout for name in BENCHMARKS)


@pytest.mark.parametrize("name", [*BENCHMARKS, "mavlink"])
def test_every_benchmark_takes_json_file_the_same_way(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--json FILE`` on every benchmark (``python -m benchmarks.mavlink`` too), with ``-``
    for the JSON on standard output: one meaning of one option, whichever is run."""
    if name == "mavlink":
        from benchmarks.mavlink import main as bench_main

        with pytest.raises(SystemExit) as e:  # its own argparse: no table around it
            bench_main(["--help"])
        assert e.value.code == 0
    else:
        assert main([name, "--help"]) == 0
    usage = " ".join(capsys.readouterr().out.split())
    assert "--json FILE" in usage and "'-': JSON on stdout" in usage


def test_json_is_written_beside_the_text_or_instead_of_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = {"figure": 1.5, "n": np.float64(2.0)}
    out = tmp_path / "figures.json"
    assert write_json("the table", doc, str(out), default=float)
    assert capsys.readouterr().out == "the table\n"
    assert json.loads(out.read_text()) == {"figure": 1.5, "n": 2.0}
    assert write_json("the table", doc, "-", default=float)
    assert json.loads(capsys.readouterr().out) == {"figure": 1.5, "n": 2.0}
    assert write_json("the table", doc, None, default=float)
    assert capsys.readouterr().out == "the table\n"


def test_a_json_file_that_cannot_be_written_is_said_and_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    nowhere = str(tmp_path / "missing" / "figures.json")
    assert not write_json("the table", {"a": 1}, nowhere)
    assert "cannot write" in capsys.readouterr().err
    passed = {"targets": [{"pass": True}]}
    assert finish("text", passed, nowhere) == 2
    assert finish("text", passed, None) == 0
    assert finish("text", {"targets": [{"pass": False}]}, None) == 1
    assert report([Figure("x", 1.0, "s", target=2.0)], nowhere) == 2


# -- soak ------------------------------------------------------------------------------


def _soak_samples(slope_mb_h: float, *, start_mb: float = 60.0, n: int = 121) -> list[Sample]:
    """A reading every 5 s for ten minutes, the resident set growing at ``slope_mb_h``
    (plus a page's wobble), 20 MB more during the first minute (the warm-up)."""
    out = []
    for i in range(n):
        t = 5.0 * i
        warm = 20.0 * min(1.0, t / 60.0)
        wobble = 0.004 * ((i * 7) % 3 - 1)
        out.append(Sample(t, start_mb + warm + slope_mb_h * t / 3600.0 + wobble, 17, 18))
    return out


def test_soak_growth_is_the_slope_after_the_warm_up() -> None:
    gcs = GroundStation(lists=10, whole=10, sets=10, acks=10)
    for slope in (0.0, 0.5, 3.0):
        figs = {f.name: f for f in soak_figures(_soak_samples(slope), gcs, warmup_s=60.0)}
        assert figs["rss_growth"].value == pytest.approx(slope, abs=0.05)
        assert figs["rss_growth"].passed is (slope <= 1.0)
    # the warm-up's 20 MB counted in: a growth far past the target
    assert slope_per_hour(_soak_samples(0.0)) > 10.0
    assert after_warmup(_soak_samples(0.0), 60.0)[0].t == 60.0
    assert (warmup_s(10.0), warmup_s(2.0), warmup_s(1.5)) == (200.0, 60.0, 0.0)
    assert math.isnan(slope_per_hour(_soak_samples(0.0)[:1]))


def test_soak_counts_threads_files_and_answers_after_the_warm_up() -> None:
    samples = _soak_samples(0.0)
    samples[3] = Sample(samples[3].t, samples[3].rss_mb, 12, 9)  # starting up: not counted
    for i in range(len(samples) - 20, len(samples)):  # a thread more from then on: a leak
        samples[i] = Sample(samples[i].t, samples[i].rss_mb, 18, 18)
    samples[40] = Sample(samples[40].t, samples[40].rss_mb, 17, 19)  # a file for a moment
    figs = {
        f.name: f
        for f in soak_figures(samples, GroundStation(lists=4, whole=3, sets=4, acks=4), 60.0)
    }
    assert figs["threads_change"].value == 1.0 and figs["threads_change"].passed is False
    assert figs["fds_change"].value == 0.0 and figs["fds_change"].passed is True
    assert figs["lists_answered"].value == 75.0 and figs["lists_answered"].passed is False
    assert all(math.isnan(f.value) for f in soak_figures([], GroundStation(), 60.0))


def test_a_count_is_judged_by_its_floor_a_moment_above_it_is_no_leak() -> None:
    assert floor_change([21] * 12) == 0.0
    assert floor_change([21, 22, 21, 21, 21, 21, 21, 21, 23, 21, 21, 21]) == 0.0  # moments
    assert floor_change([21] * 6 + [22] * 6) == 1.0  # one more from then on
    assert floor_change([21] * 6 + [22] * 4) == 0.0  # a short tail joins the run before it
    assert floor_change([21] * 12 + [26] * 6 + [31] * 6) == 10.0  # a port kept per pull
    assert math.isnan(floor_change([]))


def test_soak_with_cable_pulls_judges_files_on_settled_readings_and_counts_returns() -> None:
    samples = _soak_samples(0.0)
    samples[30] = Sample(samples[30].t, samples[30].rss_mb, 17, 17, settled=False)  # port out
    gcs = GroundStation(lists=4, whole=4, sets=4, acks=4)
    for text in ("Compass link lost (no valid frame for 2.0 s)", "Compass link restored") * 3:
        gcs.hear(text)
    gcs.hear("Parameters saved (storage is back)")  # not the link's
    assert (gcs.lost, gcs.restored) == (3, 3)
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=4)}
    assert figs["fds_change"].value == 0.0  # the reading with the port out not judged
    assert figs["link_returns"].value == 75.0 and figs["link_returns"].passed is False
    for i in range(31, len(samples)):  # settled, one file more from then on
        samples[i] = Sample(samples[i].t, samples[i].rss_mb, 17, 19)
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=3)}
    assert figs["fds_change"].value == 1.0 and figs["link_returns"].passed is True
    assert "link_returns" not in {f.name for f in soak_figures(samples, gcs, 60.0)}


def test_the_daemons_own_reopenings_are_judged_against_the_returns_heard() -> None:
    """SYS_STATUS's errors_count2 (the daemon's port reopenings) on the last settled reading
    against the returns heard by then: one nobody was told of is a figure of 1."""
    samples = _soak_samples(0.0)
    gcs = GroundStation(lists=4, whole=4, sets=4, acks=4)
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=2)}
    assert math.isnan(figs["reconnects_unheard"].value)  # no SYS_STATUS heard: not judged
    assert math.isnan(figs["pipeline_errors"].value)
    status = SimpleNamespace(errors_count1=3, errors_count2=2, errors_comm=40, errors_count4=0)
    gcs.status(status)
    assert (gcs.reconnects, gcs.lost_frames, gcs.bad_lines, gcs.pipeline_errors) == (2, 3, 40, 0)
    samples[-1] = replace(samples[-1], reconnects=2, restored=2)
    samples[-2] = replace(samples[-2], reconnects=3, restored=2)  # (not the last settled one)
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=2)}
    assert figs["reconnects_unheard"].value == 0.0 and figs["reconnects_unheard"].passed
    assert figs["reconnects_unheard"].detail["bad_lines"] == 40
    assert figs["pipeline_errors"].value == 0.0
    samples[-1] = replace(samples[-1], reconnects=3)  # a reopening no STATUSTEXT told of
    gcs.status(SimpleNamespace(errors_count1=3, errors_count2=3, errors_comm=40, errors_count4=1))
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=2)}
    assert figs["reconnects_unheard"].value == 1.0 and not figs["reconnects_unheard"].passed
    assert not figs["pipeline_errors"].passed
    samples[-1] = replace(samples[-1], settled=False)  # the last settled reading is judged
    figs = {f.name: f for f in soak_figures(samples, gcs, 60.0, pulls=2)}
    assert figs["reconnects_unheard"].value == 1.0  # (the one before: 3 against 2)


def test_a_soak_refuses_periods_the_bridge_refuses_by_design() -> None:
    with pytest.raises(ValueError, match="LIST_INTERVAL_S"):
        soak_run(0.1, period_s=2.0)  # lists refused by design that often
    with pytest.raises(ValueError, match="SETTLE_S"):
        soak_run(0.1, unplug_every_s=4.0, unplug_s=1.0)  # no time to settle between pulls


@pytest.mark.integration
@pytest.mark.slow  # 18 s of the daemon's real time: started first
def test_a_short_soak_with_the_compass_on_a_pty_pulled_out_twice() -> None:
    """The daemon child, its compass on a pseudo-terminal read through pyserial, its cable
    pulled every 6 s, and the ground station: each pull told lost and restored, every list
    answered whole and every command acknowledged, a reading a second, and the daemon back
    on the same threads and files after each return."""
    soaked = soak_run(0.3, period_s=3.0, sample_s=1.0, unplug_every_s=6.0, unplug_s=1.0)
    gcs = soaked.gcs
    assert soaked.pulls == 2 and gcs.lost == 2 and gcs.restored == 2
    # ... and the daemon's own counters (SYS_STATUS) say the same: two reopenings of the
    # port, the line noise between pulls dropped as bad lines, no pipeline error
    assert gcs.reconnects == 2 and gcs.bad_lines > 0 and gcs.pipeline_errors == 0
    assert gcs.lists >= 4 and gcs.whole == gcs.lists
    assert gcs.acks >= gcs.sets - 1 and gcs.sets >= 4
    assert 16 <= len(soaked.samples) <= 19
    assert all(20.0 < s.rss_mb < 200.0 and s.threads > 1 and s.fds > 3 for s in soaked.samples)
    # (from 2 s in: the first reading comes as the first list is answered, while the
    # daemon's start-up may still hold a file -- the benchmark's warm-up leaves it out)
    settled = [s for s in soaked.samples if s.settled and s.t >= 2.0]
    assert len(settled) >= 6 and settled[-1].t >= 16.0, settled  # after the second return too
    # judged by the floor of each two readings (two after each return): a file open for a
    # moment (params.json being written, on a loaded host) is no leak, a file per pull is
    assert floor_change([s.threads for s in settled], run=2) == 0, settled
    assert floor_change([s.fds for s in settled], run=2) == 0, settled
