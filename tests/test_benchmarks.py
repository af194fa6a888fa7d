"""``python -m benchmarks``: the table of benchmarks, each handed its own command line; run
from a checkout (the benchmarks are not installed with the package)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.__main__ import BENCHMARKS, build_parser, main
from benchmarks.figures import Figure, finish, report, write_json

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
