"""The Zenoh output: publications, queryables, remote calibration and a liveliness token.

Threads, and why:

* the pipeline (the link's reader thread) calls :meth:`ZenohOutput.publish` for every sample: it
  applies the rate caps and puts the documents of the streams that are due
  (at most one per stream per cap period, 10 Hz by default) itself. Another
  thread to hand them to would cost a wake-up, a GIL hand-over and a second
  cold start for every published sample -- more CPU than the puts (measured).
  The puts cannot hold the pipeline up: sensor streams use
  ``CongestionControl.DROP``, so a stalled subscriber makes zenoh drop *its*
  copies after a short bounded wait (``wait_before_drop``, 1 ms by default)
  instead of blocking; a put that fails is counted, never raised.
* the **publisher** thread (``zenoh-output``) opens the session (only here:
  after any fork, and a slow or failing open never holds up the daemon),
  declares everything, then turns events, the MAVLink mirror and the 1 Hz
  status into puts.
* the **command** thread (``zenoh-commands``, only with remote calibration)
  runs calibration commands, which talk to the compass and may take a while,
  so neither zenoh's callback threads nor the publisher wait on them.
* queryables (status, calibration, params) answer from zenoh's own callback
  threads with snapshots: quick, and they never raise into zenoh.

The session is closed on every exit path of the publisher thread (and, as a
last resort, by :meth:`close` if that thread does not stop in time): an
unclosed session keeps the interpreter alive.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Final

from bridge.app.services import SentMessage
from bridge.types import Clock
from bridge.zenoh import schema
from bridge.zenoh.commands import query_args, reply_command
from bridge.zenoh.contract import CommandOutcome, FleetServices, ZenohCounters, no_unsubscribe
from bridge.zenoh.instances import Instances, instance_id, instance_key, instance_keyexpr
from bridge.zenoh.mirror import MirrorMessage, mirror_key
from bridge.zenoh.pacing import Decimator, RateMeter, StatusTiming
from bridge.zenoh.session import ZenohSettings, describe_error, endpoints_text, open_session

if TYPE_CHECKING:
    import zenoh

    from bridge.app.sample import CompassSample
    from bridge.events import Event

log = logging.getLogger(__name__)


#: Remote calibration commands, as ``<prefix>/cmd/calibration/<name>``.
CALIBRATION_COMMANDS: Final = ("start", "accept", "cancel", "undo")

#: Seconds between attempts to open the session after a failure.
REOPEN_INTERVAL_S: Final = 0.5
#: How often the publisher looks for a status change when nothing tells it the link's state
#: moved (no ``subscribe_link_state``); else only events and those wake it (StatusTiming).
_CHANGE_POLL_S: Final = 0.5
#: After declaring our instance token: how long the others' (already there) take to arrive.
_CLAIM_SETTLE_S: Final = 0.3

#: A sensor stream: its name (the key under the prefix), its rate cap, its document builder.
_SensorStream = tuple[str, Decimator, Callable[..., "dict[str, Any] | None"]]


class ZenohOutput:
    """Publishes the bridge on Zenoh (see the module docstring). An :class:`~bridge.app.sample.Output`."""

    def __init__(
        self,
        settings: ZenohSettings,
        services: FleetServices,
        *,
        queue_len: int = 256,
        clock: Clock = time.monotonic,
        wall: Clock = time.time,
    ) -> None:
        if queue_len < 1:
            raise ValueError(f"queue_len must be >= 1, got {queue_len}")
        self.settings = settings
        self.services = services
        self._clock = clock
        self._wall = wall
        self._events: deque[Event] = deque(maxlen=100)
        self._mirror: deque[MirrorMessage | SentMessage] = deque(maxlen=queue_len)
        self._mirror_seq = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cmd_thread: threading.Thread | None = None
        self._commands: queue.Queue[tuple[str, Any, dict[str, Any]] | None] = queue.Queue(maxsize=8)
        self._session: zenoh.Session | None = None
        self._session_lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._mirror_publishers: dict[str, zenoh.Publisher] = {}
        self._keep: list[Any] = []  # queryables, token: undeclared when dropped, so kept here
        self._keep_claim: list[Any] = []  # our instance token and the others' subscriber
        self._claim: Instances | None = None
        self._claim_version = -1
        self._declared = False
        self._shared_with: list[str] = []  # the other bridges on our prefix, as last reported
        self._started_unix = wall()
        self._unsubscribe: list[Callable[[], None]] = []
        self._mirror_detach: Callable[[], None] = no_unsubscribe
        st = settings
        caps = tuple(
            Decimator(hz) for hz in (st.heading_rate_hz, st.attitude_rate_hz, st.imu_rate_hz)
        )
        self._decimators = caps
        #: The sensor streams in the order they go out: name, rate cap, document builder.
        self._streams = [(k, c, b) for (k, b), c in zip(schema.SENSOR_DOCS, caps, strict=True)]
        # Before this time no stream takes a sample (publish's one-comparison early out).
        self._opens_at = -math.inf
        self._rate = RateMeter(window=2.0)
        self._rate_lock = threading.Lock()
        poll = None if services.subscribe_link_state is not None else _CHANGE_POLL_S
        self._status_timing = StatusTiming(settings.status_period_s, poll)
        self._started_at = clock()
        self._logged: set[str] = set()
        self.counters = ZenohCounters()
        self.connected = threading.Event()  #: set while a session is open and declared

    # -- Output protocol ----------------------------------------------------------

    @property
    def name(self) -> str:
        """``"zenoh"``."""
        return "zenoh"

    def start(self) -> None:
        """Start the publisher thread (which opens the session)."""
        if self._thread is not None:
            raise RuntimeError("zenoh output already started")
        self._started_at = self._clock()
        self._started_unix = self._wall()
        s = self.services
        if s.subscribe_events is not None:
            self._unsubscribe.append(s.subscribe_events(self._on_event))
        if s.subscribe_link_state is not None:
            self._unsubscribe.append(s.subscribe_link_state(self._on_link_state))
        self._attach_mirror()
        self._thread = threading.Thread(target=self._run, name="zenoh-output", daemon=True)
        self._thread.start()
        if self.settings.remote_calibration:
            self._cmd_thread = threading.Thread(
                target=self._run_commands, name="zenoh-commands", daemon=True
            )
            self._cmd_thread.start()

    @property
    def due_at(self) -> float:
        """When a rate cap next opens (``+inf`` without a session: samples are only counted)."""
        return self._opens_at if self.connected.is_set() else math.inf

    def publish(self, sample: CompassSample) -> None:
        """Put ``sample`` on the streams whose rate caps let it through; never raises.

        Runs in the pipeline thread (see the module docstring): nothing is queued.
        """
        if not self.connected.is_set():
            # No session (yet, or it failed): a backlog would go out as a stale burst later.
            self.counters.unsent += 1
            return
        t = sample.t
        if t < self._opens_at:
            # No stream is due (at 100 Hz with 10 Hz caps: nine frames in ten): one
            # comparison instead of asking three decimators.
            self.counters.decimated += 3
            return
        due = [stream for stream in self._streams if stream[1].accept(t)]
        heading, attitude, imu = self._decimators
        self._opens_at = min(heading.opens_at, attitude.opens_at, imu.opens_at)
        if len(due) < 3:
            self.counters.decimated += 3 - len(due)
            if not due:
                return
        try:
            self._publish_sample(sample, due)
        except Exception as e:  # the session closing under us (a stop, a reload): count it
            self._put_failed("samples", e)

    def close(self, timeout: float) -> None:
        """Stop the threads and close the session within about ``timeout`` seconds."""
        deadline = self._clock() + timeout
        self._stop.set()
        self._wake.set()
        for unsubscribe in [*self._unsubscribe, self._mirror_detach]:
            with contextlib.suppress(Exception):
                unsubscribe()
        self._unsubscribe.clear()
        with contextlib.suppress(queue.Full):
            self._commands.put_nowait(None)
        for th in (self._thread, self._cmd_thread):
            if th is not None and th is not threading.current_thread():
                th.join(max(0.05, deadline - self._clock()))
        if self._thread is not None and self._thread.is_alive():
            log.error("zenoh output did not stop within %.1f s; closing its session", timeout)
            self._close_session()

    def _attach_mirror(self) -> None:
        """Attach the MAVLink mirror (once; it follows the bridge's MAVLink output by itself)."""
        s = self.services
        if not self.settings.mavlink_mirror or s.subscribe_mavlink is None:
            return
        if self._mirror_detach is no_unsubscribe:
            self._mirror_detach = s.subscribe_mavlink(self._on_mavlink)

    # -- callbacks from other threads -----------------------------------------------

    def _on_event(self, event: Event) -> None:
        if len(self._events) == self._events.maxlen:
            self.counters.events_dropped += 1
        self._events.append(event)
        self._wake.set()

    def _on_link_state(self, _state: Any) -> None:  # in the link reader's thread
        self._status_timing.note_change()  # the status may say something new: look
        self._wake.set()

    def _on_mavlink(self, msg: Any) -> None:
        # Called from the MAVLink side for every message it sends: keep it quick; decoding,
        # enum names and JSON happen later on our thread.
        try:
            m = msg if isinstance(msg, MirrorMessage | SentMessage) else MirrorMessage.capture(msg)
        except Exception:
            self.counters.mirror_dropped += 1
            return
        if len(self._mirror) == self._mirror.maxlen:
            self.counters.mirror_dropped += 1
        self._mirror.append(m)
        self._wake.set()

    # -- the publisher thread ---------------------------------------------------------

    def _run(self) -> None:
        try:
            if not self._open():
                return
            self._claim_prefix()
            self._follow_claim()  # declares everything, unless another bridge has the prefix
            self._loop()
        except Exception:
            log.exception("zenoh output failed; zenoh publishing stops (the bridge carries on)")
        finally:
            self._close_session()

    def _open(self) -> bool:
        """Open the session, retrying until it opens or the output stops."""
        st = self.settings
        while not self._stop.is_set():
            try:
                session, notes = open_session(st)
            except Exception as e:  # zenoh.ZError, OSError (config file), ValueError
                self.counters.open_failures += 1
                level = logging.WARNING if self.counters.open_failures == 1 else logging.DEBUG
                log.log(
                    level,
                    "zenoh: cannot open the session (%s); retrying every %.1f s",
                    describe_error(e),
                    REOPEN_INTERVAL_S,
                )
                self._stop.wait(REOPEN_INTERVAL_S)
                continue
            for note in notes:
                log.warning("zenoh: %s", note)
            with self._session_lock:
                self._session = session
            self.counters.sessions_opened += 1
            log.info(
                "zenoh: session %s open (%s; connect %s; listen %s); publishing under %s",
                session.zid(),
                st.mode,
                endpoints_text(st.connect),
                endpoints_text(st.listen) if st.listen else "default",
                st.key_prefix,
            )
            return True
        return False

    def _declare(self) -> None:
        import zenoh

        session = self._session
        assert session is not None
        st = self.settings
        streams = {
            "heading": schema.HEADING,
            "attitude": schema.ATTITUDE,
            "imu": schema.IMU,
            "status": schema.STATUS,
            "events": schema.EVENT,
        }
        for stream, name in streams.items():
            self._publishers[stream] = session.declare_publisher(
                st.key(stream),
                encoding=zenoh.Encoding(schema.encoding_text(name)),
                # Never block on a slow subscriber: zenoh drops its copy instead.
                congestion_control=zenoh.CongestionControl.DROP,
                # Events and status are rare and matter to the operator: ahead of the stream.
                priority=zenoh.Priority.DATA_HIGH
                if stream in ("status", "events")
                else zenoh.Priority.DATA,
            )
        # Commands first, status last of the queryables: whoever can query the status can
        # already command (a peer that waits for the status must not find the commands absent).
        if st.remote_calibration:
            for cmd in CALIBRATION_COMMANDS:
                key = st.key("cmd", "calibration", cmd)
                self._keep.append(
                    session.declare_queryable(key, self._command_handler(cmd, key), complete=False)
                )
            log.warning(
                "zenoh: remote calibration enabled on %s/cmd/calibration/*: restrict it with "
                "zenoh access control",
                st.key_prefix,
            )
        self._keep.append(
            session.declare_queryable(st.key("calibration"), self._answer_calibration)
        )
        self._keep.append(session.declare_queryable(st.key("params"), self._answer_params))
        self._keep.append(session.declare_queryable(st.key("status"), self._answer_status))
        # Declared last: fleet software seeing the token can query everything at once.
        self._keep.append(session.liveliness().declare_token(st.key_prefix))

    def _loop(self) -> None:
        timing = self._status_timing
        while not self._stop.is_set():
            self._wake.wait(max(0.0, timing.next_look - self._clock()) if self._declared else None)
            if self._stop.is_set():
                break
            self._wake.clear()
            claim = self._claim
            if claim is not None and claim.version != self._claim_version:
                self._follow_claim()
            if not self._declared:  # yielded the prefix: nothing out, asleep till the claim moves
                self._events.clear()
                self._mirror.clear()
                continue
            if self._drain_events():
                timing.note_change()  # a link or calibration event: the status may say more
            self._drain_mirror()
            now = self._clock()
            # The period's status needs no look at the key; between two, the key alone.
            if timing.due(now) or (
                timing.must_look(now) and timing.changed(self._status_change_key())
            ):
                doc = self._status_doc(sample_rate=True)
                self._put("status", doc)
                timing.published(schema.change_key(doc), now)
                self._attach_mirror()  # a reload may have replaced the MAVLink output

    # -- one bridge per key prefix (bridge.zenoh.instances) -------------------------------

    def _claim_prefix(self) -> None:
        """Declare our instance token and watch the others' (before anything else)."""
        session, st = self._session, self.settings
        assert session is not None
        ident = instance_id(int(self._started_unix * 1000), str(session.zid()))
        self._claim = Instances(st.key_prefix, ident)
        live = session.liveliness()
        self._keep_claim = [
            live.declare_subscriber(
                instance_keyexpr(st.key_prefix), self._on_instance, history=True
            ),
            live.declare_token(instance_key(st.key_prefix, ident)),
        ]
        # The tokens already there arrive moments after the subscriber's declaration.
        self._stop.wait(_CLAIM_SETTLE_S)

    def _on_instance(self, sample: zenoh.Sample) -> None:
        import zenoh

        claim = self._claim
        alive = sample.kind == zenoh.SampleKind.PUT
        if claim is not None and claim.update(str(sample.key_expr), alive):
            self._wake.set()

    def _follow_claim(self) -> None:
        """Publish under the prefix if we keep it, yield it if not; say so when it changes."""
        claim = self._claim
        assert claim is not None
        self._claim_version = claim.version
        others, prefix = claim.others(), self.settings.key_prefix
        if claim.holds and not self._declared:
            self._declare()
            self._declared = True
            # Only now: publish() puts on the declared publishers from the pipeline thread.
            self.connected.set()
        elif not claim.holds and self._declared:
            self.connected.clear()
            self._undeclare()
            self._declared = False
        if others == self._shared_with:
            return
        self._shared_with = others
        if not others:
            log.warning("zenoh: key prefix %s is this bridge's alone again", prefix)
            return
        what = (
            "this bridge started first and keeps it; the other publishes nothing"
            if claim.holds
            else "another bridge started first: this one publishes nothing and takes no "
            "command on Zenoh until it is gone"
        )
        text = (
            f"Zenoh key prefix {prefix} is used by {len(others)} other bridge(s) too: {what}; "
            "give each bridge its own [zenoh] key_prefix"
        )
        log.error("zenoh: %s (instances %s)", text, ", ".join(others))
        emit = self.services.emit_event
        if emit is not None:
            from bridge.events import Event, Severity

            data = {"prefix": prefix, "others": others, "keeps": claim.holds}
            emit(Event("zenoh.duplicate_prefix", text, Severity.ERROR, data))

    def _undeclare(self) -> None:
        """Everything under the prefix withdrawn (publishers, queryables, its token)."""
        for obj in [*self._publishers.values(), *self._mirror_publishers.values(), *self._keep]:
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._publishers.clear()
        self._mirror_publishers.clear()
        self._keep.clear()

    def _publish_sample(self, sample: CompassSample, due: list[_SensorStream]) -> None:
        session = self._session
        if session is None:  # closed since publish() looked at ``connected``
            self.counters.unsent += 1
            return
        ts = session.new_timestamp()
        t = sample.t
        times = schema.SampleTimes(
            t, self._wall() - (self._clock() - t), ts.to_string_rfc3339_lossy()
        )
        # Every document encoded first, then the puts back to back: zenoh's transmit thread
        # (on the other core) then finds them together and sends one batch, instead of
        # waking for each put while the next is still being encoded.
        bodies = []
        for stream, _cap, build in due:
            try:
                doc = build(sample, times)
                if doc is not None:
                    bodies.append((stream, schema.dumps(doc)))
            except Exception as e:  # one stream's failure does not hold the others back
                self._put_failed(stream, e)
        for stream, body in bodies:
            self._put_body(stream, body, ts)

    def _drain_events(self) -> bool:
        """Publish the queued events; True if there were any."""
        events = self._events  # appended to by other threads; taken from here only
        if not events:
            return False
        while events:
            self._put("events", schema.event_doc(events.popleft()))
        return True

    def _drain_mirror(self) -> None:
        if not self._mirror:  # most wake-ups (without the mirror: all)
            return
        import zenoh

        session = self._session
        assert session is not None
        while True:
            try:
                m = self._mirror.popleft()
            except IndexError:
                return
            try:
                if isinstance(m, SentMessage):
                    # Each MAVLink link numbers its own packets; the mirror is one more "link".
                    msg = m.message
                    m = MirrorMessage.from_fields(
                        msg.get_msgId(),
                        {f: getattr(msg, f) for f in msg.get_fieldnames()},
                        system_id=m.system_id,
                        component_id=m.component_id,
                        sequence=self._mirror_seq,
                    )
                    self._mirror_seq = (self._mirror_seq + 1) & 0xFF
                key, body = mirror_key(m), m.to_json()
                pub = self._mirror_publishers.get(key)
                if pub is None:
                    pub = session.declare_publisher(
                        key,
                        encoding=zenoh.Encoding.APPLICATION_JSON,
                        congestion_control=zenoh.CongestionControl.DROP,
                    )
                    self._mirror_publishers[key] = pub
                pub.put(body)
                self._count("mirror")
            except Exception as e:
                self._put_failed("mirror", e)

    def _put(self, stream: str, doc: Mapping[str, Any], ts: Any = None) -> None:
        self._put_body(stream, schema.dumps(doc), ts)

    def _put_body(self, stream: str, body: bytes, ts: Any = None) -> None:
        try:
            self._publishers[stream].put(body, timestamp=ts)
            self._count(stream)
        except Exception as e:  # a closed/broken session: count, say once, carry on
            self._put_failed(stream, e)

    def _count(self, stream: str) -> None:
        p = self.counters.published
        p[stream] = p.get(stream, 0) + 1

    def _put_failed(self, stream: str, e: Exception) -> None:
        self.counters.put_errors += 1
        if stream not in self._logged:
            self._logged.add(stream)
            log.warning(
                "zenoh: publishing %s failed (%s); further failures are only counted",
                stream,
                describe_error(e),
            )

    def _status_change_key(self) -> tuple[Any, ...]:
        """:func:`schema.change_key` of the status document, without building the document."""
        status = self.services.status()
        c = status.counters
        with self._rate_lock:  # fed at every look, so the frame rate is over the whole window
            self._rate.add(self._clock(), c.attitude_frames)
        return (status.state.value, *self._safe(self.services.calibration_state_key, (None, None)))

    def _status_doc(self, *, sample_rate: bool = False) -> dict[str, Any]:
        """The status document; ``sample_rate`` (publisher thread only) feeds the rate meter."""
        status = self.services.status()
        c = status.counters
        now = self._clock()
        with self._rate_lock:  # queries read it from zenoh's threads
            if sample_rate:
                self._rate.add(now, c.attitude_frames)
            frame_rate = self._rate.rate()
        return schema.status_doc(
            status,
            frame_rate_hz=frame_rate,
            calibration=self._safe(self.services.calibration_state, {}),
            publisher={**self.counters.as_dict(), "duplicate_prefix": list(self._shared_with)},
            t_unix=self._wall(),
            uptime_s=now - self._started_at,
            tilt=self._safe(self.services.tilt_state, {}) if self.services.tilt_state else None,
        )

    def _safe(self, fn: Callable[[], Any], default: Any) -> Any:
        try:
            return fn()
        except Exception:
            if "state" not in self._logged:
                self._logged.add("state")
                log.exception("zenoh: a status source failed (further failures not logged)")
            return default

    def _close_session(self) -> None:
        self.connected.clear()
        with self._session_lock:
            session, self._session = self._session, None
        self._keep.clear()
        self._keep_claim.clear()
        self._declared = False
        self._publishers.clear()
        self._mirror_publishers.clear()
        if session is not None:
            try:
                session.close()
            except Exception as e:
                log.warning("zenoh: closing the session failed: %s", describe_error(e))
            else:
                log.info("zenoh: session closed")

    # -- queryables (zenoh's callback threads) ------------------------------------------

    def _reply(self, query: zenoh.Query, key: str, name: str, build: Callable[[], Any]) -> None:
        import zenoh

        self.counters.queries += 1
        try:
            doc = build()
            query.reply(key, schema.dumps(doc), encoding=zenoh.Encoding(schema.encoding_text(name)))
        except Exception as e:
            self.counters.query_errors += 1
            log.debug("zenoh: answering %s failed", key, exc_info=True)
            with contextlib.suppress(Exception):
                query.reply_err(json.dumps({"error": describe_error(e)}).encode())

    def _answer_status(self, query: zenoh.Query) -> None:
        self._reply(query, self.settings.key("status"), schema.STATUS, self._status_doc)

    def _answer_calibration(self, query: zenoh.Query) -> None:
        def build() -> dict[str, Any]:
            get = self.services.calibration
            info: Mapping[str, Any] = get() if get is not None else {}
            return schema.calibration_doc(
                info.get("calibration"),
                source=str(info.get("source", "unknown")),
                report=info.get("report"),
                state=info.get("state"),
            )

        self._reply(query, self.settings.key("calibration"), schema.CALIBRATION, build)

    def _answer_params(self, query: zenoh.Query) -> None:
        def build() -> dict[str, Any]:
            get = self.services.params
            if get is None:
                raise LookupError("this bridge has no parameter table")
            return schema.params_doc(get())

        self._reply(query, self.settings.key("params"), schema.PARAMS, build)

    # -- remote calibration -----------------------------------------------------------------

    def _command_handler(self, cmd: str, key: str) -> Callable[[zenoh.Query], None]:
        def handler(query: zenoh.Query) -> None:
            # Only a query for exactly this key is a command: a fleet tool's
            # `get fleet/**` reaches this queryable too and must not start anything.
            # (It would also slip past an ACL rule on cmd/**, which matches by inclusion.)
            if str(query.key_expr) != key:
                return
            try:
                # Here, in zenoh's thread: bounded and quick (bridge.zenoh.commands).
                args = query_args(query)
            except ValueError as e:
                self.counters.bad_arguments += 1
                log.warning("zenoh: %s refused: bad arguments: %s", key, e)
                reply_command(query, key, cmd, CommandOutcome(False, f"bad arguments: {e}"))
                return
            shared = self._claim.others() if self._claim is not None else []
            if shared:
                self.counters.commands_refused += 1
                why = (
                    f"refused: key prefix {self.settings.key_prefix} is shared with another bridge"
                )
                reply_command(query, key, cmd, CommandOutcome(False, why))
                return
            try:
                self._commands.put_nowait((cmd, query, args))
            except queue.Full:
                self.counters.commands_refused += 1
                outcome = CommandOutcome(False, "busy: too many commands pending")
                reply_command(query, key, cmd, outcome)

        return handler

    def _run_commands(self) -> None:
        while True:
            item = self._commands.get()
            if item is None or self._stop.is_set():
                return
            self._execute(*item)

    def _execute(self, cmd: str, query: zenoh.Query, args: dict[str, Any]) -> None:
        key = self.settings.key("cmd", "calibration", cmd)
        self.counters.commands += 1
        run = self.services.run_command
        try:
            if run is None:
                outcome = CommandOutcome(False, "calibration is not available on this bridge")
            else:
                log.info("zenoh: remote calibration command %s %s", cmd, args or "")
                outcome = run(cmd, args)
        except ValueError as e:
            self.counters.bad_arguments += 1
            outcome = CommandOutcome(False, f"bad arguments: {e}")
        except Exception as e:
            log.exception("zenoh: calibration command %s failed", cmd)
            outcome = CommandOutcome(False, f"failed: {describe_error(e)}")
        reply_command(query, key, cmd, outcome)
