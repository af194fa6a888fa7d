"""The least a Python program does for the forwarder's output: ``versus``'s floor.

``python -m benchmarks.floor PORT --udp HOST:PORT``: :mod:`benchmarks.forwarder`
without pyserial and without ``mavutil``'s connection object -- one ``os.read`` per
wake-up on the raw pty, the forwarder's regex and formulas
(:func:`benchmarks.forwarder.attitude`), and one ATTITUDE packed by pymavlink and
sent on a connected UDP socket per frame. No program that reads the port, decodes
the frame and sends its ATTITUDE from Python can do less per frame, so its latency
is the floor of ``versus``'s harness on this machine (the pty's and the loopback's
wake-ups, the harness's own threads): ``python -m benchmarks versus --with-floor``
prints it beside the two programs compared.
"""

import argparse
import os
import socket
import time
import tty

from pymavlink.dialects.v20 import common

from benchmarks.forwarder import PGMRA, RATE_100, attitude


def main() -> None:
    ap = argparse.ArgumentParser(description="the floor: os.read -> ATTITUDE, nothing else")
    ap.add_argument("port")
    ap.add_argument("--udp", default="127.0.0.1:14550")
    args = ap.parse_args()
    fd = os.open(args.port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    os.write(fd, RATE_100)
    host, port = args.udp.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect((host, int(port)))
    mav = common.MAVLink(None, srcSystem=1)
    t0 = time.monotonic()
    buf = b""
    while True:
        buf += os.read(fd, 4096)
        *lines, buf = buf.split(b"\n")
        for line in lines:
            m = PGMRA.match(line)
            if m is None:
                continue
            roll, pitch, yaw = attitude(m.groups()[1:])
            ms = int(1000 * (time.monotonic() - t0))
            msg = common.MAVLink_attitude_message(ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
            sock.send(msg.pack(mav))


if __name__ == "__main__":
    main()
