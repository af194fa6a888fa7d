"""The ``compass-bridge`` command line.

Subcommands::

    compass-bridge run --config FILE [--set SECTION.KEY=VALUE ...] [--console]
    compass-bridge run --simulate                  # built-in simulated compass, live console line
    compass-bridge run --simulate --reset          # the same, from a fresh simulator state
    compass-bridge config [--config FILE] [--set ...] [--simulate]  # the config in effect
    compass-bridge config --docs                   # the configuration reference (Markdown)
    compass-bridge simulate --link PATH [--seed N] [--shake G]  # serve a simulated compass on a pty
    compass-bridge record --port DEV --out FILE [--duration S]  # raw byte stream, live line
    compass-bridge calibrate --recording FILE [--method NAME] [--plot FILE.png]
                             [--state-dir DIR] [--yes|--no]   # offline fit of a recording
    compass-bridge calibrate --mavlink URL [--target-system N --target-component N]
                             [--plot FILE.png] [--yes|--no]   # a running bridge, ArduPilot flow
    compass-bridge status [KEYEXPR] [--json]       # one-shot health of running bridges (Zenoh)
    compass-bridge monitor [KEYEXPR] [--once]      # live table of every bridge on Zenoh

Long operations (record, calibrate) draw a progress bar or spinner with
an ETA on stderr when it is a terminal; ``--progress/--no-progress`` forces it.

Exit codes: 0 ok (including a stop by SIGINT/SIGTERM), 2 usage or
configuration error (message on stderr), 1 anything else; ``status`` and
``monitor --once`` 3 when a bridge streams but runs uncalibrated (docs/tools.md).

Heavy imports (numpy, the link, the simulator) happen inside the subcommands
so ``--version`` and usage errors answer at once.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import FrameType
from typing import Any, NoReturn

from bridge import __version__
from bridge.config import SIM_MOTIONS, Config, ConfigError, load_config
from bridge.tools import argtypes
from bridge.tools.progress import progress_option

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


def logging_options(parser: argparse.ArgumentParser, *, suppress: bool = False) -> None:
    """``-v`` / ``--log-level`` on ``parser`` (``python -m benchmarks`` has them too).

    :func:`setup_logging_from` turns them into the log level."""
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
    logging_options(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    common = argparse.ArgumentParser(add_help=False)
    logging_options(common, suppress=True)

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
    run.add_argument(
        "--reset",
        action="store_true",
        help="with --simulate: first delete the simulator's stored calibration and parameters "
        "(a fresh start)",
    )
    run.set_defaults(func=cmd_run)

    cfg = sub.add_parser(
        "config",
        parents=[common],
        help="validate a configuration; print the one in effect, each value with its origin",
    )
    _config_options(cfg)
    cfg.add_argument(
        "--simulate",
        action="store_true",
        help="the configuration `run --simulate` (with the same options) would use",
    )
    cfg.add_argument(
        "--docs",
        action="store_true",
        help="print the configuration reference (docs/configuration.md) instead, as Markdown",
    )
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
    sim.add_argument(
        "--shake",
        type=float,
        default=0.0,
        metavar="G",
        help="a hand shaking the unit: linear acceleration, g RMS per axis (default 0)",
    )
    sim.add_argument("--flash", metavar="FILE", help="keep the unit's flash in FILE across runs")
    sim.add_argument(
        "--location",
        type=argtypes.location,
        metavar="LAT,LON[,ALT]",
        help="where the unit is (degrees, metres; default Zurich)",
    )
    sim.add_argument(
        "--hard-iron-change",
        type=argtypes.hard_iron_change,
        metavar="X,Y,Z@S",
        help="the unit's hard iron changes by X,Y,Z mG (sensor axes) S seconds after "
        "power-up (a bracket bolted on: drift for the bridge to find)",
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
    progress_option(rec, "live line")
    rec.set_defaults(func=cmd_record)

    _tools_parsers(sub, common)

    mon = sub.add_parser(
        "monitor",
        parents=[common],
        help="live table of every compass bridge on Zenoh (heading, attitude, rate, link, age)",
    )
    mon.add_argument(
        "keyexpr",
        nargs="?",
        default="fleet/**",
        metavar="KEYEXPR",
        help="key expression the bridges publish under (default fleet/**)",
    )
    mon.add_argument(
        "--connect",
        action="append",
        default=[],
        type=argtypes.zenoh_endpoint,
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to (repeatable; default tcp/127.0.0.1:7447, "
        "this host's bridge, unless --listen or --zenoh-config is given)",
    )
    mon.add_argument(
        "--listen",
        action="append",
        default=[],
        type=argtypes.zenoh_endpoint,
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on (repeatable; default none)",
    )
    mon.add_argument("--mode", choices=("peer", "client"), default="peer", help="zenoh mode")
    mon.add_argument(
        "--zenoh-config", metavar="FILE", help="zenoh JSON5 configuration used as the base"
    )
    mon.add_argument(
        "--multicast-scouting", action="store_true", help="find bridges by multicast scouting"
    )
    mon.add_argument(
        "--interval",
        type=argtypes.positive_seconds,
        default=1.0,
        metavar="S",
        help="refresh every S seconds",
    )
    mon.add_argument(
        "--once",
        action="store_true",
        help="collect for a moment (--duration, default 2.5 s), print one table, exit "
        "(exit code 1 if no bridge was seen, 3 if one runs uncalibrated)",
    )
    mon.add_argument(
        "--duration",
        type=argtypes.positive_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds",
    )
    mon.add_argument(
        "--plain",
        action="store_true",
        help="plain blocks of lines even on a terminal (the default when not a terminal)",
    )
    mon.set_defaults(func=cmd_monitor)
    return parser


def setup_logging_from(args: argparse.Namespace, stream: Any = None) -> None:
    """Logging as :func:`logging_options` asked (``stream``: stderr by default)."""
    level = args.log_level or {0: "WARNING", 1: "INFO"}.get(args.verbose, "DEBUG")
    # One line per record, rate-limited repeats; under systemd (stderr is the journal)
    # with <N> priority prefixes and no timestamps: the journal stamps time and unit itself.
    from bridge.logsetup import setup_logging

    setup_logging(level, sys.stderr if stream is None else stream)


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


def cmd_run(args: argparse.Namespace) -> int:
    """``run``: load the configuration, start the daemon, stop on SIGINT/SIGTERM."""
    from bridge.tools.simulator import reset_state, simulate_overrides

    overrides = list(args.overrides)
    if args.simulate:
        overrides[:0] = simulate_overrides(overrides, args.config)
    elif args.config is None:
        raise UsageError("run needs --config FILE (or --simulate for the built-in simulator)")
    if args.reset and not args.simulate:
        raise UsageError("--reset goes with --simulate (it clears the simulator's state)")
    cfg = load_config(args.config, overrides)
    if args.reset:
        from bridge.documents import StorageError

        try:
            print(reset_state(cfg.storage.dir), file=sys.stderr)
        except StorageError as e:
            raise UsageError(f"--reset: {e}") from None
    if args.simulate:
        log.info("simulated compass: state directory %s", cfg.storage.dir)

    from bridge.daemon import run_daemon

    def reload_config() -> Config:
        # SIGHUP: the same file and overrides as at start, read and validated afresh.
        return load_config(args.config, overrides)

    console = args.simulate or args.console
    gate = None
    if console and sys.stdout.isatty() and sys.stderr.isatty():
        # Log lines on the live line's terminal wait, as the line does, while the bridge is
        # a background job (`run --simulate &`): they would break another tool's display.
        from bridge.console import TerminalGate

        gate = TerminalGate(sys.stderr)
        setup_logging_from(args, gate)
    stop = threading.Event()
    with stop_on_signals(stop):
        return run_daemon(cfg, stop, console=console, reload_config=reload_config, gate=gate)


def cmd_config(args: argparse.Namespace) -> int:
    """``config``: the configuration in effect as TOML, each value with its origin (or the
    reference); warnings (a port that is not there now ...) on stderr."""
    if args.docs:
        from bridge.app.paramdocs import reference_markdown

        sys.stdout.write(reference_markdown())
        return EXIT_OK
    from bridge.tools.effective import effective, render, warnings
    from bridge.tools.simulator import simulate_overrides

    own = simulate_overrides(args.overrides, args.config) if args.simulate else []
    result = effective(args.config, args.overrides, simulate=own)
    sys.stdout.write(render(result))
    for text in warnings(result):
        print(f"warning: {text}", file=sys.stderr)
    return EXIT_OK


def cmd_simulate(args: argparse.Namespace) -> int:
    """``simulate``: serve the simulated compass on a pty until SIGINT/SIGTERM."""
    from bridge.sim.pty import run_simulator
    from bridge.tools.simulator import serving_line

    def ready(sim: Any) -> None:
        print(serving_line(args, sim.device), flush=True)

    # run_simulator stops cleanly on SIGINT/SIGTERM itself.
    return run_simulator(
        args.link,
        args.seed,
        args.location,
        on_ready=ready,
        motion=args.motion,
        flash_path=args.flash,
        ideal=args.ideal,
        shake_g=args.shake,
        unplug_s=args.unplug_s,
        garbage_bytes=args.garbage_bytes,
        hard_iron_change=args.hard_iron_change,
    )


def cmd_record(args: argparse.Namespace) -> int:
    """``record``: write the raw byte stream of a port to a recording (stops on SIGINT/SIGTERM)."""
    from bridge.tools.recording import record_with_progress

    summary = record_with_progress(
        args.port, args.baud, args.out, args.duration, enabled=args.progress
    )
    print(
        f"recorded {summary.bytes} bytes in {summary.records} records over "
        f"{summary.seconds:.1f} s to {summary.path} (port lost {summary.port_losses} times)",
        file=sys.stderr,
    )
    return EXIT_OK


def _tools_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """``calibrate`` and ``status`` (bridge/tools)."""
    cal = sub.add_parser(
        "calibrate",
        parents=[common],
        help="calibrate the magnetometer: offline on a recording, or a running bridge over MAVLink",
    )
    where = cal.add_mutually_exclusive_group(required=True)
    where.add_argument("--recording", metavar="FILE", help="a `record` recording to fit offline")
    where.add_argument(
        "--mavlink", metavar="URL", help="pymavlink connection to a running bridge (udpin:...)"
    )
    cal.add_argument(
        "--method",
        default="best",
        help="engine method (offline; default best): minmax, scalar, ellipsoid, best "
        "(twelve_position and accel_six_face need a live unit)",
    )
    cal.add_argument(
        "--location", type=argtypes.location, metavar="LAT,LON[,ALT]", help="for the WMM"
    )
    cal.add_argument("--state-dir", metavar="DIR", help="offline: save an accepted result here")
    cal.add_argument(
        "--plot",
        metavar="FILE.png",
        help="draw raw vs calibrated samples (offline: the recording; live: RAW_IMU of the run)",
    )
    cal.add_argument("--target-system", type=int, default=1, metavar="ID")
    cal.add_argument("--target-component", type=int, default=1, metavar="ID")
    cal.add_argument("--timeout", type=argtypes.positive_seconds, default=180.0, metavar="S")
    yn = cal.add_mutually_exclusive_group()
    yn.add_argument("--yes", action="store_true", help="accept without asking")
    yn.add_argument("--no", action="store_true", help="show the result, never accept")
    progress_option(cal, "live bar (and coverage map)")
    cal.set_defaults(func=cmd_calibrate)

    st = sub.add_parser(
        "status", parents=[common], help="one-shot health of running bridges (over Zenoh)"
    )
    st.add_argument(
        "keyexpr", nargs="?", default="fleet/**/status", metavar="KEYEXPR", help="bridges to ask"
    )
    st.add_argument(
        "--connect",
        action="append",
        default=[],
        type=argtypes.zenoh_endpoint,
        metavar="ENDPOINT",
        help="zenoh endpoint to ask (repeatable; default tcp/127.0.0.1:7447, this host's bridge)",
    )
    st.add_argument(
        "--json",
        action="store_true",
        help="JSON for scripts (exit 0 all OK, 1 one NOT OK or none, 3 one UNCALIBRATED)",
    )
    st.add_argument("--timeout", type=argtypes.positive_seconds, default=3.0, metavar="S")
    st.set_defaults(func=cmd_status)


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``calibrate``: see :mod:`bridge.tools.calibrate`."""
    from bridge.calibration.fits.methods import LIVE_ONLY, METHOD_NAMES, canonical_name
    from bridge.tools.calibrate import cmd_calibrate as run

    try:
        name = canonical_name(args.method)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if args.recording and name in LIVE_ONLY:
        raise UsageError(
            f"method {name!r} needs a live unit ({LIVE_ONLY[name]}), not a recording; "
            f"on a recording use one of: {', '.join(m for m in METHOD_NAMES if m not in LIVE_ONLY)}"
        )
    return run(args)


