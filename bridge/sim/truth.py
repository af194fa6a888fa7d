"""What the simulated unit's heading really was when a frame was sampled.

A simulator knows what no real compass knows: the attitude each frame was
sampled at (:attr:`~bridge.sim.firmware.Firmware.truth`). The console line of
``run --simulate`` shows it beside the bridge's heading, so a newcomer sees how
far the heading is from the truth before and after a calibration.

Thread use: the firmware appends to its truth log in the link's reader thread;
:func:`truth_heading_deg` reads it from another (the console's) by index only,
never by iterating the deque, so an append meanwhile cannot raise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from bridge.core.geometry import dcm_to_euler, wrap_degrees_360

if TYPE_CHECKING:
    from bridge.sim.firmware import Firmware

#: How many of the newest frames are searched for a sequence number.
SEARCH_FRAMES = 64


def declination_deg(field_ned_G: Any) -> float:
    """The declination of a NED field vector (degrees, east positive)."""
    return math.degrees(math.atan2(float(field_ned_G[1]), float(field_ned_G[0])))


def truth_heading_deg(firmware: Firmware, seq: int | None, reference: str) -> float | None:
    """The true (``reference == "true"``) or magnetic heading of frame ``seq`` as simulated.

    None when the frame is no longer in the firmware's truth log. The magnetic
    heading is the true yaw less the declination of the simulated field.
    """
    log = firmware.truth
    if seq is None:
        return None
    for back in range(1, SEARCH_FRAMES + 1):
        try:
            entry = log[-back]
        except IndexError:
            return None
        if entry.frame.seq == seq:
            yaw = math.degrees(dcm_to_euler(entry.R)[2])
            if reference != "true":
                yaw -= declination_deg(firmware.sensor.field_ned_G)
            return wrap_degrees_360(yaw)
    return None


__all__ = ["declination_deg", "truth_heading_deg"]
