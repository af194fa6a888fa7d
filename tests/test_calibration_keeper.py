"""The calibration in use, kept: a calibration set value by value (COMPASS_* PARAM_SETs) is
saved as params.json is -- at once, or within a second of the last save -- and one that
storage refused is saved when it takes it again. In memory: a document store in a dict
and the times handed in."""

from __future__ import annotations

from typing import Any

import numpy as np

from bridge.app.calibration.keeper import PACE_S, RETRY_S, CalibrationKeeper, applied
from bridge.app.calibration.store import CALIBRATION_DOCUMENT, CalibrationStore
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.documents import LoadResult, StorageError


class Documents:
    """Named documents in a dict; each save counted; ``full`` refuses them."""

    def __init__(self) -> None:
        self.docs: dict[str, dict[str, Any]] = {}
        self.saves = 0
        self.full = False

    def save(self, name: str, payload: dict[str, Any], version: int = 1) -> None:
        if self.full:
            raise StorageError("no space left on device")
        self.saves += 1
        self.docs[name] = payload

    def load(self, name: str) -> LoadResult:
        doc = self.docs.get(name)
        return LoadResult(doc, "current" if doc is not None else "none")


def offsets(x: float) -> Calibration:
    return Calibration(mag=AffineCalibration.from_arrays((x, 0.0, 0.0), np.eye(3)))


def stored_x(docs: Documents) -> float:
    return float(docs.docs[CALIBRATION_DOCUMENT]["calibration"]["mag"]["offset"][0])


def keep(k: CalibrationKeeper, x: float, now: float, paced: bool = True) -> str:
    return k.keep(
        offsets(x), source="parameters", accepted_unix=1e9, report=None, view=None,
        now=now, paced=paced,
    )  # fmt: skip


def test_values_set_in_a_storm_are_saved_once_a_second_the_last_of_them_included() -> None:
    docs = Documents()
    k = CalibrationKeeper(CalibrationStore(docs))
    assert keep(k, 0.01, now=10.0) == "" and k.saved and docs.saves == 1  # the first: at once
    for i in range(1, 200):  # 200 sets within the second: pending, not written
        assert keep(k, 0.01 + i * 1e-4, now=10.0 + i * 1e-3) == ""
    assert docs.saves == 1 and k.pending and k.paced and not k.saved
    assert k.retry_due(10.5) == 10.0 + PACE_S
    assert not k.retry(10.5) and docs.saves == 1  # not due yet
    assert not k.retry(10.0 + PACE_S)  # due: saved (False: not storage coming back)
    assert docs.saves == 2 and k.saved and not k.pending and not k.paced
    assert stored_x(docs) == 0.01 + 199 * 1e-4  # the last value set
    assert keep(k, 0.05, now=12.0) == "" and docs.saves == 3  # a second after: at once


def test_a_calibration_not_set_value_by_value_is_saved_at_once_in_the_pending_ones_place() -> None:
    docs = Documents()
    k = CalibrationKeeper(CalibrationStore(docs))
    keep(k, 0.01, now=10.0)
    keep(k, 0.02, now=10.1)
    assert k.paced and docs.saves == 1
    assert keep(k, 0.03, now=10.2, paced=False) == ""  # PREFLIGHT_STORAGE, an accepted fit ...
    assert docs.saves == 2 and stored_x(docs) == 0.03 and not k.pending
    assert not k.retry(20.0) and docs.saves == 2  # nothing left to save


def test_the_bridge_stopping_saves_the_paced_one_at_once() -> None:
    docs = Documents()
    k = CalibrationKeeper(CalibrationStore(docs))
    keep(k, 0.01, now=10.0)
    keep(k, 0.02, now=10.1)
    k.flush(now=10.2)
    assert docs.saves == 2 and stored_x(docs) == 0.02 and k.saved
    k.flush(now=10.3)  # nothing pending: nothing written
    assert docs.saves == 2


def test_a_paced_save_that_storage_refuses_is_retried_and_told_when_it_comes_back() -> None:
    docs = Documents()
    k = CalibrationKeeper(CalibrationStore(docs))
    keep(k, 0.01, now=10.0)
    keep(k, 0.02, now=10.1)
    docs.full = True
    assert not k.retry(11.0)  # the paced save fails: now a refused one, retried later
    assert k.pending and not k.paced and k.error and k.retry_due(11.0) == 11.0 + RETRY_S
    assert keep(k, 0.03, now=11.5) == "no space left on device"  # failing: tried at once
    docs.full = False
    assert k.retry(11.5 + RETRY_S)  # storage took it again: True, told as such
    assert stored_x(docs) == 0.03 and k.saved


def test_what_a_calibration_applied_says() -> None:
    events, said = applied("parameters", "", True, stored=True)
    assert said == "calibration applied (saved within a second)"
    assert [e.kind for e in events] == ["calibration.accepted"]
    assert events[0].data == {"source": "parameters", "saved": False, "paced": True}
    events, said = applied("storage", "", False, stored=True)
    assert said == "calibration applied and saved" and events[0].data["saved"] is True
    events, said = applied("parameters", "disk full", False, stored=True)
    assert said == "calibration applied but not saved: disk full"
    assert [e.kind for e in events] == ["calibration.accepted", "calibration.storage_error"]
    events, _ = applied("parameters", "no state directory configured", False, stored=False)
    assert [e.kind for e in events] == ["calibration.accepted"]


def test_the_status_line_tells_a_paced_save_from_a_refused_one() -> None:
    """ "saving" while a save waits only for its pace; "NOT SAVED (storage error)" only when
    storage refused it; nothing for a calibration never ours to save (the status line said
    "NOT SAVED (storage error)" for all three)."""
    from bridge.calibration.sessions.snapshot import CalibratorSnapshot
    from bridge.systemd.status import calibration_words

    def words(
        saved: bool,
        saving: bool = False,
        error: str = "",
        source: str = "parameters",
        calibrated: bool | None = True,
        parameters_error: str = "",
    ) -> str:
        snap = CalibratorSnapshot.of(
            None,
            onboard=False,
            calibration_source=source,
            calibration_age_s=None,
            calibration_saved=saved,
            calibration_saving=saving,
            calibration_save_error=error,
        )
        return calibration_words(snap, calibrated=calibrated, parameters_error=parameters_error)

    assert words(True) == "parameters"
    assert words(False, saving=True) == "parameters, saving"
    assert words(False, error="disk full") == "parameters, NOT SAVED (storage error)"
    simulator = "simulator (the unit's true errors)"
    assert words(False, source=simulator) == simulator  # never saved, never refused
    assert words(False, source="none (identity)", calibrated=False) == (
        "none (identity), UNCALIBRATED"
    )
    assert words(True, parameters_error="disk full") == "parameters; parameters NOT SAVED"


def test_what_a_keeper_says_of_its_calibration_follows_its_saves() -> None:
    """The keeper's own state behind those words: refused (error, retried), waiting for its
    pace (paced, no error), saved (neither)."""
    docs = Documents()
    k = CalibrationKeeper(CalibrationStore(docs))
    assert not k.saved and not k.paced and k.error == ""  # nothing kept yet: nothing refused
    keep(k, 0.01, now=10.0)
    keep(k, 0.02, now=10.1)
    assert not k.saved and k.paced and k.error == ""
    docs.full = True
    k.retry(11.0)
    assert not k.saved and not k.paced and k.error == "no space left on device"
    docs.full = False
    k.retry(11.0 + RETRY_S)
    assert k.saved and not k.paced and k.error == ""