def cmd_status(args: argparse.Namespace) -> int:
    """``status``: see :mod:`bridge.tools.status`."""
    from bridge.tools.status import run_status
    from bridge.zenoh.monitor import MonitorOptions

    opts = MonitorOptions(keyexpr=args.keyexpr, connect=tuple(args.connect))
    return run_status(opts, sys.stdout, as_json=args.json, timeout=args.timeout)


def cmd_monitor(args: argparse.Namespace) -> int:
    """``monitor``: the fleet view; stops on SIGINT/SIGTERM, ``--duration`` or ``--once``."""
    import zenoh

    from bridge.zenoh.monitor import MonitorOptions, run_monitor

    try:
        zenoh.KeyExpr(args.keyexpr)
    except zenoh.ZError as e:
        raise UsageError(f"{args.keyexpr!r} is not a key expression: {e}") from None
    opts = MonitorOptions(
        keyexpr=args.keyexpr,
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        config_file=args.zenoh_config or "",
        multicast_scouting=args.multicast_scouting,
        interval=args.interval,
        once=args.once,
        duration=args.duration,
        tty=False if args.plain else None,
    )
    stop = threading.Event()
    with stop_on_signals(stop):
        return run_monitor(opts, sys.stdout, stop=stop)


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------


def _exit_code(e: SystemExit) -> int:
    if e.code is None:
        return EXIT_OK
    return e.code if isinstance(e.code, int) else EXIT_USAGE


def _end_process(code: int) -> NoReturn:
    """Exit with ``code`` at once, skipping the interpreter's finalization.

    Called after ``run`` stopped cleanly: outputs closed, state saved (fsynced),
    logs flushed below. Finalizing the interpreter would then tear down native
    runtimes that still own threads (zenoh's); that aborts the process now and
    then (SIGABRT, glibc "exception not rethrown", about 1 stop in 20 after a
    zenoh query), which systemd records as a crash of the service.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point; returns the exit code."""
    parser = build_parser()
    in_process = argv is not None  # a caller in this process, not the program itself
    words = argtypes.glue_negative_values(list(sys.argv[1:] if argv is None else argv))
    try:
        args = parser.parse_args(words)
    except SystemExit as e:  # argparse: --help/--version (0) or usage error (2)
        return _exit_code(e)
    setup_logging_from(args)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        code = func(args)
        if not in_process and args.command == "run":
            _end_process(code)  # the program itself (not a caller in-process): see there
        return code
    except SystemExit as e:  # a subcommand ending the program itself
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
