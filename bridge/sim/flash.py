"""The simulated device's flash page: nine calibration parameters and the MAGOK/ACCOK flags.

Factory content is the datasheet's: Xoff = Yoff = Zoff = 2458, Kx = Ky = Kz = 1,
Gxoff = Gyoff = 2458, Gzoff = 2949.5, MAGOK and ACCOK clear.

Persistence (when a path is given) is a small JSON file with a CRC-32 of its
content. The device's page is double-buffered: a write cut by power loss leaves
the previous content. We emulate that with two files written one after the
other, each atomically (temp file in the same directory, fsync, rename, fsync of
the directory):

1. ``<file>.prev`` <- the content in use now (known good, it is in memory);
2. ``<file>``      <- the new content.

A crash at any point leaves ``<file>`` old or new and never half-written; a
``<file>`` that is missing, truncated or corrupt anyway (CRC mismatch, bad
value) is replaced on load by ``<file>.prev``, then by factory content. Loading
never raises; :attr:`Flash.load_source` and :attr:`Flash.load_error` say what
happened.

FLASHERR ("the last flash write failed verification") is RAM state of the
firmware, so it lives here but is not persisted: a failed write sets it and
keeps the previous content, the next good write clears it, and a power cycle
(:meth:`Flash.power_cycle`) forgets it. An OSError while saving is a failed
write too: the device would not crash on a bad flash cell either.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.files import FileMissing, FileRefused, read_regular_file
from bridge.protocol.gmr import ParamsFrame

FORMAT = "gmr-flash/1"
#: A flash file is a few hundred bytes; anything over this is not one (and is not read).
FLASH_FILE_MAX_BYTES = 64 * 1024
_PARAM_NAMES = ("xoff", "yoff", "zoff", "kx", "ky", "kz", "gxoff", "gyoff", "gzoff")


@dataclass(frozen=True, slots=True)
class FlashPage:
    """The flash content: the nine parameters as the firmware uses them, and two flags."""

    xoff: float = 2458.0
    yoff: float = 2458.0
    zoff: float = 2458.0
    kx: float = 1.0
    ky: float = 1.0
    kz: float = 1.0
    gxoff: float = 2458.0
    gyoff: float = 2458.0
    gzoff: float = 2949.5
    magok: bool = False
    accok: bool = False

    def __post_init__(self) -> None:
        # Validate exactly like the codec validates $PGMRP, so any page can be reported.
        self.params()
        for name in ("magok", "accok"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool")

    @classmethod
    def factory(cls) -> FlashPage:
        """The datasheet's factory state."""
        return cls()

    def params(self) -> ParamsFrame:
        """The nine values as a ``$PGMRP`` frame (ValueError if one is out of range)."""
        return ParamsFrame(*(getattr(self, n) for n in _PARAM_NAMES))

    def with_params(self, params: ParamsFrame, **flags: bool) -> FlashPage:
        """A copy holding ``params`` (and any of ``magok``/``accok`` given)."""
        values: dict[str, Any] = dict(zip(_PARAM_NAMES, params.values(), strict=True))
        return dataclasses.replace(self, **values, **flags)

    def to_dict(self) -> dict[str, Any]:
        """The payload (without format and CRC)."""
        return {n: getattr(self, n) for n in (*_PARAM_NAMES, "magok", "accok")}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FlashPage:
        """Inverse of :meth:`to_dict`; ValueError/TypeError/KeyError on bad content."""
        values: dict[str, Any] = {}
        for n in _PARAM_NAMES:
            v = d[n]
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{n} is not a finite number: {v!r}")
            values[n] = float(v)
        return cls(**values, magok=d["magok"], accok=d["accok"])


def _crc(payload: dict[str, Any]) -> int:
    return zlib.crc32(json.dumps(payload, sort_keys=True).encode())


def _encode(page: FlashPage) -> bytes:
    payload = page.to_dict()
    doc = {"format": FORMAT, "page": payload, "crc32": _crc(payload)}
    return (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode()


def _decode(data: bytes) -> FlashPage:
    doc = json.loads(data.decode("utf-8"))
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"not a {FORMAT} file")
    payload = doc["page"]
    if not isinstance(payload, dict) or doc.get("crc32") != _crc(payload):
        raise ValueError("CRC mismatch")
    return FlashPage.from_dict(payload)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data``: temp file beside it, fsync, rename, fsync the directory."""
    directory = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(directory)


class Flash:
    """The device's flash page, in memory or backed by ``path``.

    :meth:`write` is the firmware's "program and verify": it returns False (and
    sets :attr:`flasherr`) when the write fails, leaving the previous content.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None) -> None:
        self.path: Path | None = None if path is None else Path(path)
        self.flasherr = False
        self.writes = 0  #: successful writes (for tests and benchmarks)
        self.failed_writes = 0
        self._fail_next = 0
        self.load_source = "factory"  #: "file", "prev" or "factory"
        self.load_error: str | None = None
        self._page = self._load()

    @property
    def prev_path(self) -> Path | None:
        """The previous-content buffer beside :attr:`path`."""
        return None if self.path is None else self.path.with_name(self.path.name + ".prev")

    @property
    def page(self) -> FlashPage:
        """The content in use."""
        return self._page

    def _load(self) -> FlashPage:
        if self.path is None or self.prev_path is None:
            return FlashPage.factory()
        errors: list[str] = []
        for source, p in (("file", self.path), ("prev", self.prev_path)):
            try:
                # a regular file of bounded size: `--flash /dev/zero` is an error, not a hang
                page = _decode(read_regular_file(p, FLASH_FILE_MAX_BYTES))
            except FileMissing:
                errors.append(f"{p.name}: missing")
                continue
            except FileRefused as e:
                errors.append(f"{p.name}: {e}")
                continue
            except (ValueError, TypeError, KeyError, UnicodeDecodeError) as e:
                errors.append(f"{p.name}: {type(e).__name__}: {e}")
                continue
            self.load_source = source
            self.load_error = "; ".join(errors) or None
            return page
        self.load_source = "factory"
        # a fresh unit has no file at all: that is not an error worth reporting
        first_use = all(e.endswith(": missing") for e in errors)
        self.load_error = None if first_use else "; ".join(errors)
        return FlashPage.factory()

    def fail_next_write(self, n: int = 1) -> None:
        """Make the next ``n`` writes fail verification (FLASHERR, ``ERR,FLASH``)."""
        self._fail_next += max(0, int(n))

    def write(self, page: FlashPage) -> bool:
        """Program ``page``; True on success. A failure keeps the previous content."""
        if self._fail_next > 0:
            self._fail_next -= 1
            return self._failed()
        if self.path is not None and self.prev_path is not None:
            try:
                atomic_write(self.prev_path, _encode(self._page))
                atomic_write(self.path, _encode(page))
            except OSError:
                return self._failed()
        self._page = page
        self.flasherr = False
        self.writes += 1
        return True

    def _failed(self) -> bool:
        self.flasherr = True
        self.failed_writes += 1
        return False

    def power_cycle(self) -> None:
        """Power loss and back: RAM state (FLASHERR) is lost, content re-read from the file."""
        self.flasherr = False
        if self.path is not None:  # in memory, the content simply survives
            self._page = self._load()
