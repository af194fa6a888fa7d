"""Writing a host calibration into the compass flash (``PAR,GET`` / ``PAR,SET``).

The device's model ``H = K * (m - off)`` holds offsets and per-axis gains
(:meth:`~bridge.core.calibration.Calibration.device_page`); the level reference it
keeps (Gxoff .. Gzoff) is read first and written back unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from bridge.calibration.sessions.base import Emit, device_error
from bridge.calibration.sessions.report import MAG_PARAM_NAMES, params_dict
from bridge.core.calibration import Calibration
from bridge.protocol.device import CommandError, CommandRejected
from bridge.protocol.gmr import CommandFrame, ParamsFrame

#: Runs one device command: (name, *args) -> the answer; raises ``CommandError``.
Command = Callable[..., Any]


def write_calibration(command: Command, cal: Calibration) -> Emit:
    """PAR,SET the magnetometer part of ``cal``; the event that says how it went
    (``calibration.device_updated`` or ``calibration.device_error``)."""
    try:
        cal.device_page()  # before any command: a calibration the flash cannot hold sends none
    except ValueError as e:
        return device_error(f"the compass cannot hold this calibration: {e}")
    try:
        current = command("PAR", "GET")
        if not isinstance(current, ParamsFrame):
            raise CommandError("PAR,GET gave no parameters")
        wanted = cal.device_page(current)
        cmd = CommandFrame.par_set(wanted)
        command(cmd.command, *cmd.args)
        after = command("PAR", "GET")
    except CommandRejected as e:
        why = "the compass is calibrating" if e.reason == "STATE" else e.reason
        return device_error(f"PAR,SET refused: {why}")
    except (CommandError, ValueError) as e:
        return device_error(f"PAR,SET failed: {e}")
    page = after if isinstance(after, ParamsFrame) else None
    written = params_dict(wanted) or {}
    data = {"params": params_dict(page), "written": {k: written[k] for k in MAG_PARAM_NAMES}}
    return Emit("calibration.device_updated", "Compass flash updated", data=data)
