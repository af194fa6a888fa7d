"""``compass-bridge monitor [KEYEXPR]``: a live table of every compass bridge on the bus.

The fleet operator's view, in the spirit of gpsd's ``cgps``: one row per
bridge seen under ``KEYEXPR`` (default ``fleet/**``) with its heading,
attitude, the rate its headings arrive at, the compass link state, the
calibration quality (``DRIFT`` among the flags when the bridge says its
calibration has drifted) and how old its data is. Bridges are found by their
publications and by their liveliness token; a bridge whose token vanishes is
shown as ``gone`` until it comes back.

``KEYEXPR`` selects bridges by their key prefix: ``fleet/**`` (every one),
``fleet/*/compass``, or one exact prefix (``fleet/boat7/compass``); the
documents under each prefix (``<prefix>/heading`` ...) are what is shown.
Two bridges on one prefix (each declares a liveliness token
``<prefix>/@bridge/<zid>``, see :mod:`bridge.zenoh.instances`) are flagged
``DUP``: their documents are interleaved and a command reaches both.

On a terminal the table is redrawn in place; otherwise (a pipe, a log, a
test) a plain block of lines is printed every ``interval`` seconds, or once
with ``--once``. ``--duration`` bounds the run.

:class:`FleetView` is the PURE part (documents in, rows and lines out, times
passed in); :func:`run_monitor` the adapter (zenoh session, clock, terminal).
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final, TextIO

from bridge.zenoh import schema
from bridge.zenoh.instances import INSTANCE_CHUNK, instance_keyexpr

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

DEFAULT_KEYEXPR: Final = "fleet/**"
#: Where a monitor looks when told nothing: a bridge on this host (its default listener).
DEFAULT_CONNECT: Final = ("tcp/127.0.0.1:7447",)

_STREAMS: Final = {
    schema.HEADING: "heading",
    schema.ATTITUDE: "attitude",
    schema.IMU: "imu",
    schema.STATUS: "status",
    schema.EVENT: "events",
}

#: A bridge whose last document is older than this is shown as stale ("!" after the age).
STALE_AFTER_S: Final = 3.0
_RATE_WINDOW_S: Final = 2.0


@dataclass(slots=True)
class BridgeState:
    """What the monitor knows about one bridge (``prefix`` = its key prefix)."""

    prefix: str
    heading: Mapping[str, Any] | None = None
    attitude: Mapping[str, Any] | None = None
    status: Mapping[str, Any] | None = None
    last_event: Mapping[str, Any] | None = None
    last_seen: float | None = None
    alive: bool | None = None  #: liveliness token: True present, False vanished, None unknown
    heading_times: deque[float] = field(default_factory=deque)
    documents: int = 0
    instances: set[str] = field(default_factory=set)  #: zenoh ids of bridges on this prefix

    @property
    def duplicated(self) -> bool:
        """More than one bridge publishes under this prefix (it says so, or we see two)."""
        zen = ((self.status or {}).get("zenoh") or {}) if self.status else {}
        return len(self.instances) > 1 or bool(zen.get("duplicate_prefix"))

    def rx_rate(self, now: float) -> float | None:
        """Headings received per second over the last couple of seconds."""
        times = self.heading_times
        while times and times[0] < now - _RATE_WINDOW_S:
            times.popleft()
        if len(times) < 2:
            return None
        span = max(now - times[0], times[-1] - times[0])
        return (len(times) - 1) / span if span > 0 else None


@dataclass(frozen=True, slots=True)
class Row:
    """One line of the table, as text cells."""

    bridge: str
    heading: str
    pitch: str
    roll: str
    rate: str
    link: str
    calibration: str
    flags: str
    age: str


HEADERS: Final = Row("BRIDGE", "HDG", "PITCH", "ROLL", "HZ", "LINK", "CAL", "FLAGS", "AGE")


class FleetView:
    """The table's model: feed it samples and liveliness changes; read rows. Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._bridges: dict[str, BridgeState] = {}
        self.rejected = 0  #: documents that failed their schema
        self.ignored = 0  #: documents of no schema we show

    # -- input ------------------------------------------------------------------------

    def update(self, key: str, payload: bytes, now: float) -> bool:
        """One sample from the bus; returns whether it was a valid document we show."""
        prefix, _, leaf = key.rpartition("/")
        try:
            doc = json.loads(payload)
        except (UnicodeDecodeError, json.JSONDecodeError):
            self.rejected += 1
            return False
        if not isinstance(doc, dict) or doc.get("schema") not in _STREAMS:
            self.ignored += 1
            return False
        try:
            name, _ = schema.validate(doc)
        except schema.SchemaError as e:
            self.rejected += 1
            log.debug("monitor: %s: %s", key, e)
            return False
        if not prefix or _STREAMS[name] != leaf:
            self.ignored += 1  # a document under a key that is not its stream
            return False
        with self._lock:
            b = self._bridge(prefix)
            b.last_seen = now
            b.documents += 1
            if name == schema.HEADING:
                b.heading = doc
                b.heading_times.append(now)
            elif name == schema.ATTITUDE:
                b.attitude = doc
            elif name == schema.STATUS:
                b.status = doc
            elif name == schema.EVENT:
                b.last_event = doc
        return True

    def liveliness(self, key: str, alive: bool, now: float) -> None:
        """A bridge's token appeared (``alive``) or vanished."""
        with self._lock:
            b = self._bridge(key)
            b.alive = alive
            if alive and b.last_seen is None:
                b.last_seen = now

    def instance(self, key: str, alive: bool, now: float) -> None:
        """A bridge's instance token ``<prefix>/@bridge/<zid>`` appeared or vanished."""
        prefix, sep, zid = key.rpartition(INSTANCE_CHUNK)
        if not sep or not prefix or not zid:
            return
        with self._lock:
            b = self._bridge(prefix)
            if alive:
                b.instances.add(zid)
            else:
                b.instances.discard(zid)

    def seen_documents(self) -> int:
        """Bridges with at least one valid document."""
        with self._lock:
            return sum(1 for b in self._bridges.values() if b.documents)

    def _bridge(self, prefix: str) -> BridgeState:
        b = self._bridges.get(prefix)
        if b is None:
            b = self._bridges[prefix] = BridgeState(prefix)
        return b

    # -- output -----------------------------------------------------------------------

    def bridges(self) -> list[str]:
        """Prefixes of every bridge seen, sorted."""
        with self._lock:
            return sorted(self._bridges)

    def state(self, prefix: str) -> BridgeState | None:
        """The state of one bridge (a live object: read under no lock only in tests)."""
        with self._lock:
            return self._bridges.get(prefix)

    def duplicated(self) -> list[str]:
        """Prefixes that more than one bridge holds (``DUP`` in the table)."""
        with self._lock:
            return sorted(p for p, b in self._bridges.items() if b.duplicated)

    def uncalibrated(self) -> list[str]:
        """Prefixes of the bridges whose last status says they run uncalibrated."""
        with self._lock:
            return sorted(p for p, b in self._bridges.items() if uncalibrated(b.status))

    def rows(self, now: float) -> list[Row]:
        """One row per bridge, sorted by prefix."""
        with self._lock:
            return [_row(self._bridges[p], now) for p in sorted(self._bridges)]

    def render(self, now: float, *, width: int = 120) -> list[str]:
        """The table as lines (a header, then one line per bridge)."""
        rows = self.rows(now)
        table = [HEADERS, *rows]
        cols = list(zip(*(_cells(r) for r in table), strict=True))
        widths = [max(len(c) for c in col) for col in cols]
        lines = []
        for r in table:
            cells = _cells(r)
            line = "  ".join(
                c.ljust(w) if i in (0, 5, 6, 7) else c.rjust(w)
                for i, (c, w) in enumerate(zip(cells, widths, strict=True))
            )
            lines.append(line.rstrip()[:width])
        if not rows:
            lines.append("(no compass bridge seen yet)")
        return lines


