"""Real magnetometer recordings (``tests/data``, see its SOURCES.md), as the product receives them.

Each source is read in its own units and axes and put in the compass's body
axes (x forward, y right, z down; the accelerometer reads *gravity*, +1 g on z
when level), then :func:`write_recording` turns it into what ``compass-bridge
record`` writes: ``$PGMRA`` frames at the datasheet's nominal transfer
(``2458 + 2560 counts/G``, ``2458 + 491.5 counts/g``, rounded; a channel
beyond 0..4095 is clipped and the frame flagged ``SAT``), the on-board
heading/pitch/roll the factory flash would give, each frame's bytes
timestamped with its time. The frame counter is the source's own sample
number, so a kept subset shows as lost frames and a gap as a jump.

No code of the sources is used: only their numbers.
"""

from __future__ import annotations

import csv
import functools
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypedDict

import numpy as np
import numpy.typing as npt

from bridge.core.sensor import (
    ADC_MAX,
    STANDARD_GRAVITY,
    g_to_acc_counts,
    gauss_to_mag_counts,
)
from bridge.link.record import RecordingWriter
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.protocol.gmr_frames import encode
from bridge.sim.firmware import FACTORY, onboard_attitude
from bridge.types import FloatArray, IntArray

DATA = Path(__file__).parent / "data"


@dataclass(frozen=True)
class RealData:
    """One source in body axes: ``mag_G`` (N, 3), ``acc_g`` (N, 3), frame numbers and times."""

    name: str
    mag_G: FloatArray
    acc_g: FloatArray
    seq: IntArray
    t_s: FloatArray
    has_accelerometer: bool

    def __len__(self) -> int:
        return int(self.mag_G.shape[0])

    @property
    def rate_hz(self) -> float:
        """Frames per second within runs (median step)."""
        d = np.diff(self.t_s)
        return 1.0 / float(np.median(d[d > 0]))

    def every(self, k: int) -> RealData:
        """Every ``k``-th frame: the same motion seen by a slower logger."""
        s = slice(None, None, k)
        return replace(
            self, mag_G=self.mag_G[s], acc_g=self.acc_g[s], seq=self.seq[s], t_s=self.t_s[s]
        )


def _read_only(data: RealData) -> RealData:
    """``data`` with its arrays made read-only: a loader's result is shared (see below)."""
    for a in (data.mag_G, data.acc_g, data.seq, data.t_s):
        a.setflags(write=False)
    return data


#: The loaders below are cached: a source file is parsed once per process, not again by
#: every test that starts from it (the 100 Hz tumble's 2000 rows were parsed eight times
#: in ``test_real_recordings``). Their arrays are read-only, so no test can change what
#: the next one is given; ``RealData.every`` gives read-only views of them.


def _comments_stripped(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]


def _ck(name: str, acc_mag: FloatArray, row: IntArray, source_rate_hz: float) -> RealData:
    # The log reads -1 g on z lying flat: its axes are (forward, left, up). Turned by 180 deg
    # about x -- (x, -y, -z), a rotation, for both sensors -- they are the compass's.
    flip = np.array([1.0, -1.0, -1.0])
    return RealData(
        name, acc_mag[:, 3:6] * flip, acc_mag[:, 0:3] * flip, row, row / source_rate_hz, True
    )


@functools.cache
def ck_tumble(source_rate_hz: float = 100.0) -> RealData:
    """CK-Explorer's hand tumble (LSM9DS1-class: 0.14 mG steps), 394 rows of 12 000.

    Units: g and gauss. The log reads -1 g on z when the unit lies flat, so its
    axes are (forward, left, up): turned by 180 deg about x -- (x, -y, -z), a
    rotation, for both sensors -- they are the compass's (forward, right, down),
    and the hard iron (0.15, -0.39, +0.06 G in these axes) stays inside the ADC's
    -0.96..+0.64 G. The source gives no sample rate; ``source_rate_hz`` is the
    one assumed for its row numbers (~100 Hz: a hand's 7-14 Hz tremor sits at
    0.07-0.14 cycles per row, and the tumble then turns at ~45 deg/s). The rows
    kept are about every 6th of eight stretches: ~17 Hz frames in eight runs.
    """
    rows = list(csv.reader(_comments_stripped(DATA / "ck_tumble.csv")))[1:]
    a = np.array([[float(v) for v in r[1:]] for r in rows])
    row = np.array([int(r[0]) for r in rows], dtype=np.int64)
    return _read_only(_ck("ck_tumble", a, row, source_rate_hz))


@functools.cache
def ck_tumble_100hz(source_rate_hz: float = 100.0) -> RealData:
    """The same log's 2000 consecutive rows 1400..3399: 20 s of the tumble at its own ~100 Hz.

    Axes, units and the assumed rate as :func:`ck_tumble`; every row is a frame,
    the frame counter the row number (``first_row`` in the file's header).
    """
    path = DATA / "ck_tumble_100hz.csv"
    first = next(
        int(ln.split(":", 1)[1])
        for ln in path.read_text().splitlines()
        if ln.startswith("# first_row:")
    )
    rows = list(csv.reader(_comments_stripped(path)))[1:]
    a = np.array([[float(v) for v in r] for r in rows])
    row = first + np.arange(a.shape[0], dtype=np.int64)
    return _read_only(_ck("ck_tumble_100hz", a, row, source_rate_hz))


