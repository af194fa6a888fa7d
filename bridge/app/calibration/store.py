"""The calibration store: one document, one format, one loader.

The calibration in use lives in ``<storage.dir>/calibration.json`` (a
:class:`~bridge.documents.DocumentStore` document, crash-safe)::

    {"calibration": Calibration.to_dict(),
     "source": "mag" | "accel" | "level" | "fixed_yaw" | "parameters" | "calibrate" | ...,
     "accepted_unix": 1732456789.1,
     "report": {...},                # the fit's report, when there was a fit
     "view": {"COMPASS_OFS_X": ...}, # the parameter values as a user set them (source
                                     # "parameters"): read back exactly as written
     "replaced": {"calibration": ..., "source": ..., "accepted_unix": ..., "report": ...,
                  "view": ...}}      # the calibration this one replaced, for an undo

``replaced`` is the calibration in use before the last change -- except that a
learned calibration replacing another learned one (online learning moves the
offsets in several steps, source ``"learned"``) keeps the replaced copy of the
first step: an undo goes back to where learning started, not one step.

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

from bridge.core.calibration import Calibration
from bridge.documents import DocumentStore, StorageError

log = logging.getLogger(__name__)

#: Name of the calibration document in the state directory.
CALIBRATION_DOCUMENT = "calibration"
#: ``source`` of the identity calibration used when nothing (usable) is stored.
NO_CALIBRATION = "none (identity)"
#: ``source`` of a calibration learned online (bridge.app.calibration.drift): steps of it share one undo.
LEARNED_SOURCE = "learned"


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
    loads give the identity, saves raise :class:`~bridge.documents.StorageError`.
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
        if not isinstance(doc, dict):
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        stored = _stored(doc, result.source, result.saved_at)
        if stored is None:
            return StoredCalibration(Calibration(), NO_CALIBRATION)
        return stored

    def replaced(self) -> StoredCalibration | None:
        """The calibration the stored one replaced (see the module docstring), or None.

        Its ``origin`` is ``"replaced"``; never raises (a damaged copy is None).
        """
        doc = self._document()
        prev = doc.get("replaced") if doc is not None else None
        return _stored(prev, "replaced", None) if isinstance(prev, dict) else None

    def _document(self) -> dict[str, Any] | None:
        if self.documents is None:
            return None
        try:
            payload: Any = self.documents.load(CALIBRATION_DOCUMENT).payload
        except Exception:  # an unreadable directory: nothing to keep or to go back to
            return None
        return payload if isinstance(payload, dict) else None

    def save(
        self,
        calibration: Calibration,
        *,
        source: str,
        accepted_unix: float,
        report: Mapping[str, Any] | None = None,
        view: Mapping[str, float] | None = None,
    ) -> None:
        """Replace the stored calibration; :class:`~bridge.documents.StorageError` if it cannot.

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
        replaced = self._to_keep(source)
        if replaced is not None:
            payload["replaced"] = replaced
        try:
            self.documents.save(CALIBRATION_DOCUMENT, payload)
        except (TypeError, ValueError) as e:
            if "report" not in payload:
                raise StorageError(f"calibration not storable: {e}") from e
            log.warning("calibration report not storable (%s); saved without it", e)
            del payload["report"]
            self.documents.save(CALIBRATION_DOCUMENT, payload)

    def _to_keep(self, source: str) -> dict[str, Any] | None:
        """What a new calibration from ``source`` keeps as ``replaced``."""
        doc = self._document()
        if doc is None or _stored(doc, "current", None) is None:
            return None
        if source == LEARNED_SOURCE and doc.get("source") == LEARNED_SOURCE:
            prev = doc.get("replaced")  # a further learned step: the undo stays where it was
            return prev if isinstance(prev, dict) else None
        return {k: v for k, v in doc.items() if k != "replaced"}


def _stored(doc: Any, origin: str, saved_at: float | None) -> StoredCalibration | None:
    """A stored calibration from its document (None when it is unusable)."""
    if not isinstance(doc, dict):
        return None
    # The document, or (older files) the bare Calibration.to_dict().
    inner = doc.get("calibration")
    body: dict[str, Any] = inner if isinstance(inner, dict) else doc
    try:
        cal = Calibration.from_dict(body)
    except (KeyError, TypeError, ValueError) as e:
        log.warning("calibration: stored document is unusable (%s); using identity", e)
        return None
    source = doc.get("source")
    report = doc.get("report")
    accepted = doc.get("accepted_unix", saved_at)
    return StoredCalibration(
        calibration=cal,
        source=source if isinstance(source, str) and source else "stored",
        origin=origin,
        accepted_unix=float(accepted) if isinstance(accepted, int | float) else None,
        report=report if isinstance(report, dict) else None,
        view=_numbers(doc.get("view")),
    )


def _numbers(v: object) -> dict[str, float] | None:
    if not isinstance(v, dict):
        return None
    out = {str(k): float(x) for k, x in v.items() if isinstance(x, int | float)}
    return out if len(out) == len(v) else None
