"""Reading the small files a configuration names: regular files only, bounded, never blocking.

The configuration file, the MAVLink signing key, zenoh's own configuration and
the state directory's documents are all read through :func:`read_regular_file`,
so that a typo naming ``/dev/urandom``, a FIFO, a directory or a huge file is
one clear error instead of a hang or unbounded memory.
"""

from __future__ import annotations

import os
import stat


class FileRefused(Exception):  # noqa: N818 - reads as "the file was refused"
    """:func:`read_regular_file` refused a path: the message says why (one line)."""


class FileMissing(FileRefused):
    """:func:`read_regular_file`: there is no file at the path."""


_FILE_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind(mode: int) -> str:
    for test, name in _FILE_KINDS:
        if test(mode):
            return name
    return "not a regular file"


def read_regular_file(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The content of a small regular file; :class:`FileRefused` for anything else.

    Every file the daemon reads because a configuration names it goes through here,
    so that a typo naming ``/dev/urandom``, a FIFO, a directory or a huge file is
    one clear error instead of a hang or unbounded memory. Never blocks: the path
    is checked with ``stat`` before it is opened (opening a device can have side
    effects: a serial port raises DTR), opened ``O_NONBLOCK`` (a FIFO swapped in
    meanwhile does not wait for a writer), checked again with ``fstat`` on the
    open descriptor, and read to at most ``max_bytes`` (a file that grows while it
    is read is refused too).
    """
    p = os.fspath(path)
    if "\0" in p:
        raise FileRefused("the path contains a NUL byte")
    try:
        st = os.stat(p)
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(f"{_kind(st.st_mode)}, not a regular file")
        flags = os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
        fd = os.open(p, flags)
    except FileNotFoundError:
        raise FileMissing("does not exist") from None
    except OSError as e:
        raise FileRefused(f"cannot read: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(f"{_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise FileRefused(f"{st.st_size} bytes, over the {max_bytes}-byte limit")
        chunks: list[bytes] = []
        total = 0
        while True:
            chunk = os.read(fd, min(1 << 16, max_bytes + 1 - total))
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:
                raise FileRefused(f"over the {max_bytes}-byte limit (it grew while read)")
    except OSError as e:
        raise FileRefused(f"cannot read: {e.strerror or e}") from None
    finally:
        os.close(fd)
