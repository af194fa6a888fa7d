"""The ``compass-bridge`` command line.

Subcommands::

    compass-bridge run --config FILE [--set SECTION.KEY=VALUE ...] [--console]
    compass-bridge run --simulate                  # built-in simulated compass, live console line
    compass-bridge config [--config FILE] [--set ...]   # validate, print the effective config
    compass-bridge simulate --link PATH [--seed N] # serve a simulated compass on a pty
    compass-bridge record --port DEV --out FILE    # record the raw byte stream
    compass-bridge bench accuracy [...]            # accuracy benchmark

Exit codes: 0 ok (including a stop by SIGINT/SIGTERM), 2 usage or
configuration error (message on stderr), 1 anything else.

Heavy imports (numpy, the link, the simulator) happen inside the subcommands
so ``--version`` and usage errors answer at once.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import FrameType
from typing import Any

from bridge import __version__
from bridge.config import SIM_MOTIONS, ConfigError, load_config, to_toml

log = logging.getLogger("bridge.cli")

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2

#: After SIGINT/SIGTERM the daemon has this long to stop before the process exits anyway.
SHUTDOWN_TIMEOUT_S = 5.0

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


class UsageError(Exception):
    """A command line that parses but makes no sense (exit code 2)."""


# ---------------------------------------------------------------------------
# Parser
# ---------------------------------------------------------------------------


def _logging_options(parser: argparse.ArgumentParser, *, suppress: bool) -> None:
    # The same options are accepted before and after the subcommand; SUPPRESS on
    # the subparsers keeps a value given before the subcommand from being reset.
    default: Any = argparse.SUPPRESS if suppress else None
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=argparse.SUPPRESS if suppress else 0,
        help="more log output (-v info, -vv debug)",
    )
    parser.add_argument(
        "--log-level",
        type=str.upper,
        choices=LOG_LEVELS,
        default=default,
        help="log level (default WARNING; overrides -v)",
    )


def _config_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="TOML configuration file")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one key (value parsed as TOML, else a string); repeatable",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for docs and tests)."""
    parser = argparse.ArgumentParser(
        prog="compass-bridge",
        description="GMR compass bridge: calibrated, tilt-compensated heading to MAVLink and Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"compass-bridge {__version__}")
    _logging_options(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    common = argparse.ArgumentParser(add_help=False)
    _logging_options(common, suppress=True)

    run = sub.add_parser("run", parents=[common], help="run the daemon")
    _config_options(run)
    run.add_argument(
        "--simulate",
        action="store_true",
        help='use the built-in simulated compass (device.port = "sim") and show a live line',
    )
    run.add_argument(
        "--console", action="store_true", help="show the live heading line (implied by --simulate)"
    )
    run.set_defaults(func=cmd_run)

    cfg = sub.add_parser(
        "config", parents=[common], help="validate a configuration and print the effective one"
    )
    _config_options(cfg)
    cfg.set_defaults(func=cmd_config)

    sim = sub.add_parser(
        "simulate", parents=[common], help="serve a simulated compass on a pseudo-terminal"
    )
    sim.add_argument("--link", required=True, metavar="PATH", help="symlink to create to the pty")
    sim.add_argument("--seed", type=int, default=1, metavar="N", help="unit seed (default 1)")
    sim.add_argument(
        "--motion", choices=SIM_MOTIONS, default="turns", help="motion script (default turns)"
    )
    sim.add_argument("--ideal", action="store_true", help="a perfect, noise-free unit")
    sim.add_argument("--flash", metavar="FILE", help="keep the unit's flash in FILE across runs")
    sim.add_argument(
        "--location",
        type=_location,
        metavar="LAT,LON[,ALT]",
        help="where the unit is (degrees, metres; default Zurich)",
    )
    sim.add_argument(
        "--unplug-s",
        type=float,
        default=1.0,
        metavar="S",
        help="on SIGUSR1 the pty goes away and a new one appears after S seconds (default 1)",
    )
    sim.add_argument(
        "--garbage-bytes",
        type=int,
        default=256,
        metavar="N",
        help="on SIGUSR2 send N bytes of line noise (default 256)",
    )
    sim.set_defaults(func=cmd_simulate)

    rec = sub.add_parser("record", parents=[common], help="record a compass's raw byte stream")
    rec.add_argument("--port", required=True, help="serial device (or sim)")
    rec.add_argument("--baud", type=int, default=115200, help="baud rate (default 115200)")
    rec.add_argument("--out", required=True, metavar="FILE", help="recording to write")
    rec.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    rec.set_defaults(func=cmd_record)

    bench = sub.add_parser("bench", parents=[common], help="benchmarks")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", required=True)
    # The benchmark parses its own options (and its own --help): everything after
    # "accuracy" is passed through unparsed (see main()).
    acc = bench_sub.add_parser(
        "accuracy",
        add_help=False,
        help="heading accuracy of the calibration methods (prints figures, JSON)",
    )
    acc.set_defaults(func=cmd_bench_accuracy, passthrough=True)
    return parser


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------


def _location(text: str) -> tuple[float, float, float]:
    """``LAT,LON[,ALT]`` for ``simulate --location``."""
    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers: {text!r}") from None
    if len(parts) not in (2, 3) or not (-90 <= parts[0] <= 90 and -180 <= parts[1] <= 180):
        raise argparse.ArgumentTypeError(
            f"want LAT,LON[,ALT] in degrees (and metres), got {text!r}"
        )
    return (parts[0], parts[1], parts[2] if len(parts) == 3 else 0.0)


def _setup_logging(args: argparse.Namespace) -> None:
    level = args.log_level or {0: "WARNING", 1: "INFO"}.get(args.verbose, "DEBUG")
    # Under systemd the journal stamps time and unit itself.
    fmt = "%(levelname)s %(name)s: %(message)s"
    if not os.environ.get("JOURNAL_STREAM"):
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level, format=fmt, stream=sys.stderr, force=True)


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` (a clean stop) while the block runs.

    If the clean stop takes longer than :data:`SHUTDOWN_TIMEOUT_S`, the
    process exits with code 1 anyway: a service manager must never wait on a
    wedged serial port.
    """

    watchdog = threading.Timer(SHUTDOWN_TIMEOUT_S, _force_exit)
    watchdog.daemon = True

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            return
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()
        watchdog.start()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        watchdog.cancel()  # stopped in time (a no-op if no signal came)
        for s, h in old.items():
            signal.signal(s, h)


def _force_exit() -> None:
    sys.stderr.write(f"compass-bridge: stop took over {SHUTDOWN_TIMEOUT_S:g} s, exiting\n")
    sys.stderr.flush()
    os._exit(EXIT_FAILURE)


# ---------------------------------------------------------------------------
# Commands
# ---------------------------------------------------------------------------


def simulator_state_dir() -> str:
    """State directory of ``run --simulate``: ``$XDG_STATE_HOME/compass-bridge/sim``.

    Falls back to ``~/.local/state`` (the XDG default) when XDG_STATE_HOME is unset.
    """
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(
        os.path.expanduser("~"), ".local", "state"
    )
    return os.path.join(base, "compass-bridge", "sim")


def cmd_run(args: argparse.Namespace) -> int:
    """``run``: load the configuration, start the daemon, stop on SIGINT/SIGTERM."""
    overrides = list(args.overrides)
    if args.simulate:
        # The simulated compass speaks the GMR protocol, whatever a --config file says.
        overrides[:0] = ["device.port=sim", "device.protocol=gmr"]
        if not any(o.startswith("storage.dir=") for o in overrides):
            # The simulated unit must never read or overwrite a real unit's calibration
            # in the service's state directory: give it a per-user directory of its own.
            overrides.insert(2, f"storage.dir={simulator_state_dir()}")
    elif args.config is None:
        raise UsageError("run needs --config FILE (or --simulate for the built-in simulator)")
    cfg = load_config(args.config, overrides)

    from bridge.daemon import run_daemon

    stop = threading.Event()
    with stop_on_signals(stop):
        return run_daemon(cfg, stop, console=args.simulate or args.console)


def cmd_config(args: argparse.Namespace) -> int:
    """``config``: validate and print the effective configuration as TOML."""
    cfg = load_config(args.config, args.overrides)
    sys.stdout.write(to_toml(cfg))
    return EXIT_OK


def cmd_simulate(args: argparse.Namespace) -> int:
    """``simulate``: serve the simulated compass on a pty until SIGINT/SIGTERM."""
    from bridge.sim.pty import run_simulator

    # run_simulator stops cleanly on SIGINT/SIGTERM itself.
    return run_simulator(
        args.link,
        args.seed,
        args.location,
        motion=args.motion,
        flash_path=args.flash,
        ideal=args.ideal,
        unplug_s=args.unplug_s,
        garbage_bytes=args.garbage_bytes,
    )


def cmd_record(args: argparse.Namespace) -> int:
    """``record``: write the raw byte stream of a port to a recording (stops on SIGINT/SIGTERM)."""
    from bridge.link.record import record

    summary = record(args.port, args.baud, args.out, args.duration)
    print(
        f"recorded {summary.bytes} bytes in {summary.records} records over "
        f"{summary.seconds:.1f} s to {summary.path} (port lost {summary.port_losses} times)",
        file=sys.stderr,
    )
    return EXIT_OK


def cmd_bench_accuracy(args: argparse.Namespace) -> int:
    """``bench accuracy``: hand over to the benchmark's own command line."""
    from bridge.bench.accuracy import main as accuracy_main

    return int(accuracy_main(args.rest) or 0)


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------


def _exit_code(e: SystemExit) -> int:
    if e.code is None:
        return EXIT_OK
    return e.code if isinstance(e.code, int) else EXIT_USAGE


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point; returns the exit code."""
    parser = build_parser()
    try:
        args, rest = parser.parse_known_args(argv)
        if rest and not getattr(args, "passthrough", False):
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
    except SystemExit as e:  # argparse: --help/--version (0) or usage error (2)
        return _exit_code(e)
    args.rest = rest
    _setup_logging(args)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except SystemExit as e:  # a passed-through parser (bench) exiting on --help or bad usage
        return _exit_code(e)
    except ConfigError as e:
        print(f"config error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as e:
        parser.print_usage(sys.stderr)
        print(f"compass-bridge: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_OK
    except Exception as e:
        log.debug("failed", exc_info=True)
        print(f"compass-bridge: error: {e}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
