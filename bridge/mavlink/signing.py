"""MAVLink 2 message signing: signing what we send, checking what we are told to do.

The signature (MAVLink 2 spec, "Message Signing") is 13 bytes after the CRC::

    link_id (1) | timestamp (6, little endian, 10 us units since 2015-01-01 UTC) | sig (6)
    sig = SHA-256(secret_key + header + payload + CRC + link_id + timestamp)[:6]

Outgoing packets are signed by pymavlink (each link's ``MAVLink`` object, set
up by :func:`sign_outgoing`); the bridge only keeps its timestamp at
``max(last + 1, wall clock)`` (:meth:`Signing.floor`) before each packet:
pymavlink counts up from where it started, so after a day of uptime at 40
packets a second its timestamp would be hours behind real time, and a peer
that restarts refuses a "new stream" more than a minute older than its own
clock.

Incoming signatures are *not* checked by pymavlink: its checker records a
stream's timestamp *before* it verifies the signature (so one forged packet
with a far-future timestamp locks the real sender out; shown by
``tests/test_mavlink_signing.py``), keeps its replay table per parser
instance (one per connection here, so a packet captured on one link could be
replayed on another), and is not thread-safe. The bridge therefore parses
without a key and checks signatures in one place, :class:`Signing`, shared by
every endpoint:

* **verify**: :meth:`Signing.verify` checks the signature *first*, then the
  replay rules: per stream ``(link_id, system, component)`` the timestamp
  must increase; a stream seen for the first time must not be more than
  :data:`NEW_STREAM_WINDOW_S` older than our own timestamp. Only a valid
  packet updates the table and advances our own timestamp.
* **peers**: :meth:`Signing.fresh` is the endpoints' question "may this packet make
  (or keep) its sender a peer?": a valid signature, newer than the last one seen
  from that stream *as a peer* (a table of its own, so it never spends the
  timestamp :meth:`Signing.verify` will check when the packet is obeyed) and than
  the last one obeyed, and not more than a minute older than our own clock for a
  stream not seen before. A replayed or forged packet makes nobody a peer.
* **restart**: the table lives on in the state directory (:meth:`Signing.snapshot`,
  :meth:`Signing.restore`; the MAVLink output writes it before it obeys a signed
  command or parameter set), so a packet captured before a restart is still a
  replay after it.
"""

from __future__ import annotations

import hashlib
import hmac
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from enum import Enum
from typing import Any

from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, SIGNATURE_LEN

#: 2015-01-01T00:00:00Z, the epoch of MAVLink signing timestamps.
SIGNING_EPOCH_UNIX = 1420070400
TICKS_PER_SECOND = 100_000  #: timestamps count 10 us ticks
NEW_STREAM_WINDOW_S = 60.0  #: the spec's "one minute" for a stream not seen before
KEY_BYTES = 32
_MAX_STREAMS = 4096  # bounded replay table: oldest streams are forgotten first


class Verdict(Enum):
    """Outcome of :meth:`Signing.verify`."""

    OK = "ok"
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad signature"
    REPLAY = "replayed (timestamp not newer than the stream's last)"
    STALE = "stale (new stream more than a minute old)"


def unix_to_ticks(t_unix: float) -> int:
    """A Unix time as a signing timestamp (never negative: a clock before 2015 gives 0)."""
    return max(0, int((t_unix - SIGNING_EPOCH_UNIX) * TICKS_PER_SECOND))


def is_signed(packet: bytes | bytearray) -> bool:
    """A MAVLink 2 packet whose incompat flags announce a signature."""
    return len(packet) > 2 and packet[0] == MAGIC_V2 and bool(packet[2] & IFLAG_SIGNED)


