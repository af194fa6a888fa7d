"""Raw byte-stream recordings of a compass link: format, writer, reader.

The recorder (a port tapped into a file: ``compass-bridge record``) is
:mod:`bridge.link.recorder`; this module knows files only, so the replay
transport can read them without a cycle.

A recording keeps exactly the bytes the device sent (and, optionally, what the
host wrote) with monotonic timestamps, so that a session can be replayed
through the same decoder later (:class:`bridge.link.transport.ReplayTransport`).

File format, version 1 (all integers little-endian)::

    header
      magic         8 bytes   b"CBREC\\r\\n\\x1a"  (PNG-style: CR/LF/^Z catch text-mode damage)
      version       u16       1
      header_len    u16       length of the fields that follow, up to the CRC
      start_wall    f64       time.time() when the recording started (UNIX seconds)
      baud          u32       the port's baud rate (0 when not a serial port)
      port_len      u16       length of the port name
      port          bytes     UTF-8 port name as given ("/dev/ttyUSB0", "sim", ...)
      header_crc    u32       CRC-32 of everything from magic to the end of port
    records, repeated
      kind          u8        0 = RX (device -> host), 1 = TX (host -> device); others reserved
      reserved      u8        0
      length        u16       1..65535 bytes of data
      t_ns          u64       monotonic nanoseconds since the recording started
      crc           u32       CRC-32 of the 12 bytes above followed by the data
      data          length bytes

Why this shape: a recording is written by a daemon that may lose power at any
moment. Every record carries its own CRC, so a reader stops cleanly at the
first record that is short (cut tail) or fails its CRC (a tail of unwritten,
zero-filled or stale blocks, as some filesystems leave after power loss) and
replays everything before it. A reader skips record kinds it does not know,
so later versions can add kinds (e.g. markers) without breaking old readers,
and ``header_len`` lets later versions append header fields.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import BinaryIO

from bridge.types import ClosedOnExit

MAGIC = b"CBREC\r\n\x1a"
VERSION = 1
MAX_CHUNK = 0xFFFF  #: largest data length of one record; longer writes are split

_PREFIX = struct.Struct("<8sHH")  # magic, version, header_len
_HEADER_FIXED = struct.Struct("<dIH")  # start_wall, baud, port_len
_CRC = struct.Struct("<I")
_RECORD = struct.Struct("<BBHQ")  # kind, reserved, length, t_ns
_RECORD_HEAD = _RECORD.size + _CRC.size
_MAX_PORT_NAME = 1024

log = logging.getLogger(__name__)


class RecordingFormatError(ValueError):
    """The file is not a recording this version can read (bad magic, version or header)."""


class Kind(IntEnum):
    """What a record holds."""

    RX = 0  #: bytes received from the device
    TX = 1  #: bytes the host wrote to the device


#: The kinds by their byte, for the reader's lookup of every record's kind: ``Kind(byte)``,
#: the enum's call, cost more than the record's other checks (a record a frame).
_KIND_BY_VALUE: dict[int, Kind] = {int(k): k for k in Kind}


@dataclass(frozen=True, slots=True)
class RecordingHeader:
    """The header of a recording."""

    version: int
    start_wall: float  #: UNIX time when the recording started
    port: str
    baud: int


@dataclass(frozen=True, slots=True)
class Chunk:
    """One record: ``t`` seconds after the recording started, ``kind`` and its bytes."""

    t: float
    kind: Kind
    data: bytes


def _encode_header(port: str, baud: int, start_wall: float) -> bytes:
    name = port.encode("utf-8")
    if len(name) > _MAX_PORT_NAME:
        raise ValueError(f"port name longer than {_MAX_PORT_NAME} bytes")
    if not 0 <= baud <= 0xFFFFFFFF:
        raise ValueError(f"baud out of range: {baud}")
    fields = _HEADER_FIXED.pack(start_wall, baud, len(name)) + name
    head = _PREFIX.pack(MAGIC, VERSION, len(fields)) + fields
    return head + _CRC.pack(zlib.crc32(head))


class RecordingWriter(ClosedOnExit):
    """Appends records to a new recording file.

    The writer does not read any clock: the caller passes each chunk's time
    (seconds since the recording started, from a monotonic clock). Each record
    is handed to the OS when written (:meth:`write` flushes), so at most the
    record being written is lost if the process dies; :meth:`sync` additionally
    forces it to the disk (the recorder does that about once a second).
    """

    def __init__(self, path: str | os.PathLike[str], port: str, baud: int, start_wall: float):
        self.path = Path(path)
        self.header = RecordingHeader(VERSION, start_wall, port, baud)
        header = _encode_header(port, baud, start_wall)
        # "xb": never silently overwrite an earlier recording.
        self._f: BinaryIO | None = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        self._f.write(header)
        self._f.flush()
        self.records = 0
        self.bytes = 0

    def write(self, t: float, data: bytes, kind: Kind = Kind.RX) -> None:
        """Append ``data`` seen ``t`` seconds after the start (split when over 64 KiB)."""
        if self._f is None:
            raise ValueError("recording is closed")
        if t < 0:
            raise ValueError(f"negative time offset {t}")
        t_ns = round(t * 1e9)
        parts = []
        for i in range(0, len(data), MAX_CHUNK):
            part = data[i : i + MAX_CHUNK]
            head = _RECORD.pack(int(kind), 0, len(part), t_ns)
            parts.append(head + _CRC.pack(zlib.crc32(part, zlib.crc32(head))) + part)
            self.records += 1
            self.bytes += len(part)
        self._f.write(b"".join(parts))
        self._f.flush()

    def sync(self) -> None:
        """Force what was written so far onto the disk."""
        if self._f is not None:
            self._f.flush()
            os.fsync(self._f.fileno())

    def close(self) -> None:
        """Sync and close (idempotent)."""
        if self._f is not None:
            try:
                self.sync()
            finally:
                self._f.close()
                self._f = None


class RecordingReader(ClosedOnExit):
    """Reads a recording lazily (a multi-hour file is never loaded whole).

    Opening checks the header and raises :class:`RecordingFormatError` when the
    file is not a readable recording. :meth:`chunks` yields the records in
    order and stops at the first short or corrupt one; afterwards
    :attr:`truncated` tells whether it stopped early and :attr:`good_bytes`
    how far the file was intact.
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        self._f: BinaryIO | None = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        try:
            self.header, self._data_start = self._read_header(self._f)
        except BaseException:
            self.close()
            raise
        self.truncated = False
        self.good_bytes = self._data_start

    @staticmethod
    def _read_header(f: BinaryIO) -> tuple[RecordingHeader, int]:
        prefix = f.read(_PREFIX.size)
        if len(prefix) < _PREFIX.size:
            raise RecordingFormatError("not a recording: file shorter than its header")
        magic, version, header_len = _PREFIX.unpack(prefix)
        if magic != MAGIC:
            raise RecordingFormatError(f"not a recording: bad magic {magic!r}")
        if version != VERSION:
            raise RecordingFormatError(f"unsupported recording version {version} (want {VERSION})")
        if header_len < _HEADER_FIXED.size:
            raise RecordingFormatError(f"header length {header_len} too short")
        fields = f.read(header_len)
        crc = f.read(_CRC.size)
        if len(fields) < header_len or len(crc) < _CRC.size:
            raise RecordingFormatError("recording header is truncated")
        if _CRC.unpack(crc)[0] != zlib.crc32(prefix + fields):
            raise RecordingFormatError("recording header fails its CRC")
        start_wall, baud, port_len = _HEADER_FIXED.unpack_from(fields)
        end = _HEADER_FIXED.size + port_len
        if end > header_len:
            raise RecordingFormatError("recording header: port name overruns the header")
        try:
            port = fields[_HEADER_FIXED.size : end].decode("utf-8")
        except UnicodeDecodeError as e:
            raise RecordingFormatError(f"recording header: port name is not UTF-8: {e}") from e
        return RecordingHeader(version, start_wall, port, baud), f.tell()

    def chunks(self, kinds: frozenset[Kind] | None = frozenset({Kind.RX})) -> Iterator[Chunk]:
        """Yield the records of the given kinds (default RX only; None for all), in order."""
        f = self._f
        if f is None:
            raise ValueError("recording is closed")
        f.seek(self._data_start)
        self.truncated = False
        self.good_bytes = self._data_start
        while True:
            head = f.read(_RECORD_HEAD)
            if not head:
                return  # clean end
            if len(head) < _RECORD_HEAD:
                break
            kind, _reserved, length, t_ns = _RECORD.unpack_from(head)
            (crc,) = _CRC.unpack_from(head, _RECORD.size)
            if length == 0:
                break  # the writer never writes empty records: this is a zero-filled tail
            data = f.read(length)
            if len(data) < length or zlib.crc32(data, zlib.crc32(head[: _RECORD.size])) != crc:
                break
            self.good_bytes += _RECORD_HEAD + length
            k = _KIND_BY_VALUE.get(kind)
            if k is None:
                continue  # a kind from a later version: skip it
            if kinds is None or k in kinds:
                yield Chunk(t_ns / 1e9, k, data)
        self.truncated = True
        log.warning(
            "recording %s is cut or damaged after byte %d; replaying up to there",
            self.path,
            self.good_bytes,
        )

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._f is not None:
            self._f.close()
            self._f = None
