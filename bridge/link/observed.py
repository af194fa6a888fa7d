"""A transport whose reader-side calls report progress, and that can be swapped while open.

The service watchdog vouches for the serial reader only while it makes
progress: every return (or exception) from ``open()`` and ``read()`` -- the
calls only the link's reader thread makes -- calls ``on_progress``, so a read
that never returns (a wedged USB-serial driver) stops the beats.

A reload that changes the port's settings hands a new transport to
:meth:`ObservedTransport.replace`; the reader swaps it in at its next call.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from bridge.link.transport import Transport, TransportError

log = logging.getLogger(__name__)


class ObservedTransport:
    """Wraps a :class:`~bridge.link.transport.Transport` (see the module docstring).

    Everything else (``baud``, a simulator's ``firmware`` ...) is passed through.
    """

    def __init__(self, inner: Transport, on_progress: Callable[[], None]) -> None:
        self._inner: Any = inner
        self._on_progress = on_progress
        self._swap_lock = threading.Lock()
        self._pending: Transport | None = None

    def __getattr__(self, attr: str) -> Any:
        # Only called for attributes not found here: baud, firmware, ended, ...
        return getattr(self._inner, attr)

    @property
    def inner(self) -> Transport:
        """The transport in use."""
        inner: Transport = self._inner
        return inner

    @property
    def name(self) -> str:
        """The wrapped transport's name."""
        return str(self._inner.name)

    @property
    def interactive(self) -> bool:
        """The wrapped transport's ``interactive``."""
        return bool(self._inner.interactive)

    def replace(self, inner: Transport) -> None:
        """Use ``inner`` from now on (a reload changed the port settings).

        The swap happens in the reader thread, at its next ``read()`` (which
        then fails as if the port went away, so the link reopens -- now the new
        transport -- and redoes its connect handshake) or ``open()``. The old
        transport is closed there too: never under a read in progress.
        """
        with self._swap_lock:
            self._pending = inner

    def _swap(self) -> bool:
        if self._pending is None:
            # Unlocked peek (one attribute read) on the per-read path: a reload's replace()
            # racing it is seen at the next read, a few milliseconds later.
            return False
        with self._swap_lock:
            new, self._pending = self._pending, None
        if new is None:
            return False
        old, self._inner = self._inner, new
        try:
            old.close()
        except OSError as e:
            log.debug("closing the replaced transport: %s", e)
        return True

    def open(self) -> None:
        """Open the wrapped transport (progress either way)."""
        try:
            self._swap()
            self._inner.open()
        finally:
            self._on_progress()

    def read(self, max_bytes: int, timeout: float) -> bytes:
        """Read from the wrapped transport (progress on return)."""
        if self._swap():
            self._on_progress()
            raise TransportError("port settings changed by a reload; reopening")
        try:
            data: bytes = self._inner.read(max_bytes, timeout)
            return data
        finally:
            self._on_progress()

    def write(self, data: bytes) -> None:
        """Write to the wrapped transport (not progress: command threads write too)."""
        self._inner.write(data)

    def close(self) -> None:
        """Close the wrapped transport."""
        self._inner.close()
