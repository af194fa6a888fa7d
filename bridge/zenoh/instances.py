"""One bridge per key prefix: instance tokens, and who keeps a prefix two bridges claim.

Two bridges with the same ``[zenoh] key_prefix`` (two boards left at one
hostname) would interleave their headings under one key, and one ``start``
query would start a calibration on both. Zenoh's liveliness tokens tell them
apart: a token declared twice under one key is one token to everyone else (and
its DELETE, when one of them goes, hides the other), so every bridge declares
its own **instance token** ``<prefix>/@bridge/<started_ms>-<zid>`` beside the
prefix's token. ``@bridge`` is a verbatim chunk: no ``fleet/**`` wildcard
matches it, so existing subscribers see nothing new; a liveliness subscriber
on ``<prefix>/@bridge/*`` (``fleet/**/@bridge/*`` in ``monitor``) sees each
bridge's own.

The bridge that started first (the smallest id: start time, then zenoh id)
keeps the prefix; any other one **yields**: it publishes nothing and answers
no query under the prefix until the first one is gone, and says why, loudly,
while it waits. The one that keeps it reports the other in its status
document (``zenoh.duplicate_prefix``) and in its log, so both bridges and
``monitor`` (a ``DUP`` flag) tell the operator.

:class:`Instances` is the PURE bookkeeping (keys in, decisions out).
"""

from __future__ import annotations

import threading
from typing import Final

#: The chunk between a prefix and an instance id in an instance token's key.
INSTANCE_CHUNK: Final = "/@bridge/"


def instance_id(started_ms: int, zid: str) -> str:
    """An instance's id: its start time (ms, zero-padded, so ids sort by it), then its zid."""
    return f"{max(0, int(started_ms)):013d}-{zid}"


def instance_key(prefix: str, ident: str) -> str:
    """The instance token of bridge ``ident`` under ``prefix``."""
    return f"{prefix}{INSTANCE_CHUNK}{ident}"


def instance_keyexpr(keyexpr: str) -> str:
    """The instance tokens of every bridge whose prefix matches ``keyexpr``."""
    return f"{keyexpr}{INSTANCE_CHUNK}*"


class Instances:
    """The bridges seen on one prefix, our own included (thread-safe: zenoh's callbacks feed it)."""

    def __init__(self, prefix: str, own: str) -> None:
        self.prefix = prefix
        self.own = own
        self._lock = threading.Lock()
        self._ids = {own}
        self.version = 0  #: bumped on every change

    def update(self, key: str, alive: bool) -> bool:
        """An instance token under our prefix appeared (``alive``) or vanished; True if it changed
        what we know. Our own token never leaves (we hold it)."""
        head, sep, ident = key.rpartition(INSTANCE_CHUNK)
        if not sep or head != self.prefix or not ident or ident == self.own:
            return False
        with self._lock:
            if alive == (ident in self._ids):
                return False
            if alive:
                self._ids.add(ident)
            else:
                self._ids.discard(ident)
            self.version += 1
            return True

    def others(self) -> list[str]:
        """The other bridges on our prefix, oldest first."""
        with self._lock:
            return sorted(i for i in self._ids if i != self.own)

    @property
    def keeper(self) -> str:
        """The id of the bridge that keeps the prefix: the one that started first."""
        with self._lock:
            return min(self._ids)

    @property
    def holds(self) -> bool:
        """We keep the prefix (alone, or as the first to start)."""
        return self.keeper == self.own