def _cells(r: Row) -> tuple[str, ...]:
    return (r.bridge, r.heading, r.pitch, r.roll, r.rate, r.link, r.calibration, r.flags, r.age)


def _num(v: Any, fmt: str) -> str:
    return format(v, fmt) if isinstance(v, int | float) and not isinstance(v, bool) else "-"


def _row(b: BridgeState, now: float) -> Row:
    h, a, s = b.heading, b.attitude, b.status
    heading = "-"
    flags: list[str] = []
    if h is not None:
        ref = "T" if h.get("heading_reference") == "true" else "M"
        heading = f"{_num(h.get('heading_deg'), '.1f')}{ref}"
        f = h.get("flags") or {}
        flags = [short for name, short in _FLAG_SHORT if f.get(name)]
    pitch = _num(a.get("pitch_deg"), "+.1f") if a is not None else "-"
    roll = _num(a.get("roll_deg"), "+.1f") if a is not None else "-"
    rate = b.rx_rate(now)
    link = "-"
    cal = "-"
    if s is not None:
        link_info = s.get("link") or {}
        link = str(link_info.get("state", "-"))
        dev_rate = link_info.get("frame_rate_hz")
        if isinstance(dev_rate, int | float) and link == "streaming":
            link += f" {dev_rate:.0f}Hz"
        cal = _calibration_text(s.get("calibration") or {})
        if schema.drift_detected(s):
            flags.append("DRIFT")
        if uncalibrated(s):
            flags.append("UNCAL")
        if schema.storage_refused(s):  # lost at a restart until saved
            flags.append("NOSAVE")
    if b.duplicated:
        flags.insert(0, f"DUP{max(2, len(b.instances))}")
    if b.alive is False:
        age = "gone"
    elif b.last_seen is None:
        age = "-"
    else:
        dt = max(0.0, now - b.last_seen)
        age = f"{dt:.1f}s" + ("!" if dt > STALE_AFTER_S else "")
    return Row(
        bridge=b.prefix,
        heading=heading,
        pitch=pitch,
        roll=roll,
        rate=f"{rate:.1f}" if rate is not None else "-",
        link=link,
        calibration=cal,
        flags=",".join(flags) or "-",
        age=age,
    )


