"""``python -m benchmarks``: the table of benchmarks, each handed its own command line; run
from a checkout (the benchmarks are not installed with the package)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.__main__ import BENCHMARKS, build_parser, main

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
    assert set(BENCHMARKS) == {"accuracy", "pipeline", "fuzz", "drift", "tilt", "versus", "reads"}


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
