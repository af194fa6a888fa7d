"""The optional compiled hot path, :mod:`bridge._speedups`: its functions, or ``None`` each.

``bridge/_speedups.c`` holds C twins of two pure-Python functions that run for every
frame: the ``$PGMRA`` fast-path decode (:mod:`bridge.protocol.gmr`) and the attitude
arithmetic (:class:`bridge.core.attitude.AttitudeEngine`). They give bit-identical
results (tests/test_speedups.py); they exist only because at 100 Hz the interpreter runs
each frame cold and the C versions cost a fraction of the CPU (README, "Speed and
footprint"). ``pip install`` builds the module when a C compiler is there and quietly
leaves it out when not; the Python twins then run.

Set ``COMPASS_BRIDGE_PURE_PYTHON=1`` in the environment to run the Python twins even
when the module is built (to rule it out when chasing a problem).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from types import ModuleType
from typing import Any, Literal

PURE_PYTHON_ENV = "COMPASS_BRIDGE_PURE_PYTHON"


def _load() -> ModuleType | None:
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        # By name: the module has no stub; the typed names below are its interface.
        return importlib.import_module("bridge._speedups")
    except ImportError:
        return None


_module = _load()

#: ``"c"`` when the compiled hot path is in use, ``"python"`` otherwise (status, bench).
IMPLEMENTATION = "c" if _module is not None else "python"

# The C functions, each None without the module (documented in bridge/_speedups.c).
bind_attitude_frame: Callable[[type, type, tuple[Any, ...], int], None] | None = (
    _module.bind_attitude_frame if _module is not None else None
)
decode_attitude_lines: Callable[[bytes], list[Any] | None] | None = (
    _module.decode_attitude_lines if _module is not None else None
)
#: What ``solve`` returns: AttitudeSolution's fields from roll to degraded, in order, then |g|.
SolveResult = tuple[
    float,  # roll
    float,  # pitch
    float,  # yaw
    float,  # heading_magnetic_deg
    float | None,  # heading_true_deg
    float | None,  # declination_deg
    Literal["magnetic", "true"],  # heading_reference
    tuple[float, float, float, float],  # quaternion
    tuple[float, float, float],  # mag_G
    tuple[float, float, float],  # accel_g
    float,  # field_strength_G
    float,  # dip_deg
    bool,  # degraded
    float,  # |g|
]
solve: Callable[..., SolveResult | None] | None = _module.solve if _module is not None else None
