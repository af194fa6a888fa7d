"""Zenoh session settings and the zenoh configuration built from them.

The bridge is a guest on someone else's network, so the defaults are
conservative:

* **Listen on loopback only.** Zenoh's own default for a peer is a listener on
  every interface (``tcp/[::]:0``). With no ``listen`` endpoints configured the
  bridge listens on ``tcp/127.0.0.1:7447`` (Zenoh's well-known port, so a
  ``compass-bridge monitor`` on the same host finds it). If that port is taken
  (a ``zenohd`` on the host) the session opens without a listener and says so.
  A client never listens.
* **No multicast scouting** unless ``multicast_scouting = true``: nothing is
  sent to 224.0.0.224 and no stranger connects because of a multicast hello.
* **Fast re-join.** Zenoh retries a lost ``connect`` endpoint after 1 s, then
  backs off to 4 s; the bridge retries after 250 ms, backing off to 1 s, so a
  peer or router that comes back is re-joined in about a second.
* **Bounded input.** A message larger than 1 MiB (``transport/link/rx/max_message_size``,
  zenoh's own bound, 1 GiB by default) is dropped by zenoh before it is assembled.
* **No shared memory.** ``transport/shared_memory/enabled`` is off: every
  sensor document is a few hundred bytes and goes over the link's socket
  anyway, and once a peer on the same host has negotiated SHM, zenoh's ``net``
  thread wakes 20 times a second for the rest of the process's life
  (docs/zenoh.md, "Shared memory off").
* **Never fatal.** ``connect/exit_on_failure`` is off: an absent peer is
  retried in the background; a client's ``open`` gives up after
  ``connect/timeout_ms`` (1 s) and the output retries it itself.

A full zenoh JSON5 file (``config_file``) is the base when given: its TLS,
user/password and access-control settings pass straight through. The
``[zenoh]`` keys are applied on top: ``mode`` and ``multicast_scouting``
always; ``connect`` / ``listen`` only when non-empty (an empty list leaves the
file's endpoints alone); the retry tuning and the message bound only where the
file sets none; shared memory only where the file does not name it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    import zenoh

    from bridge.config import ZenohConfig

#: Listener used in peer mode when none is configured: loopback only.
DEFAULT_LISTEN: Final = ("tcp/127.0.0.1:7447",)

#: Connect retry: first retry after 250 ms, doubling up to 1 s (zenoh: 1 s up to 4 s).
CONNECT_RETRY: Final[Mapping[str, int]] = {
    "period_init_ms": 250,
    "period_max_ms": 1000,
    "period_increase_factor": 2,
}
#: How long ``open`` waits for a connect endpoint (a client needs its router).
CONNECT_TIMEOUT_MS: Final = 1000
#: Zenoh's shared-memory transport, off. With it on (zenoh's default) and a peer on the
#: same host that has it on too, the link negotiates SHM and zenoh starts its handoff
#: reclamation task (zenoh-transport ``unicast/establishment/ext/shm/handoff.rs``,
#: ``HandoffReactor::new``: a loop of ``tokio::time::sleep(100 ms)`` on ``ZRuntime::Net``).
#: It wakes the ``net-0`` thread 20 times a second (each 100 ms sleep is two timer-wheel
#: wake-ups) from the first such link on, for the life of the process: sent or not, peer
#: gone or not. The bridge never allocates SHM buffers, and its documents (a few hundred
#: bytes; the parameter table about 1 KB) are below the 3 KiB from which zenoh copies a
#: payload into SHM (``transport_optimization/message_size_threshold``); a larger reply
#: would have gone through SHM to a querier on the same host. Off, everything goes over
#: the link's socket: subscribers and queriers get the same bytes.
SHARED_MEMORY: Final = False
_SHARED_MEMORY_KEY: Final = "transport/shared_memory/enabled"
_SHARED_MEMORY_SECTION: Final = "shared_memory"
#: The largest message the bridge's session takes in (zenoh's own bound, 1 GiB by default):
#: the bridge receives queries (remote commands, a few hundred bytes) and liveliness
#: tokens, so 1 MiB leaves room; a flood of huge queries then costs no memory
#: (:mod:`bridge.zenoh.commands` answers "bad arguments" below it).
MAX_MESSAGE_BYTES: Final = 1 << 20


@dataclass(frozen=True, slots=True)
class ZenohSettings:
    """Everything the Zenoh output needs to know; built from ``[zenoh]`` by :meth:`from_config`.

    ``heading_rate_hz`` / ``attitude_rate_hz`` / ``imu_rate_hz`` cap the sensor
    streams (0 = every frame the compass sends). ``status_period_s`` paces
    ``<prefix>/status`` (it is also sent at once on a change).
    ``remote_calibration`` declares the ``cmd/calibration/*`` queryables;
    ``mavlink_mirror`` republishes the bridge's MAVLink messages as JSON.
    ``overrides`` are extra ``(key, json5 value)`` insertions applied last
    (tests, and settings no TOML key covers). ``default_listen`` is the
    listener a peer gets when none is configured.
    """

    enabled: bool = True
    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    key_prefix: str = "fleet/compass"
    multicast_scouting: bool = False
    config_file: str = ""
    heading_rate_hz: float = 0.0
    attitude_rate_hz: float = 0.0
    imu_rate_hz: float = 0.0
    status_period_s: float = 1.0
    remote_calibration: bool = False
    mavlink_mirror: bool = False
    overrides: tuple[tuple[str, str], ...] = ()
    default_listen: tuple[str, ...] = DEFAULT_LISTEN

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client"):
            raise ValueError(f"mode must be 'peer' or 'client', got {self.mode!r}")
        for name in ("heading_rate_hz", "attitude_rate_hz", "imu_rate_hz"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.status_period_s > 0.0:
            raise ValueError(f"status_period_s must be positive, got {self.status_period_s}")
        if not self.key_prefix or self.key_prefix.strip("/") != self.key_prefix:
            raise ValueError(f"key_prefix must be a key expression, got {self.key_prefix!r}")

    @classmethod
    def from_config(cls, zc: ZenohConfig, **extra: Any) -> ZenohSettings:
        """From the ``[zenoh]`` section (every key of it is a setting; ``extra`` sets the rest)."""
        values: dict[str, Any] = {f.name: getattr(zc, f.name) for f in fields(zc)}
        values.update(extra)
        for name in ("connect", "listen"):
            values[name] = tuple(values.get(name, ()))
        return cls(**values)

    def key(self, *parts: str) -> str:
        """``<prefix>/<parts...>``."""
        return "/".join((self.key_prefix, *parts))


def _json(v: Any) -> str:
    return json.dumps(v)


def config_items(
    settings: ZenohSettings,
    *,
    file_sets: frozenset[str] = frozenset(),
    with_default_listener: bool = True,
) -> list[tuple[str, str]]:
    """The ``(key, json5)`` insertions the settings make, in order. PURE.

    ``file_sets`` names the keys a base config file already sets (see
    :func:`build_config`): the retry tuning and the default listener yield to
    them. ``with_default_listener=False`` drops the implicit loopback
    listener (used when its port is taken).
    """
    items: list[tuple[str, str]] = [
        ("mode", _json(settings.mode)),
        ("scouting/multicast/enabled", _json(settings.multicast_scouting)),
    ]
    if settings.connect:
        items.append(("connect/endpoints", _json(list(settings.connect))))
    if "connect/retry" not in file_sets:
        items.append(("connect/retry", _json(dict(CONNECT_RETRY))))
    if "connect/timeout_ms" not in file_sets:
        items.append(("connect/timeout_ms", _json(CONNECT_TIMEOUT_MS)))
    if "connect/exit_on_failure" not in file_sets:
        items.append(("connect/exit_on_failure", _json(False)))
    if "transport/link/rx/max_message_size" not in file_sets:
        items.append(("transport/link/rx/max_message_size", _json(MAX_MESSAGE_BYTES)))
    if _SHARED_MEMORY_KEY not in file_sets:
        items.append((_SHARED_MEMORY_KEY, _json(SHARED_MEMORY)))
    if settings.mode == "client":
        # A client never listens; zenoh's client default is already no listener.
        pass
    elif settings.listen:
        items.append(("listen/endpoints", _json(list(settings.listen))))
    elif "listen/endpoints" not in file_sets:
        # Replace zenoh's every-interface default with loopback (or with nothing).
        items.append(
            (
                "listen/endpoints",
                _json(list(settings.default_listen) if with_default_listener else []),
            )
        )
    items.extend(settings.overrides)
    return items


#: Keys whose presence in a base file changes what :func:`config_items` inserts.
_FILE_KEYS: Final = (
    "transport/link/rx/max_message_size",
    _SHARED_MEMORY_KEY,
    "connect/retry",
    "connect/timeout_ms",
    "connect/exit_on_failure",
    "listen/endpoints",
)


def build_config(settings: ZenohSettings, *, with_default_listener: bool = True) -> zenoh.Config:
    """The zenoh configuration: ``config_file`` (if any) with the settings on top.

    Raises ``zenoh.ZError`` (or ``OSError``) for an unreadable or invalid file or value.
    """
    import zenoh

    if settings.config_file:
        cfg = zenoh.Config.from_file(settings.config_file)
        default = zenoh.Config()
        # A key the file leaves alone reads the same as in a default config.
        sets = {k for k in _FILE_KEYS if cfg.get_json(k) != default.get_json(k)}
        # Shared memory is zenoh's default: a file that turns it on reads like one that
        # says nothing, so a file that names the section at all decides it.
        if _SHARED_MEMORY_SECTION in Path(settings.config_file).read_text(errors="replace"):
            sets.add(_SHARED_MEMORY_KEY)
        file_sets = frozenset(sets)
    else:
        cfg = zenoh.Config()
        file_sets = frozenset()
    for key, value in config_items(
        settings, file_sets=file_sets, with_default_listener=with_default_listener
    ):
        cfg.insert_json5(key, value)
    return cfg


def uses_default_listener(settings: ZenohSettings, cfg: zenoh.Config) -> bool:
    """Whether ``cfg`` (from :func:`build_config`) listens on the implicit loopback default."""
    if settings.mode == "client" or settings.listen:
        return False
    listen = json.loads(cfg.get_json("listen/endpoints"))
    return bool(settings.default_listen) and listen == list(settings.default_listen)


def open_session(settings: ZenohSettings) -> tuple[zenoh.Session, list[str]]:
    """Open a session; returns it and notes worth logging (e.g. the default port was taken).

    Raises ``zenoh.ZError``/``OSError``/``ValueError`` when it cannot be opened.
    """
    import zenoh

    notes: list[str] = []
    cfg = build_config(settings)
    try:
        return zenoh.open(cfg), notes
    except zenoh.ZError as e:
        # The implicit loopback listener is a convenience: if its port is taken
        # (typically by a zenohd on this host) run without it rather than not at all.
        if not uses_default_listener(settings, cfg) or "listener" not in str(e):
            raise
        notes.append(
            f"{', '.join(settings.default_listen)} is not available ({_first_line(e)}); running without a "
            "listener -- set [zenoh] connect to reach a router on this host"
        )
        return zenoh.open(build_config(settings, with_default_listener=False)), notes


def _first_line(e: BaseException) -> str:
    text = str(e)
    return text.split(" at /", 1)[0].strip() or type(e).__name__


def describe_error(e: BaseException) -> str:
    """A zenoh error without its Rust source location."""
    return _first_line(e)


def endpoints_text(endpoints: Sequence[str]) -> str:
    """For logs."""
    return ", ".join(endpoints) or "none"
