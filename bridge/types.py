"""The type aliases and the small vocabularies the whole package shares, each defined once.

The bottom layer: it imports nothing of the package, and not numpy either at run
time -- the array aliases are written as strings that type checkers resolve, so
the command line answers ``--version`` and usage errors without loading numpy.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Literal, Self, TypeAlias

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

#: numpy arrays of one element type (any shape: (3,), (N, 3), (3, 3) ...).
FloatArray: TypeAlias = "npt.NDArray[np.float64]"
IntArray: TypeAlias = "npt.NDArray[np.int64]"
BoolArray: TypeAlias = "npt.NDArray[np.bool_]"

#: A 3-vector and a 3x3 matrix as plain floats (frozen dataclasses, the per-frame path).
Vec3: TypeAlias = tuple[float, float, float]
Mat3: TypeAlias = tuple[Vec3, Vec3, Vec3]

#: A monotonic clock in seconds (``time.monotonic``, or a test's fake).
Clock: TypeAlias = Callable[[], float]

#: The north a published heading is measured from: magnetic (as the compass and ArduPilot's
#: compass driver report) or true (magnetic + the WMM declination at the configured location).
HeadingReference: TypeAlias = Literal["magnetic", "true"]
HEADING_REFERENCES: tuple[HeadingReference, ...] = ("magnetic", "true")

#: What the drift monitor does with the calibration in use (``[calibration] learn``; the
#: parameter BRG_CAL_LEARN is the index): nothing, detect drift and warn, also learn offsets.
LEARN_MODES: tuple[str, ...] = ("off", "detect", "learn")


class ClosedOnExit:
    """A ``with`` block closes the object on the way out: ``__enter__`` hands the object
    itself, ``__exit__`` calls its :meth:`close` (which the class defines)."""

    __slots__ = ()

    def close(self) -> None:
        """Release what the object holds (idempotent in the classes that use this)."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
