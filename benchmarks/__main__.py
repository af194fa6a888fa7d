"""The benchmarks, run from a checkout: ``python -m benchmarks NAME [ARGS ...]``.

Each benchmark prints its figures (with its targets and PASS/FAIL where it has
them) and parses its own options (``python -m benchmarks NAME --help``);
everything after the name is handed over unparsed. ``-v`` / ``--log-level``
before the name set the log level as they do for ``compass-bridge``.

The benchmarks are not part of the installed package: they live beside it in
the repository, import :mod:`bridge` (installed, or the checkout's), and are
never imported by it. ``python -m benchmarks.mavlink`` runs the MAVLink
encoding benchmark, which has no entry here.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from bridge.cli import logging_options, setup_logging_from

#: The benchmarks, ``benchmarks.<name>``, each with its own command line (``main``).
BENCHMARKS = {
    "accuracy": "heading accuracy of the calibration methods (prints figures, JSON)",
    "pipeline": "speed and footprint: throughput, latency, CPU, RSS, start-up, fit time",
    "fuzz": "hostile input: fuzzed serial chunks and MAVLink messages against a running daemon",
    "drift": "hard-iron drift: detection time, false alarms, heading before/after learning",
    "tilt": "heading under acceleration: accelerometer, autopilot and magnetometer tilt sources",
    "versus": "CPU and latency against a naive 40-line forwarder on the same compass, interleaved",
    "reads": "the drift monitor on frames read as they come, in the link's bursts, on a busy host",
    "soak": "a long run of the real daemon: its memory, threads and files, and its answers",
}

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    """``python -m benchmarks [-v] [--log-level L] NAME ...``."""
    p = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="Benchmarks that print figures (run from a checkout of compass-bridge).",
    )
    logging_options(p)
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    # Each benchmark parses its own options (and its own --help): everything after its
    # name is passed through unparsed (see main()).
    for name, help_text in BENCHMARKS.items():
        sub.add_parser(name, add_help=False, help=help_text)
    return p


def _exit_code(e: SystemExit) -> int:
    if e.code is None:
        return 0
    return e.code if isinstance(e.code, int) else 2


def main(argv: Sequence[str] | None = None) -> int:
    """Hand over to the benchmark's own command line (imported on use); its exit code."""
    words = list(sys.argv[1:] if argv is None else argv)
    try:
        args, rest = build_parser().parse_known_args(words)
    except SystemExit as e:  # --help, or a usage error (2)
        return _exit_code(e)
    setup_logging_from(args)
    bench_main = importlib.import_module(f"benchmarks.{args.bench}").main
    try:
        return int(bench_main(rest) or 0)
    except SystemExit as e:  # the benchmark's parser: --help (0) or a usage error (2)
        return _exit_code(e)
    except KeyboardInterrupt:
        return 0
    except Exception as e:
        log.debug("failed", exc_info=True)
        print(f"python -m benchmarks: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
