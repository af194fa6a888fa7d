"""``compass-bridge`` with a serial port that can wedge: a test's stand-in for a hung driver.

Run as ``python tests/hanging_reader.py [compass-bridge arguments]``. After SIGUSR2 the
next read of the compass port blocks until the port is closed, as a wedged USB-serial
driver would; everything else is the real daemon. The hook lives here, in the tests, so
the installed package carries none.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from typing import Any

from bridge import cli
from bridge.daemon import runner

log = logging.getLogger("hanging_reader")


class HangingTransport:
    """Passes everything through; after :func:`arm` the next ``read`` blocks until ``close``."""

    armed = threading.Event()

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self._released = threading.Event()

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._inner, attr)

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if HangingTransport.armed.is_set():
            HangingTransport.armed.clear()
            log.warning("test hook: the serial reader hangs now")
            self._released.wait()
        data: bytes = self._inner.read(max_bytes, timeout)
        return data

    def close(self) -> None:
        self._released.set()
        self._inner.close()


def main() -> int:
    real = runner.make_transport
    runner.make_transport = lambda cfg, simulator=None: HangingTransport(real(cfg, simulator))
    signal.signal(signal.SIGUSR2, lambda *_: HangingTransport.armed.set())
    return cli.main(sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
