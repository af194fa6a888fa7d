"""State storage adapter: calibration and parameters that are never lost.

Each document (``calibration``, ``params``, ...) is one JSON file in the state
directory, wrapped in an envelope that carries a schema name, a schema version
and a SHA-256 of the payload, so a truncated *or* bit-flipped file is detected,
not just an unparsable one.

A save is crash-safe at every instant (``kill -9`` or power loss)::

    1. write ``<name>.json.tmp``, fsync it
    2. hard-link the current ``<name>.json`` to ``<name>.json.prev.tmp`` and
       rename that over ``<name>.json.prev``   (the previous good copy)
    3. rename ``<name>.json.tmp`` over ``<name>.json``, fsync the directory

Between any two steps either ``<name>.json`` or ``<name>.json.prev`` holds a
complete, verified document, and :meth:`StateStore.load` falls back from the
first to the second. A failed save (read-only or full disk) raises
:class:`StorageError`; the caller keeps the new values in memory and reports.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from bridge.config import DEFAULT_STATE_DIR
from bridge.documents import LoadResult, StorageError
from bridge.files import FileMissing, FileRefused, read_regular_file

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_STATE_DIR",
    "DocumentError",
    "FileMissing",
    "FileRefused",
    "LoadResult",
    "StateStore",
    "StorageError",
    "read_regular_file",
    "resolve_state_dir",
]

SCHEMA_PREFIX = "compass-bridge/"


#: Upper bound of a stored document (calibration, parameters: a few kB in practice).
MAX_DOCUMENT_BYTES = 1 << 20


class DocumentError(StorageError, ValueError):
    """A document refused before anything was written (NaN, not JSON-able, bad name)."""


def resolve_state_dir(configured: str) -> Path:
    """The storage directory: the configured one, else $STATE_DIRECTORY (systemd), else the default.

    systemd may pass several colon-separated directories in $STATE_DIRECTORY;
    the first is ours.
    """
    if configured:
        return Path(configured)
    env = os.environ.get("STATE_DIRECTORY", "")
    if env:
        return Path(env.split(":")[0])
    return Path(DEFAULT_STATE_DIR)


def _digest(payload_text: str) -> str:
    return hashlib.sha256(payload_text.encode("utf-8")).hexdigest()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class StateStore:
    """Crash-safe JSON documents in one directory (see the module docstring)."""

    def __init__(self, directory: Path | str) -> None:
        self.directory = Path(directory)

    def _path(self, name: str) -> Path:
        if not name.isidentifier():
            raise DocumentError(f"bad document name {name!r}")
        return self.directory / f"{name}.json"

    def save(self, name: str, payload: dict[str, Any], version: int = 1) -> None:
        """Atomically replace document ``name``, keeping the previous good copy.

        Raises :class:`StorageError` for every failure, so a caller that catches
        it cannot be killed by another exception type: an OS error (read-only,
        full, missing dir) or a path the OS refuses (a NUL byte in the directory);
        :class:`DocumentError` (also a ValueError) for a payload that cannot be
        stored (NaN, not JSON-able) before anything is written. The files on disk
        are then unchanged or still loadable.
        """
        path = self._path(name)
        try:
            # Canonical text so the digest does not depend on dict order.
            payload_text = json.dumps(
                payload, sort_keys=True, separators=(",", ":"), allow_nan=False
            )
        except (TypeError, ValueError, RecursionError) as exc:
            raise DocumentError(f"cannot save {name}: {exc}") from exc
        try:
            self._write(name, path, payload_text, version)
        except OSError as exc:
            raise StorageError(
                f"cannot save {name} in {self.directory}: {exc.strerror or exc}"
            ) from exc
        except Exception as exc:  # e.g. ValueError("embedded null byte") from the OS layer
            where = repr(str(self.directory))  # repr: the path may hold the NUL at fault
            raise StorageError(f"cannot save {name} in {where}: {exc}") from exc

    def _write(self, name: str, path: Path, payload_text: str, version: int) -> None:
        envelope = {
            "schema": SCHEMA_PREFIX + name,
            "version": version,
            "saved_at": time.time(),
            "sha256": _digest(payload_text),
            "payload": json.loads(payload_text),
        }
        data = (json.dumps(envelope, sort_keys=True, indent=1) + "\n").encode("utf-8")
        tmp = path.with_name(path.name + ".tmp")
        prev = path.with_name(path.name + ".prev")
        prev_tmp = path.with_name(path.name + ".prev.tmp")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
            try:
                view = memoryview(data)
                while view:
                    n = os.write(fd, view)
                    view = view[n:]
                os.fsync(fd)
            finally:
                os.close(fd)
            if path.exists() and self._verify_file(path, name)[0] is not None:
                # Only a *good* current copy becomes the previous copy: a corrupt
                # current file must never overwrite the last good one.
                with contextlib.suppress(FileNotFoundError):
                    prev_tmp.unlink()
                os.link(path, prev_tmp)
                os.replace(prev_tmp, prev)
            os.replace(tmp, path)
            _fsync_dir(self.directory)
        except BaseException:
            with contextlib.suppress(OSError, ValueError):
                tmp.unlink()
            raise

    def _verify_file(
        self, path: Path, name: str
    ) -> tuple[dict[str, Any] | None, str, float | None]:
        try:
            # Bounded, never blocks: a FIFO or device planted here must not hang the start.
            raw = read_regular_file(path, MAX_DOCUMENT_BYTES)
        except FileMissing:
            return None, f"{path.name}: missing", None
        except FileRefused as exc:
            return None, f"{path.name}: unreadable ({exc})", None
        try:
            env = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            return None, f"{path.name}: truncated or not JSON", None
        if not isinstance(env, dict) or env.get("schema") != SCHEMA_PREFIX + name:
            return None, f"{path.name}: wrong schema", None
        payload = env.get("payload")
        if not isinstance(payload, dict):
            return None, f"{path.name}: no payload", None
        text = json.dumps(payload, sort_keys=True, separators=(",", ":"))
        if env.get("sha256") != _digest(text):
            return None, f"{path.name}: checksum mismatch (corrupt)", None
        saved_at = env.get("saved_at")
        return payload, "", float(saved_at) if isinstance(saved_at, int | float) else None

    def documents(self) -> list[Path]:
        """Every file of a document this store keeps (current, previous and leftover
        temporary copies), sorted; none when the directory does not exist."""
        try:
            entries = sorted(self.directory.iterdir())
        except (FileNotFoundError, NotADirectoryError):
            return []
        except OSError as exc:
            raise StorageError(f"cannot list {self.directory}: {exc.strerror or exc}") from exc
        out = []
        for p in entries:
            stem, dot, rest = p.name.partition(".json")
            if dot and stem.isidentifier() and rest in ("", ".prev", ".tmp", ".prev.tmp"):
                out.append(p)
        return out

    def clear(self) -> list[Path]:
        """Delete every document (see :meth:`documents`); returns the files removed.

        Only the store's own files go: anything else in the directory stays, and so
        does the directory. Raises :class:`StorageError` when a file cannot be removed.
        """
        removed = []
        for p in self.documents():
            try:
                p.unlink()
            except FileNotFoundError:
                continue
            except OSError as exc:
                raise StorageError(f"cannot remove {p}: {exc.strerror or exc}") from exc
            removed.append(p)
        return removed

    def load(self, name: str) -> LoadResult:
        """Load ``name``, falling back to the previous good copy; never raises for bad files."""
        path = self._path(name)
        problems: list[str] = []
        for source, candidate in (
            ("current", path),
            ("previous", path.with_name(path.name + ".prev")),
        ):
            payload, problem, saved_at = self._verify_file(candidate, name)
            if payload is not None:
                if source == "previous":
                    log.warning("%s: using the last good copy (%s)", name, "; ".join(problems))
                return LoadResult(payload, source, tuple(problems), saved_at)
            problems.append(problem)
        return LoadResult(None, "none", tuple(p for p in problems if not p.endswith("missing")))
