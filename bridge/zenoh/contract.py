"""What the Zenoh output asks of the bridge, and what it counts.

:class:`FleetServices` is the output's view of the application (built from the
bridge's services by :func:`bridge.zenoh.services.fleet_services`),
:class:`CommandOutcome` a remote command's answer and :class:`ZenohCounters`
the counters ``<prefix>/status`` carries under ``zenoh``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from bridge.app.sample import DaemonStatus
    from bridge.events import Event


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """What a remote calibration command did: ``ok``, a sentence, and details (JSON-ready)."""

    ok: bool
    message: str
    detail: Mapping[str, Any] | None = None


def _no_state() -> Mapping[str, Any]:
    return {}


def no_unsubscribe() -> None:
    """An unsubscribe that has nothing to undo."""


@dataclass(slots=True)
class FleetServices:
    """What the Zenoh output asks of the rest of the bridge; every part but ``status`` optional.

    All callables are called from the output's or zenoh's threads and must be
    quick and thread-safe, except ``run_command`` (its own thread).

    * ``status`` -- the daemon's :class:`~bridge.app.sample.DaemonStatus`.
    * ``calibration_state`` -- a small JSON-ready dict for ``<prefix>/status``
      (``state``, ``source``, ``percent``, ``fitness_mG`` ...).
    * ``calibration_key`` -- its ``(state, source)`` alone, cheaper (looked at when
      something may have changed); without it they are read from ``calibration_state``.
    * ``calibration`` -- ``{"calibration", "source", "report", "state"}`` for
      the ``<prefix>/calibration`` query.
    * ``params`` -- the parameter table (name -> value), or None without one.
    * ``run_command`` -- ``(name, args) -> CommandOutcome`` for remote calibration.
    * ``subscribe_events`` / ``subscribe_mavlink`` -- register a callback,
      return the function that unregisters it (the MAVLink messages the bridge
      sends, whichever MAVLink output sends them: a reload does not detach it).
    * ``emit_event`` -- tell the operator on every front end (a key prefix shared
      with another bridge).
    * ``subscribe_link_state`` -- register a callback told every change of the link's
      state (any thread; it must be quick); returns its unregister. Without it the
      output looks for a change of the status twice a second.
    """

    status: Callable[[], DaemonStatus]
    calibration_state: Callable[[], Mapping[str, Any]] = _no_state
    calibration_key: Callable[[], tuple[Any, Any]] | None = None
    calibration: Callable[[], Mapping[str, Any]] | None = None
    params: Callable[[], Mapping[str, float]] | None = None
    run_command: Callable[[str, Mapping[str, Any]], CommandOutcome] | None = None
    subscribe_events: Callable[[Callable[[Event], None]], Callable[[], None]] | None = None
    subscribe_mavlink: Callable[[Callable[[Any], None]], Callable[[], None]] | None = None
    emit_event: Callable[[Event], None] | None = None
    tilt_state: Callable[[], Mapping[str, Any]] | None = None  #: the tilt source (status)
    subscribe_link_state: Callable[[Callable[[Any], None]], Callable[[], None]] | None = None

    def calibration_state_key(self) -> tuple[Any, Any]:
        """``(state, source)`` of the calibration: ``calibration_key`` or ``calibration_state``'s."""
        if self.calibration_key is not None:
            return self.calibration_key()
        cal = self.calibration_state()
        return cal.get("state"), cal.get("source")


@dataclass(slots=True)
class ZenohCounters:
    """The output's own counters (also published in ``<prefix>/status`` under ``zenoh``)."""

    published: dict[str, int] = field(default_factory=dict)
    unsent: int = 0  #: samples that came while no session was open
    decimated: int = 0  #: samples not published because of a rate cap
    put_errors: int = 0
    open_failures: int = 0
    sessions_opened: int = 0
    queries: int = 0
    query_errors: int = 0
    commands: int = 0
    commands_refused: int = 0  #: busy, or the key prefix is shared with another bridge
    bad_arguments: int = 0  #: commands refused for oversized or malformed arguments
    events_dropped: int = 0
    mirror_dropped: int = 0

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready copy."""
        return {
            "published": dict(self.published),
            "unsent": self.unsent,
            "decimated": self.decimated,
            "put_errors": self.put_errors,
            "open_failures": self.open_failures,
            "sessions_opened": self.sessions_opened,
            "queries": self.queries,
            "query_errors": self.query_errors,
            "commands": self.commands,
            "commands_refused": self.commands_refused,
            "bad_arguments": self.bad_arguments,
            "events_dropped": self.events_dropped,
            "mirror_dropped": self.mirror_dropped,
        }
