"""The compass as the application sees it: :class:`DevicePort` and the words it is told in.

The application layer (:mod:`bridge.app`, with the calibration controller) talks
to the compass through :class:`DevicePort`, never through the serial adapter's
classes, so the dependencies point inwards: :class:`bridge.link.serial_link.CompassLink`
is a :class:`DevicePort`, and :mod:`bridge.daemon` hands it in. (The state
directory has its own: :mod:`bridge.documents`.)

The types every layer names live here too: the link's state and counters (in
every status), a received frame, and the errors a device command can end with.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol, TypeAlias

from bridge.protocol.gmr import AckFrame, GmrFrame, ParamsFrame, VersionFrame
from bridge.protocol.heading import HeadingFrame

#: What the link hands on: a GMR sentence, or a heading-only compass's sentence.
LinkFrame: TypeAlias = GmrFrame | HeadingFrame

# ---------------------------------------------------------------------------
# The compass link
# ---------------------------------------------------------------------------


class LinkState(enum.Enum):
    """Where the compass link stands: ``absent`` (no port), ``opening`` (port open, no
    valid frame yet), ``streaming``, ``stale`` (no valid frame for ``stale_after``)."""

    ABSENT = "absent"
    OPENING = "opening"
    STREAMING = "streaming"
    STALE = "stale"


@dataclass(frozen=True, slots=True)
class LinkCounters:
    """A snapshot of the link's counters (all cumulative since the link was made)."""

    bytes_read: int = 0
    frames: int = 0  #: valid sentences decoded, of any type
    attitude_frames: int = 0
    bad_lines: Mapping[str, int] = field(default_factory=dict)  #: decoder drops by reason
    lost_frames: int = 0  #: from $PGMRA seq gaps (mod 65536)
    seq_discontinuities: int = 0  #: seq jumps too large (or backwards) to be loss
    reconnects: int = 0  #: successful opens after the first
    open_failures: int = 0
    stale_events: int = 0
    device_resets: int = 0  #: unasked $PGMRV, or seq restarting at 0
    callback_errors: int = 0
    commands_sent: int = 0  #: attempts written, retries included
    command_retries: int = 0
    command_timeouts: int = 0
    command_rejections: int = 0
    late_answers: int = 0  #: answers to timed-out attempts, absorbed
    unsolicited_answers: int = 0  #: acks nobody was waiting for

    @property
    def bad_lines_total(self) -> int:
        """All decoder drops."""
        return sum(self.bad_lines.values())


class Received(NamedTuple):
    """A decoded frame and the monotonic time its last byte was read (the link's output).

    ``t`` is the time the outputs pace it by. A frame held through a burst that was read
    after the due time is stamped just before it, so that no held frame passes for the
    due one (``bridge.link.serial_link._held``); ``read_at`` then keeps when it was read,
    which the frame clock needs (an arrival stamped earlier than the frame came would put
    the instants of the frames after it early). None: ``t`` is the read's time.
    """

    frame: LinkFrame
    t: float
    read_at: float | None = None


class CommandError(Exception):
    """A device command could not be completed."""


class CommandTimeout(CommandError):  # noqa: N818 - named by the link interface
    """No answer after all attempts."""


class CommandLate(CommandTimeout):
    """The device answered, but after its datasheet deadline: a time-out all the same.

    The command was not sent again (its answer could still come), so it ran on the
    device once; ``answer`` is what the device said (an OK or an ERR frame) and
    ``late_s`` how long after the deadline it came.
    """

    def __init__(self, command: str, answer: Any, late_s: float, deadline_s: float) -> None:
        super().__init__(
            f"{command} answered {late_s:.2f} s after its {deadline_s:.2f} s deadline "
            "(the compass is slower than its datasheet)"
        )
        self.command = command
        self.answer = answer
        self.late_s = late_s


class CommandRejected(CommandError):  # noqa: N818 - named by the link interface
    """The device answered ``$PGMRK,<command>,ERR,<reason>``."""

    def __init__(self, command: str, reason: str, answer: AckFrame) -> None:
        super().__init__(f"{command} rejected by the device: {reason}")
        self.command = command
        self.reason = reason
        self.answer = answer


class CommandNotSupported(CommandError):  # noqa: N818 - named by the link interface
    """The link's protocol has no commands (heading-only compasses)."""


class LinkDown(CommandError):  # noqa: N818 - named by the link interface
    """The port is not open, or the link is closed."""


class DevicePort(Protocol):
    """What the application uses of the compass link (device commands and its state)."""

    @property
    def name(self) -> str:
        """The port's name."""
        ...

    @property
    def protocol(self) -> str:
        """``"gmr"`` (raw vectors, commands) or a heading-only protocol."""
        ...

    @property
    def state(self) -> LinkState:
        """The link's state now."""
        ...

    @property
    def counters(self) -> LinkCounters:
        """The link's counters now."""
        ...

    @property
    def version(self) -> VersionFrame | None:
        """The last ``$PGMRV`` seen."""
        ...

    @property
    def params(self) -> ParamsFrame | None:
        """The last ``$PGMRP`` seen."""
        ...

    def command(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> Any:
        """One command transaction; the answer frame, or a :class:`CommandError`."""
        ...
