"""The state directory as the application sees it: named JSON documents that survive a crash.

The application layer (parameters, the calibration store) saves and loads
through :class:`DocumentStore`, never through the storage adapter's classes:
:class:`bridge.storage.StateStore` is one, and :mod:`bridge.daemon` hands it in.
A save that cannot be written ends with :class:`StorageError`; a load never
raises, it says what it found (:class:`LoadResult`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol


class StorageError(Exception):
    """A document could not be saved (the in-memory value stays authoritative)."""


@dataclass(frozen=True, slots=True)
class LoadResult:
    """What :meth:`DocumentStore.load` found.

    ``source`` is ``"current"``, ``"previous"`` (the current copy was bad and
    the last good copy was used) or ``"none"`` (nothing valid: use defaults).
    ``problems`` lists what was wrong with the copies that were rejected.
    """

    payload: dict[str, Any] | None
    source: str
    problems: tuple[str, ...] = ()
    saved_at: float | None = None


class DocumentStore(Protocol):
    """Named JSON documents that survive a crash (the state directory)."""

    def save(self, name: str, payload: dict[str, Any], version: int = 1) -> None:
        """Replace document ``name``; :class:`StorageError` when it cannot be written."""
        ...

    def load(self, name: str) -> LoadResult:
        """Document ``name`` (its last good copy); never raises for a bad file."""
        ...