class Signing:
    """One secret key, the outgoing timestamp and the incoming replay table (thread-safe)."""

    def __init__(self, key: bytes, *, clock: Callable[[], float] = time.time) -> None:
        if not isinstance(key, bytes | bytearray) or len(key) != KEY_BYTES:
            raise ValueError(f"a MAVLink signing key is {KEY_BYTES} bytes")
        self._key = bytes(key)
        self._clock = clock
        self._lock = threading.Lock()
        self._timestamp = 0
        self._streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()
        self._peers: OrderedDict[tuple[int, int, int], int] = OrderedDict()  # see fresh()
        self.accepted = 0
        self.rejected: dict[Verdict, int] = {v: 0 for v in Verdict if v is not Verdict.OK}

    @property
    def key(self) -> bytes:
        """The secret key."""
        return self._key

    @property
    def timestamp(self) -> int:
        """The last timestamp used or seen (10 us ticks since 2015)."""
        with self._lock:
            return self._timestamp

    def floor(self) -> int:
        """The lowest timestamp our next signed packet may carry: strictly increasing per
        the spec, and never behind the wall clock or the newest valid one we saw."""
        with self._lock:
            return max(self._timestamp + 1, unix_to_ticks(self._clock()))

    def verify(self, packet: bytes | bytearray, src_system: int, src_component: int) -> Verdict:
        """Check one received packet (the full bytes, signature included)."""
        if not is_signed(packet) or len(packet) < 12 + SIGNATURE_LEN:
            return self._reject(Verdict.UNSIGNED)
        data = bytes(packet)
        expected = hashlib.sha256(self._key + data[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, data[-6:]):
            return self._reject(Verdict.BAD_SIGNATURE)
        link_id = data[-SIGNATURE_LEN]
        ts = int.from_bytes(data[-12:-6], "little")
        key = (link_id, src_system, src_component)
        with self._lock:
            last = self._streams.get(key)
            if last is not None:
                if ts <= last:
                    self.rejected[Verdict.REPLAY] += 1
                    return Verdict.REPLAY
                self._streams.move_to_end(key)
            else:
                ours = max(self._timestamp, unix_to_ticks(self._clock()))
                if ts + NEW_STREAM_WINDOW_S * TICKS_PER_SECOND < ours:
                    self.rejected[Verdict.STALE] += 1
                    return Verdict.STALE
            self._streams[key] = ts
            if len(self._streams) > _MAX_STREAMS:
                self._streams.popitem(last=False)
            # The spec: our next timestamp is at least the newest valid one we saw.
            self._timestamp = max(self._timestamp, ts)
            self.accepted += 1
        return Verdict.OK

    def fresh(self, packet: bytes | bytearray, src_system: int, src_component: int) -> bool:
        """A packet that may make its sender a peer (see the module docstring); no side
        effect on :meth:`verify`'s replay table."""
        if not is_signed(packet) or len(packet) < 12 + SIGNATURE_LEN:
            return False
        data = bytes(packet)
        if not hmac.compare_digest(hashlib.sha256(self._key + data[:-6]).digest()[:6], data[-6:]):
            return False
        ts = int.from_bytes(data[-12:-6], "little")
        key = (data[-SIGNATURE_LEN], src_system, src_component)
        with self._lock:
            last = self._peers.get(key)
            obeyed = self._streams.get(key)  # a packet obeyed before (a restart) is no news
            if obeyed is not None and ts <= obeyed:
                return False
            if last is None:
                ours = max(self._timestamp, unix_to_ticks(self._clock()))
                if ts + NEW_STREAM_WINDOW_S * TICKS_PER_SECOND < ours:
                    return False
            elif ts <= last:
                return False
            self._peers[key] = ts
            self._peers.move_to_end(key)
            if len(self._peers) > _MAX_STREAMS:
                self._peers.popitem(last=False)
        return True

    def snapshot(self) -> dict[str, Any]:
        """The replay table and our timestamp, JSON-ready (what survives a restart)."""
        with self._lock:
            return {
                "timestamp": self._timestamp,
                "streams": [[*k, ts] for k, ts in self._streams.items()],
            }

    def restore(self, doc: object) -> int:
        """Take back a :meth:`snapshot` (after a restart); returns the streams restored.

        Entries that are not four non-negative integers are ignored: a damaged
        document must not stop the bridge, and at worst forgets streams (which are
        then judged as new ones: no more than a minute old).
        """
        if not isinstance(doc, dict):
            return 0
        streams = doc.get("streams")
        n = 0
        with self._lock:
            ts0 = doc.get("timestamp")
            if isinstance(ts0, int) and not isinstance(ts0, bool) and ts0 >= 0:
                self._timestamp = max(self._timestamp, ts0)
            for entry in streams if isinstance(streams, list) else ():
                if (
                    isinstance(entry, list)
                    and len(entry) == 4
                    and all(
                        isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in entry
                    )
                ):
                    link_id, sysid, compid, ts = entry
                    key = (link_id, sysid, compid)
                    self._streams[key] = max(ts, self._streams.get(key, 0))
                    n += 1
            while len(self._streams) > _MAX_STREAMS:
                self._streams.popitem(last=False)
        return n

    def _reject(self, verdict: Verdict) -> Verdict:
        with self._lock:
            self.rejected[verdict] += 1
        return verdict


def sign_outgoing(mav: Any, signing: Signing, link_id: int) -> None:
    """Make pymavlink's ``mav`` sign what it packs with ``signing``'s key as ``link_id``."""
    mav.signing.secret_key = signing.key
    mav.signing.link_id = link_id & 0xFF
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = signing.floor()
