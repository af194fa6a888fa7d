"""What the state directory holds, in words an operator reads (console, ``config``, logs).

The bridge keeps two documents there (``calibration.json``, ``params.json``;
see :mod:`bridge.app.calibration.store` and :mod:`bridge.app.params`); these read
them through the :class:`~bridge.documents.DocumentStore` port without changing
anything, for the lines that say what a run will start from.
"""

from __future__ import annotations

import os
import time
from typing import Any

from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMS_DOCUMENT
from bridge.documents import DocumentStore


def home_relative(path: object) -> str:
    """``path`` with the user's home directory written ``~`` (as a person types it)."""
    text = str(path)
    home = os.path.expanduser("~")
    if home not in ("", "/", "~") and (text == home or text.startswith(home + os.sep)):
        return "~" + text[len(home) :]
    return text


def value_text(v: object) -> str:
    """A stored parameter value as a ground station shows it (1, 0.2)."""
    return f"{v:g}" if isinstance(v, int | float) and not isinstance(v, bool) else repr(v)


def stored_parameters(documents: DocumentStore) -> dict[str, Any]:
    """The parameter values users set and the bridge stored (``params.json``), by name.

    Raises what the store raises for an unreadable directory (a bad file reads as none).
    """
    doc = documents.load(PARAMS_DOCUMENT).payload
    stored = doc.get("set") if isinstance(doc, dict) else None
    return dict(stored) if isinstance(stored, dict) else {}


def calibration_summary(documents: DocumentStore) -> str:
    """The stored calibration in a few words ("" when none is stored)."""
    stored = CalibrationStore(documents).load()
    if not stored.stored:
        return ""
    when = ""
    if stored.accepted_unix is not None:
        when = time.strftime(", %Y-%m-%d %H:%M", time.localtime(stored.accepted_unix))
    return f"a calibration ({stored.source}{when})"


def state_summary(documents: DocumentStore) -> str:
    """What the state directory holds ("nothing yet", "a calibration (mag, 2026-11-26
    10:12) and BRG_HDG_REF = 1"); never raises (an unreadable directory says so)."""
    try:
        held = [calibration_summary(documents)]
        params = stored_parameters(documents)
    except Exception as e:
        return f"nothing readable ({e})"
    if params:
        held.append(", ".join(f"{k} = {value_text(v)}" for k, v in sorted(params.items())))
    held = [h for h in held if h]
    return " and ".join(held) if held else "nothing yet"


__all__ = [
    "calibration_summary",
    "home_relative",
    "state_summary",
    "stored_parameters",
    "value_text",
]
