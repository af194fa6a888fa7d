"""Writing a host calibration into the compass flash (``PAR,GET`` / ``PAR,SET``).

The device's model ``H = K * (m - off)`` holds offsets and per-axis gains
(:func:`~bridge.calibration.fits.fixed_yaw.device_params_for`); the level reference it
keeps (Gxoff .. Gzoff) is read first and written back unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from bridge.calibration.fits.fixed_yaw import device_params_for
from bridge.calibration.model import Calibration
from bridge.calibration.sessions.base import Emit, device_error
from bridge.calibration.sessions.report import params_dict
from bridge.device import CommandError, CommandRejected
from bridge.protocol.gmr import CommandFrame, ParamsFrame

#: Runs one device command: (name, *args) -> the answer; raises ``CommandError``.
Command = Callable[..., Any]


def write_calibration(command: Command, cal: Calibration) -> Emit:
    """PAR,SET the magnetometer part of ``cal``; the event that says how it went
    (``calibration.device_updated`` or ``calibration.device_error``)."""
    try:
        wanted = device_params_for(cal.mag)
    except ValueError as e:
        return device_error(f"the compass cannot hold this calibration: {e}")
    try:
        current = command("PAR", "GET")
        if not isinstance(current, ParamsFrame):
            raise CommandError("PAR,GET gave no parameters")
        cmd = CommandFrame.par_set(wanted.with_level_reference(current))
        command(cmd.command, *cmd.args)
        after = command("PAR", "GET")
    except CommandRejected as e:
        why = "the compass is calibrating" if e.reason == "STATE" else e.reason
        return device_error(f"PAR,SET refused: {why}")
    except (CommandError, ValueError) as e:
        return device_error(f"PAR,SET failed: {e}")
    page = after if isinstance(after, ParamsFrame) else None
    data = {"params": params_dict(page), "written": wanted.to_dict()}
    return Emit("calibration.device_updated", "Compass flash updated", data=data)