def uncalibrated(status: Mapping[str, Any] | None) -> bool:
    """A status document says the bridge runs with no calibration (no iron correction)."""
    cal = status.get("calibration") if status is not None else None
    return isinstance(cal, Mapping) and cal.get("calibrated") is False


_FLAG_SHORT: Final = (
    ("saturated", "SAT"),
    ("degraded", "DEG"),
    ("disturbed", "DIST"),
    ("accelerating", "ACC"),
)


def _calibration_text(cal: Mapping[str, Any]) -> str:
    """Calibration quality in a few characters: what is applied, how good, what runs."""
    state = cal.get("state")
    percent = cal.get("percent")
    if isinstance(state, str) and state not in ("idle", "none", "") and state is not None:
        if isinstance(percent, int | float) and not isinstance(percent, bool):
            return f"{state} {percent:.0f}%"
        return state
    text = str(cal.get("source", "-"))
    fitness = cal.get("fitness_mG")
    if isinstance(fitness, int | float) and not isinstance(fitness, bool):
        text += f" {fitness:.1f}mG"
    return text


# ---------------------------------------------------------------------------
# The adapter
# ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MonitorOptions:
    """How the monitor connects and shows (``connect`` empty + no file = this host's bridge)."""

    keyexpr: str = DEFAULT_KEYEXPR
    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str = ""
    multicast_scouting: bool = False
    interval: float = 1.0
    once: bool = False
    duration: float | None = None
    tty: bool | None = None
    overrides: tuple[tuple[str, str], ...] = ()


def document_keys(keyexpr: str) -> tuple[str, ...]:
    """What to subscribe to for the documents of the bridges ``keyexpr`` selects.

    A bridge publishes ``<prefix>/<stream>``: an expression ending in ``**`` covers
    them already; any other (an exact prefix, ``fleet/*/compass``) names prefixes,
    so their streams are one chunk below (the expression itself is kept too, for a
    user who names one stream).
    """
    if keyexpr == "**" or keyexpr.endswith("/**"):
        return (keyexpr,)
    return (keyexpr, f"{keyexpr}/*")


def monitor_config(opts: MonitorOptions) -> zenoh.Config:
    """The monitor's zenoh configuration: a peer (or client) that listens nowhere by default."""
    import zenoh

    cfg = zenoh.Config.from_file(opts.config_file) if opts.config_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(opts.mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(opts.multicast_scouting))
    connect = opts.connect or (() if opts.config_file or opts.listen else DEFAULT_CONNECT)
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if opts.mode == "peer" and (opts.listen or not opts.config_file):
        # Zenoh's peer default listens on every interface; a viewer needs no listener.
        cfg.insert_json5("listen/endpoints", json.dumps(list(opts.listen)))
    for key, value in opts.overrides:
        cfg.insert_json5(key, value)
    return cfg