@functools.cache
def px4_mag_data1(rate_hz: float = 10.0) -> RealData:
    """PX4's replay data: 231 calibration samples (gauss) of a vehicle with ~0.6 G of hard iron.

    No accelerometer in the source: the recording carries a still, level unit's
    reading (0, 0, +1 g) -- the heading part of a fit cannot be judged on it.
    No times either: the samples are in collection order, ``rate_hz`` apart.
    """
    rows = list(csv.reader(_comments_stripped(DATA / "px4_mag_data1.csv")))[1:]
    m = np.array([[float(v) for v in r] for r in rows])
    n = m.shape[0]
    acc = np.tile([0.0, 0.0, 1.0], (n, 1))
    seq = np.arange(n, dtype=np.int64)
    return _read_only(RealData("px4_mag_data1", m, acc, seq, seq / rate_hz, False))


@functools.cache
def sap6_hc() -> RealData:
    """The SAP6 cave-survey instrument "HC": 24 still shots, magnetometer (uT) and gravity (m/s^2).

    Axes as the instrument's own calibration file maps them (``mag_axes``
    "+X+Y-Z", ``grav_axes`` "-Y-X+Z"): one right-handed body frame in which
    both sensors agree (the angle between them is constant). Each shot is a
    separate still measurement: frames 20 counts apart, 2 s each, so no
    hand-held window ever spans two shots.
    """
    d = json.loads((DATA / "sap6_HC.json").read_text())
    m = np.asarray(d["mag"], dtype=np.float64)
    g = np.asarray(d["grav"], dtype=np.float64)
    mag = m * np.array([1.0, 1.0, -1.0]) / 100.0  # uT -> G
    grav = np.column_stack([-g[:, 1], -g[:, 0], g[:, 2]]) / STANDARD_GRAVITY
    n = mag.shape[0]
    seq = 20 * np.arange(n, dtype=np.int64)
    return _read_only(RealData("sap6_HC", mag, grav, seq, seq * 0.1, True))


class Published(TypedDict):
    """A calibration as its instrument published it."""

    centre_G: FloatArray
    field_G: float
    dip_deg: float


def sap6_published() -> Published:
    """The instrument's own calibration (its .cfg): centre in uT in its mapped axes, field, dip."""
    cfg = json.loads((DATA / "sap6_HC.cfg").read_text())
    return {
        "centre_G": np.asarray(cfg["calib"]["mag"]["centre"], dtype=np.float64) / 100.0,
        "field_G": float(cfg["calib"]["mag"]["field_avg"]) / 100.0,
        "dip_deg": float(cfg["calib"]["dip_avg"]),
    }


#: PX4's own test of this data (mag_calibration_test.cpp, replayTestData): the offsets
#: within 0.01 G and the ellipsoid's diagonal within 0.01 of these.
PX4_PUBLISHED_OFFSETS_G = np.array([-0.18, 0.05, -0.58])
PX4_PUBLISHED_DIAG = np.array([1.0, 1.06, 0.94])


def counts(data: RealData) -> tuple[IntArray, IntArray, npt.NDArray[np.bool_]]:
    """Nominal-transfer counts of every frame (rounded, clipped) and the saturated flags."""
    m = np.rint(gauss_to_mag_counts(data.mag_G)).astype(np.int64)
    a = np.rint(g_to_acc_counts(data.acc_g)).astype(np.int64)
    sat = np.any((m <= 0) | (m >= ADC_MAX) | (a <= 0) | (a >= ADC_MAX), axis=1)
    return np.clip(m, 0, ADC_MAX), np.clip(a, 0, ADC_MAX), sat


def write_recording(data: RealData, path: Path) -> Path:
    """``data`` as a ``compass-bridge record`` recording of ``$PGMRA`` frames (see the module doc)."""
    m, a, sat = counts(data)
    with RecordingWriter(path, "converted:" + data.name, 115200, 0.0) as w:
        for i in range(len(data)):
            mi = (int(m[i, 0]), int(m[i, 1]), int(m[i, 2]))
            ai = (int(a[i, 0]), int(a[i, 1]), int(a[i, 2]))
            hdg, pitch, roll = onboard_attitude(mi, ai, FACTORY)
            hdg = round(hdg, 1)
            frame = AttitudeFrame(
                int(data.seq[i]) % 65536,
                0.0 if hdg >= 360.0 else hdg,
                round(pitch, 1),
                round(roll, 1),
                *mi,
                *ai,
                Flags.SAT if sat[i] else Flags(0),
            )
            w.write(float(data.t_s[i] - data.t_s[0]), encode(frame))
    return path


def heading_deg(mG: float, horizontal_mG: float) -> float:
    """A milligauss error across the horizontal field, as degrees of heading."""
    return math.degrees(math.atan2(mG, horizontal_mG))
