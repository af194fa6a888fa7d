"""The calibration store: one document, one format, one loader.

The calibration in use lives in ``<storage.dir>/calibration.json`` (a
:class:`~bridge.ports.DocumentStore` document, crash-safe)::

    {"calibration": Calibration.to_dict(),
     "source": "mag" | "accel" | "level" | "fixed_yaw" | "parameters" | "calibrate" | ...,
     "accepted_unix": 1732456789.1,
     "report": {...},                # the fit's report, when there was a fit
     "view": {"COMPASS_OFS_X": ...}} # the parameter values as a user set them (source
                                     # "parameters"): read back exactly as written

Every writer (the calibration controller on accept, the parameter store on a
PARAM_SET of the calibration group, ``compass-bridge calibrate`` offline) goes
through :meth:`CalibrationStore.save`; the daemon's start-up, the parameter
store and the status queries through :meth:`CalibrationStore.load`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from bridge.calibration.model import Calibration
from bridge.ports import DocumentStore, StorageError

log = logging.getLogger(__name__)

#: Name of the calibration document in the state directory.
CALIBRATION_DOCUMENT = "calibration"
#: ``source`` of the identity calibration used when nothing (usable) is stored.
NO_CALIBRATION = "none (identity)"


@dataclass(frozen=True, slots=True)
class StoredCalibration:
    """What the store holds: the calibration and what is known about it.

    ``source`` is where the calibration came from (``"none (identity)"`` when
    nothing usable is stored); ``origin`` which copy was read (``"current"``,
    ``"previous"`` -- the current copy was damaged --, or ``"none"``).
    """

    calibration: Calibration
    source: str
    origin: str = "none"
    accepted_unix: float | None = None
    report: Mapping[str, Any] | None = None
    view: Mapping[str, float] | None = None

    @property
    def stored(self) -> bool:
        """A stored calibration (not the identity fallback)."""
        return self.origin != "none"

    @property
    def description(self) -> str:
        """How the status line names it: ``stored``, ``stored (previous copy)``, or the fallback."""
        if not self.stored:
            return NO_CALIBRATION
        return "stored" if self.origin == "current" else "stored (previous copy)"


class CalibrationStore:
    """Loads and saves the calibration document (see the module docstring).

    ``documents`` None keeps nothing (a bridge without a state directory):
    loads give the identity, saves raise :class:`~bridge.ports.StorageError`.
    """

    def __init__(self, documents: DocumentStore | None) -> None:
        self.documents = documents

    def load(self) -> StoredCalibration:
        """The stored calibration, or the identity; never raises (a bad file is logged)."""
        if self.documents is None:
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        try:
            result = self.documents.load(CALIBRATION_DOCUMENT)
        except Exception as e:  # an unreadable directory must not stop the bridge
            log.warning("calibration: cannot read the state directory (%s); using identity", e)
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        for problem in result.problems:
            log.warning("calibration: %s", problem)
        doc: Any = result.payload
        if doc is None:
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        # The document, or (older files) the bare Calibration.to_dict().
        body = doc.get("calibration") if isinstance(doc.get("calibration"), dict) else doc
        try:
            cal = Calibration.from_dict(body)
        except (KeyError, TypeError, ValueError) as e:
            log.warning("calibration: stored document is unusable (%s); using identity", e)
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        source = doc.get("source")
        report = doc.get("report")
        view = doc.get("view")
        accepted = doc.get("accepted_unix", result.saved_at)
        return StoredCalibration(
            calibration=cal,
            source=source if isinstance(source, str) and source else "stored",
            origin=result.source,
            accepted_unix=float(accepted) if isinstance(accepted, int | float) else None,
            report=report if isinstance(report, dict) else None,
            view=_numbers(view),
        )

    def save(
        self,
        calibration: Calibration,
        *,
        source: str,
        accepted_unix: float,
        report: Mapping[str, Any] | None = None,
        view: Mapping[str, float] | None = None,
    ) -> None:
        """Replace the stored calibration; :class:`~bridge.ports.StorageError` if it cannot.

        A report that is not JSON (a fit's numpy leftovers) is dropped with a
        warning rather than losing the calibration itself.
        """
        if self.documents is None:
            raise StorageError("no state directory configured")
        payload: dict[str, Any] = {
            "calibration": calibration.to_dict(),
            "source": source,
            "accepted_unix": accepted_unix,
        }
        if view is not None:
            payload["view"] = dict(view)
        if report is not None:
            payload["report"] = dict(report)
        try:
            self.documents.save(CALIBRATION_DOCUMENT, payload)
        except (TypeError, ValueError) as e:
            if "report" not in payload:
                raise StorageError(f"calibration not storable: {e}") from e
            log.warning("calibration report not storable (%s); saved without it", e)
            del payload["report"]
            self.documents.save(CALIBRATION_DOCUMENT, payload)


def _numbers(v: object) -> dict[str, float] | None:
    if not isinstance(v, dict):
        return None
    out = {str(k): float(x) for k, x in v.items() if isinstance(x, int | float)}
    return out if len(out) == len(v) else None
