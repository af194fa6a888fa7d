"""Pure sample collectors behind the calibration controller (no clock, no threads, no I/O).

Time, where a collector needs it, comes in as an argument (``now``, seconds on
any monotonic scale), so the same code runs in real time in the daemon and on
a simulated clock in tests.

* :class:`MagCollector` -- ArduPilot's two-step magnetometer sample buffer
  (``CompassCalibrator``): step one fills the buffer at a 200 mG spacing, a
  sphere fit sets the real radius, the buffer is thinned and step two refills
  it; coverage (the 80 MAG_CAL_PROGRESS sections), completion percent and a
  direction hint follow the samples.
* :class:`FaceCollector` -- PX4's six-face accelerometer routine: wait until
  the unit rests still on a face, average it, ask for the next one.
* :class:`StillCollector` -- one still average (level calibration, fixed yaw).

The device's own MAGCAL routine is followed by
:class:`~bridge.calibration.sessions.onboard.OnboardMagTracker`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.accel_faces import Face, detect_face
from bridge.calibration.fits.coverage import (
    MASK_BYTES,
    N_SECTIONS,
    completion_mask,
    section_vertices,
    sections,
)
from bridge.calibration.fits.ellipsoid import fit_sphere
from bridge.calibration.fits.samples import COMPASS_CAL_NUM_SAMPLES, SampleAcceptor
from bridge.calibration.sessions.motion import FrameSeries, MotionJudge, MotionWarning
from bridge.core import sensor
from bridge.protocol.gmr import AttitudeFrame
from bridge.types import FloatArray, Vec3

#: ArduPilot's progress split: step one is the first third of the bar.
STEP_ONE_PCT = 33.3
STEP_TWO_PCT = 65.7
#: Plausible Earth-field radii for a sphere fit (ArduPilot's 150..950 mG, widened for step one).
_RADIUS_RANGE_G = (0.1, 1.5)
#: Samples before the coverage centre switches from the mean to a sphere fit.
_SPHERE_CENTRE_MIN = 20

_SECTION_DIRS: FloatArray = np.array(
    [section_vertices(i).mean(axis=0) for i in range(N_SECTIONS)], dtype=np.float64
)
_SECTION_DIRS /= np.linalg.norm(_SECTION_DIRS, axis=1, keepdims=True)


def counts_to_nominal(
    mx: int, my: int, mz: int, ax: int, ay: int, az: int
) -> tuple[Vec3, Vec3, bool]:
    """Raw ADC counts to nominal gauss and g (scalar fast path) plus the saturation flag."""
    z, mg, ag = sensor.ZERO_COUNTS, sensor.MAG_COUNTS_PER_GAUSS, sensor.ACC_COUNTS_PER_G
    top = sensor.ADC_MAX
    sat = not (0 < mx < top and 0 < my < top and 0 < mz < top) or not (
        0 < ax < top and 0 < ay < top and 0 < az < top
    )
    return (
        ((mx - z) / mg, (my - z) / mg, (mz - z) / mg),
        ((ax - z) / ag, (ay - z) / ag, (az - z) / ag),
        sat,
    )


def frame_vectors(f: AttitudeFrame) -> tuple[Vec3, Vec3, bool]:
    """An attitude frame's raw vectors in nominal gauss and g, and whether it is saturated
    (a channel at an ADC rail, or the device's SAT flag)."""
    mag, acc, sat = counts_to_nominal(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
    return mag, acc, sat or f.sat_flag


# ---------------------------------------------------------------------------
# host magnetometer
# ---------------------------------------------------------------------------


class MagCollector:
    """ArduPilot-style two-step magnetometer sample collection (one attempt).

    ``offer`` every frame's raw vectors; when :attr:`full` the owner runs
    :func:`sphere_step` (step one) or the final fit (step two) on
    :meth:`data` -- in a worker thread, the collector is just data -- and in
    step one hands the sphere to :meth:`begin_step_two`. The accelerometer
    vector of each kept frame travels with its magnetometer vector (the
    aligned fit needs both).

    Frames offered with their time (``now``) are also kept in order in
    :attr:`series` -- all of them, not only the kept samples -- and judged by
    ``judge`` (a :class:`MotionJudge`, if given): :meth:`pop_motion_warning`
    returns what it found worth telling the operator.
    """

    def __init__(
        self,
        capacity: int = COMPASS_CAL_NUM_SAMPLES,
        seed: int = 0,
        *,
        judge: MotionJudge | None = None,
    ) -> None:
        self.acceptor = SampleAcceptor(capacity)
        self.series = FrameSeries()
        self.judge = judge
        self._warning: MotionWarning | None = None
        self.capacity = capacity
        self.step = 1
        self._acc: dict[Vec3, Vec3] = {}
        self._rng = np.random.default_rng(seed)
        self._sum = np.zeros(3)
        self._kept_after_thin = 0
        self.centre: FloatArray = np.zeros(3)
        self.radius_G: float | None = None
        self._mask = bytes(MASK_BYTES)
        self._hit: frozenset[int] = frozenset()
        #: the centre _hit and _mask were worked out from (None: not yet)
        self._covered_from: FloatArray | None = None
        #: _SECTION_DIRS of the sections not in _hit, as an array and as rows of floats
        #: (None: not worked out since it changed)
        self._missing_dirs: tuple[FloatArray, list[list[float]]] | None = None
        self.last_mag: Vec3 | None = None
        self.offered = 0
        self._sphere_centre = False

    # -- collection ---------------------------------------------------------------

    @property
    def full(self) -> bool:
        """The buffer is full: time for this step's fit."""
        return self.acceptor.full

    def __len__(self) -> int:
        return len(self.acceptor)

    def offer(self, mag_G: Vec3, acc_g: Vec3, saturated: bool, now: float | None = None) -> bool:
        """Offer one frame (raw nominal gauss / g); True when kept. Saturated frames never are.

        ``now`` (seconds, any monotonic scale) adds the frame to :attr:`series`
        and to the motion judge.
        """
        self.offered += 1
        self.last_mag = mag_G
        if now is not None:
            self.series.add(now, mag_G, acc_g, saturated)
            if self.judge is not None:
                w = self.judge.feed(now, acc_g, saturated)
                if w is not None:
                    self._warning = w
        if not self.acceptor.offer(mag_G, saturated=saturated):
            return False
        self._acc[mag_G] = acc_g
        self._sum += mag_G
        self._update_coverage(mag_G)
        return True

    def _update_coverage(self, new: Vec3 | None = None) -> None:
        """The sections the kept samples reach from the centre; ``new`` is the sample just
        kept (None: the buffer changed otherwise, as when it is thinned)."""
        n = len(self.acceptor)
        if self.step == 1:
            # Before step one's fit the centre is a guess: the mean of the samples,
            # then (every 10 samples) a linear sphere fit once a few outline the sphere.
            if n >= _SPHERE_CENTRE_MIN and (n % 10 == 0 or not self._sphere_centre):
                sph = sphere_step(self.acceptor.samples)
                if sph is not None:
                    self.centre = sph[0]
                    self._sphere_centre = True
            if not self._sphere_centre:
                self.centre = self._sum / max(n, 1)
        centre = self.centre
        if new is not None and centre is self._covered_from:
            # The centre has not moved (all of step two, most of step one): the other
            # samples' sections stand, as a section depends on its own vector alone
            # (coverage.sections), and only the new sample's is worked out -- not the
            # whole buffer's again for every sample kept.
            k = int(sections(np.array(new) - centre)[0])
            if k < 0 or k in self._hit:
                return
            hit = self._hit | {k}
            self._mask = completion_mask(sorted(hit))
        else:
            s = sections(self.acceptor.samples - centre)
            self._mask = completion_mask(s)
            hit = frozenset(s[s >= 0].tolist())
            self._covered_from = centre
        if hit != self._hit:
            self._hit = hit
            self._missing_dirs = None

    def begin_step_two(self, centre: npt.ArrayLike, radius_G: float) -> int:
        """Step one's sphere is known: respace the buffer for it and keep collecting.

        Returns how many samples the thinning removed (ArduPilot shuffles first
        so neighbours are not removed in runs; the shuffle is seeded).
        """
        self.centre = np.asarray(centre, dtype=np.float64).reshape(3)
        self.radius_G = float(radius_G)
        self.acceptor.set_radius(self.radius_G)
        removed = self.acceptor.thin(self._rng.permutation(len(self.acceptor)))
        kept = self.acceptor.samples
        keep = _row_set(kept)
        self._acc = {k: v for k, v in self._acc.items() if k in keep}
        self._sum = kept.sum(axis=0) if len(kept) else np.zeros(3)
        self._kept_after_thin = len(kept)
        self.step = 2
        self._update_coverage()
        return removed

    def pop_motion_warning(self) -> MotionWarning | None:
        """The motion judge's latest warning, once (None: nothing to say)."""
        w, self._warning = self._warning, None
        return w

    def data(self) -> tuple[FloatArray, FloatArray]:
        """The kept (N, 3) magnetometer samples and the (N, 3) accelerometer ones of the same frames."""
        mag = self.acceptor.samples
        acc = np.array([self._acc[(float(r[0]), float(r[1]), float(r[2]))] for r in mag])
        return mag, acc.reshape(-1, 3)

    # -- progress -----------------------------------------------------------------

    @property
    def percent(self) -> float:
        """ArduPilot's completion: step one fills 33.3 %, step two the next 65.7 % (never 100)."""
        n = len(self.acceptor)
        if self.step == 1:
            return STEP_ONE_PCT * n / self.capacity
        base = self._kept_after_thin
        span = max(1, self.capacity - base)
        return STEP_ONE_PCT + STEP_TWO_PCT * max(0, n - base) / span

    @property
    def mask(self) -> bytes:
        """MAG_CAL_PROGRESS.completion_mask: the sections the kept samples reach."""
        return self._mask

    @property
    def sections_hit(self) -> frozenset[int]:
        """Indices of the sections reached."""
        return self._hit

    def direction_hint(self) -> Vec3:
        """Where to turn next: the unvisited section nearest the current field direction.

        A body-frame unit vector (sensor axes, x forward, y right, z down): turn the
        unit until the Earth's field points along it. ``(0, 0, 0)`` when every
        section is visited or nothing is known yet (MAG_CAL_PROGRESS.direction_*).
        """
        if self.last_mag is None or len(self._hit) >= N_SECTIONS:
            return (0.0, 0.0, 0.0)
        # In plain floats up to the one product with the missing sections' directions (a
        # status query can ask for this every frame, and numpy's dispatch on a 3-vector
        # cost more than its arithmetic): the field from the centre, its length (the
        # dot product in the order numpy's sums it: the same bits) and the unit vector.
        mx, my, mz = self.last_mag
        cx, cy, cz = self.centre.tolist()
        x, y, z = mx - cx, my - cy, mz - cz
        n = math.sqrt(x * x + y * y + z * z)
        if not n > 0.0:
            return (0.0, 0.0, 0.0)
        missing = self._missing_dirs
        if missing is None:  # once per change of the sections reached, not once per frame
            idx = np.array(sorted(set(range(N_SECTIONS)) - self._hit), dtype=np.int64)
            dirs = _SECTION_DIRS[idx]
            missing = self._missing_dirs = (dirs, dirs.tolist())
        dirs, rows = missing
        # ndarray.dot rather than @: the same BLAS call (a row-major gemv: the same bits),
        # without matmul's ufunc machinery (half the time on these few rows)
        x, y, z = rows[int(dirs.dot(np.array((x / n, y / n, z / n))).argmax())]
        return (x, y, z)


def _row_set(x: FloatArray) -> set[Vec3]:
    return {(float(r[0]), float(r[1]), float(r[2])) for r in x}


def sphere_step(mag_G: npt.ArrayLike) -> tuple[FloatArray, float] | None:
    """Step one's fit: the sphere (centre, radius in gauss) of the samples, None if implausible."""
    sph = fit_sphere(mag_G)
    if sph is None or not _RADIUS_RANGE_G[0] < sph[1] < _RADIUS_RANGE_G[1]:
        return None
    return sph


# ---------------------------------------------------------------------------
# accelerometer faces and still averages
# ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FaceNotice:
    """What a :class:`FaceCollector` has to say after a frame.

    ``kind`` is ``"detected"`` (a new face is held still), ``"done"`` (its mean
    is recorded), ``"already_done"`` (this face was done before) or
    ``"moved"`` (the unit moved before the face was averaged).
    """

    kind: str
    face: Face


@dataclass(slots=True)
class _Window:
    """Recent (t, vector) rows no older than ``span_s``."""

    span_s: float
    rows: deque[tuple[float, Vec3]] = field(default_factory=deque)

    def add(self, now: float, v: Vec3) -> None:
        self.rows.append((now, v))
        while self.rows and self.rows[0][0] < now - self.span_s:
            self.rows.popleft()

    def covers(self, now: float, min_rows: int) -> bool:
        # 90 % of the span: frame ticks never land exactly on the window edge.
        return len(self.rows) >= min_rows and now - self.rows[0][0] >= 0.9 * self.span_s

    def array(self) -> FloatArray:
        return np.array([v for _, v in self.rows], dtype=np.float64).reshape(-1, 3)


class FaceCollector:
    """PX4's six-face routine on raw nominal accelerometer samples.

    A face counts when the last ``still_s`` seconds are still and point along
    it (:func:`~bridge.calibration.fits.accel_faces.detect_face`); its mean is then
    taken over ``collect_s`` more seconds of stillness. ``norm_tol_g`` is wide
    by default because an uncalibrated unit can read 1 +- 0.5 g (ADC zero and
    gain tolerances).
    """

    def __init__(
        self,
        still_s: float = 1.0,
        collect_s: float = 1.5,
        still_tol_g: float = 0.02,
        norm_tol_g: float = 0.5,
        min_rows: int = 5,
    ) -> None:
        self.still_s = still_s
        self.collect_s = collect_s
        self.still_tol_g = still_tol_g
        self.norm_tol_g = norm_tol_g
        self.min_rows = min_rows
        self._win = _Window(still_s)
        self.means: dict[Face, FloatArray] = {}
        self.current: Face | None = None  #: face being averaged
        self._since: float = 0.0
        self._last_t: float = 0.0
        self._collected: list[Vec3] = []
        self._resting_on: Face | None = None  #: last face seen still (for "already done")

    @property
    def done(self) -> bool:
        """All six faces averaged."""
        return len(self.means) == len(Face)

    @property
    def percent(self) -> float:
        """Faces done (and the share of the current one) out of six, 0-100."""
        part = 0.0
        if self.current is not None and self.collect_s > 0:
            part = min(1.0, max(0.0, self._last_t - self._since) / self.collect_s)
        return 100.0 * (len(self.means) + part) / len(Face)

    def _detect(self) -> Face | None:
        return detect_face(self._win.array(), self.still_tol_g, norm_tol_g=self.norm_tol_g)

    def feed(self, now: float, acc_g: Vec3, saturated: bool = False) -> list[FaceNotice]:
        """One frame; returns what changed (usually nothing)."""
        if saturated or not all(math.isfinite(v) for v in acc_g):
            return []
        self._last_t = now
        self._win.add(now, acc_g)
        if not self._win.covers(now, self.min_rows):
            return []
        face = self._detect()
        out: list[FaceNotice] = []
        if self.current is not None:
            if face is not self.current:
                out.append(FaceNotice("moved", self.current))
                self.current = None
                self._collected = []
                self._resting_on = face
                return out
            self._collected.append(acc_g)
            if now - self._since >= self.collect_s:
                window = self._win.array()
                # The face mean: the detection window plus everything collected since.
                self.means[self.current] = np.vstack(
                    [window, np.asarray(self._collected, dtype=np.float64)]
                ).mean(axis=0)
                out.append(FaceNotice("done", self.current))
                self._resting_on = self.current
                self.current = None
                self._collected = []
            return out
        if face is None:
            self._resting_on = None
            return out
        if face in self.means:
            if face is not self._resting_on:
                out.append(FaceNotice("already_done", face))
            self._resting_on = face
            return out
        self.current = face
        self._since = now
        self._collected = []
        self._resting_on = face
        out.append(FaceNotice("detected", face))
        return out


class StillCollector:
    """Averages ``collect_s`` seconds of samples and says whether they were still.

    Used by the host level calibration (accelerometer) and kept as a rolling
    window for the fixed-yaw calibration (magnetometer + accelerometer).
    """

    def __init__(self, collect_s: float = 1.0, still_tol_g: float = 0.02, min_rows: int = 5):
        self.collect_s = collect_s
        self.still_tol_g = still_tol_g
        self.min_rows = min_rows
        self._start: float | None = None
        self._mag: list[Vec3] = []
        self._acc: list[Vec3] = []
        self._last: float | None = None

    def feed(self, now: float, mag_G: Vec3, acc_g: Vec3, saturated: bool = False) -> bool:
        """Add one frame; True once ``collect_s`` seconds (and ``min_rows`` frames) are in."""
        if self._start is None:
            self._start = now
        self._last = now
        if not saturated:
            self._mag.append(mag_G)
            self._acc.append(acc_g)
        return self.complete

    @property
    def complete(self) -> bool:
        """Enough time and frames collected."""
        return (
            self._start is not None
            and self._last is not None
            and self._last - self._start >= self.collect_s
            and len(self._acc) >= self.min_rows
        )

    @property
    def percent(self) -> float:
        """Share of the collection time done, 0-100."""
        if self._start is None or self._last is None or self.collect_s <= 0:
            return 0.0
        return min(100.0, 100.0 * (self._last - self._start) / self.collect_s)

    def means(self) -> tuple[FloatArray, FloatArray, float]:
        """(mean mag, mean acc, largest per-axis accelerometer standard deviation in g)."""
        acc = np.asarray(self._acc, dtype=np.float64).reshape(-1, 3)
        mag = np.asarray(self._mag, dtype=np.float64).reshape(-1, 3)
        if len(acc) == 0:
            return np.full(3, math.nan), np.full(3, math.nan), math.inf
        return mag.mean(axis=0), acc.mean(axis=0), float(np.max(np.std(acc, axis=0)))

    @property
    def still(self) -> bool:
        """Every accelerometer axis varied less than ``still_tol_g`` (one sigma)."""
        return self.means()[2] < self.still_tol_g