def run_monitor(
    opts: MonitorOptions,
    out: TextIO,
    *,
    stop: threading.Event | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> int:
    """Run the monitor until ``stop``, ``--duration`` or (``--once``) one table.

    Returns 0; with ``--once`` 1 when it saw no bridge at all and 3 when a bridge it saw
    runs uncalibrated (``UNCAL``), as ``status`` does (scripts can test it).
    The zenoh session is closed on every exit path.
    """
    import zenoh

    stop = stop if stop is not None else threading.Event()
    tty = out.isatty() if opts.tty is None else opts.tty
    view = FleetView()
    session = zenoh.open(monitor_config(opts))
    try:

        def on_sample(sample: zenoh.Sample) -> None:
            view.update(str(sample.key_expr), sample.payload.to_bytes(), clock())

        def on_token(sample: zenoh.Sample) -> None:
            view.liveliness(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, clock())

        def on_instance(sample: zenoh.Sample) -> None:
            view.instance(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, clock())

        # Held until the session closes: a dropped subscriber is undeclared.
        _subscribers = [
            *(session.declare_subscriber(k, on_sample) for k in document_keys(opts.keyexpr)),
            session.liveliness().declare_subscriber(opts.keyexpr, on_token, history=True),
            session.liveliness().declare_subscriber(
                instance_keyexpr(opts.keyexpr), on_instance, history=True
            ),
        ]
        return _show(view, opts, out, tty, stop, clock)
    finally:
        session.close()


def _show(
    view: FleetView,
    opts: MonitorOptions,
    out: TextIO,
    tty: bool,
    stop: threading.Event,
    clock: Callable[[], float],
) -> int:
    start = clock()
    # --once collects for a moment (a 1 Hz status needs a second) and prints one table.
    duration = opts.duration if opts.duration is not None else (2.5 if opts.once else None)
    end = start + duration if duration is not None else None
    if opts.once:
        stop.wait(max(0.0, end - clock()) if end is not None else 0.0)
        _write_block(out, view, clock(), tty=False)
        # as `status`: 0 all seen calibrated, 3 one runs uncalibrated (UNCAL), 1 none seen
        # or a prefix held by two bridges (DUP: nobody can tell whose heading is whose)
        if view.seen_documents() and not view.duplicated():
            return 3 if view.uncalibrated() else 0
        if view.bridges():  # a token, and not one document: say what was (not) seen
            out.write(
                f"no document from {', '.join(view.bridges())} in {duration:g} s "
                f"(a bridge's liveliness token only: is it publishing?)\n"
            )
        return 1
    # A terminal shows the (empty) table at once; a log gets its first block after one
    # interval, and a last one when the run ends (so a short --duration still prints).
    next_draw = start if tty else start + opts.interval
    last_draw: float | None = None
    try:
        while not stop.is_set():
            now = clock()
            if end is not None and now >= end:
                break
            if now >= next_draw:
                _write_block(out, view, now, tty=tty)
                last_draw, next_draw = now, now + opts.interval
            wake = next_draw if end is None else min(next_draw, end)
            stop.wait(max(0.0, wake - clock()))
        now = clock()
        if not tty and (last_draw is None or now - last_draw >= 0.5 * opts.interval):
            _write_block(out, view, now, tty=False)
    finally:
        if tty:
            with contextlib.suppress(Exception):
                out.write("\n")
                out.flush()
    return 0


def _write_block(out: TextIO, view: FleetView, now: float, *, tty: bool) -> None:
    lines = view.render(now)
    stamp = time.strftime("%H:%M:%S")
    title = f"compass-bridge monitor  {stamp}  {len(view.bridges())} bridge(s)"
    if tty:
        # Home the cursor and clear the screen, then draw: the table updates in place.
        out.write("\x1b[H\x1b[2J" + title + "\n\n" + "\n".join(lines) + "\n")
    else:
        out.write(title + "\n" + "\n".join(lines) + "\n\n")
    out.flush()
