"""The program an integrator would write instead of the bridge (the benchmarks' yardstick).

``python -m benchmarks.forwarder PORT [--udp HOST:PORT] [--baud N]``: pyserial reads the
compass line by line, a regex takes the ``$PGMRA`` fields, the datasheet's tilt
compensation (../shared/gmr-compass-protocol.md: nominal zero, no calibration) gives
the heading, pymavlink's ``mavutil`` ``udpout`` sends one ATTITUDE per frame. It asks
the compass for 100 Hz first. ``python -m benchmarks versus`` runs it beside the bridge.
"""

import argparse
import math
import re
import time

import serial
from pymavlink import mavutil

PGMRA = re.compile(rb"\$PGMRA,(\d+),[-\d.]+,[-\d.]+,[-\d.]+,(\d+),(\d+),(\d+),(\d+),(\d+),(\d+),")
ZERO = 2458.0  # counts at 0 G / 0 g (the datasheet's nominal transfer)


def main() -> None:
    ap = argparse.ArgumentParser(description="naive $PGMRA -> MAVLink ATTITUDE forwarder")
    ap.add_argument("port")
    ap.add_argument("--udp", default="127.0.0.1:14550")
    ap.add_argument("--baud", type=int, default=115200)
    args = ap.parse_args()
    ser = serial.Serial(args.port, args.baud, timeout=1.0)
    ser.write(RATE_100)
    mav = mavutil.mavlink_connection(f"udpout:{args.udp}", source_system=1)
    t0 = time.monotonic()
    while True:
        m = PGMRA.match(ser.readline())
        if m is None:
            continue
        roll, pitch, yaw = attitude(m.groups()[1:])
        ms = int(1000 * (time.monotonic() - t0))
        mav.mav.attitude_send(ms, roll, pitch, yaw, 0.0, 0.0, 0.0)


def attitude(counts: tuple[bytes, ...]) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) from the six count fields, the datasheet's tilt compensation."""
    mx, my, mz, ax, ay, az = (float(v) - ZERO for v in counts)
    pitch = -math.asin(max(-1.0, min(1.0, ax / math.sqrt(ax * ax + ay * ay + az * az))))
    roll = math.atan2(ay, az)
    x = mx * math.cos(pitch) + my * math.sin(pitch) * math.sin(roll)
    x += mz * math.sin(pitch) * math.cos(roll)
    y = my * math.cos(roll) - mz * math.sin(roll)
    return roll, pitch, math.atan2(-y, x)


def _checksum(body: bytes) -> int:
    cs = 0
    for b in body:
        cs ^= b
    return cs


RATE_100 = b"$PGMRQ,RATE,100*%02X\r\n" % _checksum(b"PGMRQ,RATE,100")


if __name__ == "__main__":
    main()
