"""Sphere coverage of calibration samples: the 80-section geodesic grid of MAG_CAL_PROGRESS.

A ground station draws MAG_CAL_PROGRESS.completion_mask (``uint8[10]``) as a
sphere: bit ``i % 8`` of byte ``i // 8`` is set when a sample has landed in
section ``i``. The sections are ArduPilot's ``AP_GeodesicGrid``: an
icosahedron whose 20 faces are each split into 4 by their edge midpoints. We
reproduce that layout exactly -- same face order, same sub-triangle numbering
-- so QGroundControl / Mission Planner light up the right patches:

* face ``T_i`` (``i`` in 0..9) has the vertices listed in :data:`ICOSAHEDRON_FACES`
  (``g`` is the golden ratio), and ``T_{i+10} = -T_i``;
* with ``T = (a, b, c)`` and the midpoints ``m_a = (a+b)/2``, ``m_b = (b+c)/2``,
  ``m_c = (c+a)/2``, sub-triangle 0 is ``(m_a, m_b, m_c)``, 1 is ``(a, m_a, m_c)``,
  2 is ``(m_a, b, m_b)``, 3 is ``(m_c, m_b, c)``;
* section index ``= 4 * face + sub_triangle``.

The vector classified is the sample relative to the current centre estimate
(hard-iron offset), optionally through the current soft-iron matrix, as
ArduPilot's ``CompassCalibrator::update_completion_mask`` does. Axes are the
sensor's body axes (x forward, y right, z down), the same as ArduPilot's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.types import FloatArray, IntArray

N_SECTIONS = 80  #: 20 icosahedron faces x 4 sub-triangles
MASK_BYTES = 10  #: MAG_CAL_PROGRESS.completion_mask is uint8[10]

_G = (1.0 + math.sqrt(5.0)) / 2.0  # golden ratio

#: The first ten icosahedron faces in AP_GeodesicGrid's order (vertices a, b, c);
#: faces 10..19 are their negatives.
ICOSAHEDRON_FACES: tuple[tuple[tuple[float, float, float], ...], ...] = (
    ((-_G, 1.0, 0.0), (-1.0, 0.0, -_G), (-_G, -1.0, 0.0)),
    ((-1.0, 0.0, -_G), (-_G, -1.0, 0.0), (0.0, -_G, -1.0)),
    ((-_G, -1.0, 0.0), (0.0, -_G, -1.0), (0.0, -_G, 1.0)),
    ((-1.0, 0.0, -_G), (0.0, -_G, -1.0), (1.0, 0.0, -_G)),
    ((0.0, -_G, -1.0), (0.0, -_G, 1.0), (_G, -1.0, 0.0)),
    ((0.0, -_G, -1.0), (1.0, 0.0, -_G), (_G, -1.0, 0.0)),
    ((_G, -1.0, 0.0), (1.0, 0.0, -_G), (_G, 1.0, 0.0)),
    ((1.0, 0.0, -_G), (_G, 1.0, 0.0), (0.0, _G, -1.0)),
    ((1.0, 0.0, -_G), (0.0, _G, -1.0), (-1.0, 0.0, -_G)),
    ((0.0, _G, -1.0), (-_G, 1.0, 0.0), (-1.0, 0.0, -_G)),
)


def _build_tables() -> tuple[FloatArray, FloatArray]:
    half = np.asarray(ICOSAHEDRON_FACES, dtype=np.float64)  # (10, 3 vertices, 3)
    faces = np.concatenate([half, -half])  # (20, 3, 3): T_{i+10} = -T_i
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    mids = np.stack([(a + b) / 2.0, (b + c) / 2.0, (c + a) / 2.0], axis=1)
    # Columns are the midpoints, so inv @ v gives v's coefficients on (m_a, m_b, m_c).
    mid_inv = np.linalg.inv(np.transpose(mids, (0, 2, 1)))
    return faces, mid_inv


_FACES, _MID_INV = _build_tables()
#: the face centres' x, y and z coordinates, each (20,) (the centres are all equally long)
_FC_X, _FC_Y, _FC_Z = np.ascontiguousarray(_FACES.mean(axis=1).T)


def face_vertices(face: int) -> FloatArray:
    """The three vertices (a, b, c) of icosahedron face ``face`` (0..19) as rows (unnormalised)."""
    if not 0 <= face < 20:
        raise ValueError(f"face {face} outside 0..19")
    return _FACES[face].copy()


def section_vertices(section: int) -> FloatArray:
    """The three corners of grid section ``section`` (0..79) as rows (unnormalised)."""
    if not 0 <= section < N_SECTIONS:
        raise ValueError(f"section {section} outside 0..{N_SECTIONS - 1}")
    a, b, c = _FACES[section // 4]
    ma, mb, mc = (a + b) / 2.0, (b + c) / 2.0, (c + a) / 2.0
    corners = ((ma, mb, mc), (a, ma, mc), (ma, b, mb), (mc, mb, c))[section % 4]
    return np.array(corners)


def sections(vectors: npt.ArrayLike) -> IntArray:
    """Section index (0..79) crossed by each vector of an (N, 3) batch; -1 for a null/non-finite one.

    A vector on a boundary belongs to one of the touching sections (like
    ArduPilot's ``inclusive=true``).
    """
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    # (the arrays' own all/any: the same masks without np.all / np.any's dispatch, once per
    # sample a collection keeps)
    ok = np.isfinite(v).all(axis=1) & (v != 0.0).any(axis=1)
    # Every vector usable (a collection's kept samples always are): no copy of the usable
    # rows and no masked write-back -- v itself when it is laid out as that copy would be
    # (C order), so the products below see the same matrix.
    every = v.shape[0] > 0 and bool(ok.all()) and v.flags.c_contiguous
    if every:
        vv = v
    else:
        out = np.full(v.shape[0], -1, dtype=np.int64)
        if not ok.any():
            return out
        vv = v[ok]
    # The spherical face a direction crosses is the one whose centre is nearest
    # (the face centres of a regular icosahedron are the vertices of its dual, and
    # each face is exactly their Voronoi cell): the dot products and an argmax. The
    # products are written out rather than one matmul so that a vector's section depends
    # on that vector alone, to the bit: BLAS rounds a row's three products differently
    # with the batch's size (its kernels fuse multiply-adds), and a collection classifies
    # each new sample alone (MagCollector). The two can part only on a boundary, where
    # either section is right.
    face = np.argmax(vv[:, 0:1] * _FC_X + vv[:, 1:2] * _FC_Y + vv[:, 2:3] * _FC_Z, axis=1)
    mi = _MID_INV[face]
    m = mi[:, :, 0] * vv[:, 0:1] + mi[:, :, 1] * vv[:, 1:2] + mi[:, :, 2] * vv[:, 2:3]
    # Outside the middle triangle exactly one coefficient is negative; the corner
    # opposite that midpoint is the sub-triangle (AP_GeodesicGrid's test order).
    sub = np.where(m[:, 0] < 0.0, 3, np.where(m[:, 1] < 0.0, 1, np.where(m[:, 2] < 0.0, 2, 0)))
    if every:
        return np.asarray(4 * face + sub, dtype=np.int64)
    out[ok] = 4 * face + sub
    return out


def section(vector: npt.ArrayLike) -> int:
    """Section index (0..79) crossed by one vector; -1 for the null vector."""
    return int(sections(np.asarray(vector, dtype=np.float64).reshape(1, 3))[0])


def completion_mask(section_indices: npt.ArrayLike) -> bytes:
    """MAG_CAL_PROGRESS.completion_mask (10 bytes) from section indices; negatives are ignored."""
    s = np.asarray(section_indices, dtype=np.int64).reshape(-1)
    s = s[(s >= 0) & (s < N_SECTIONS)]
    return _pack(np.bincount(s, minlength=N_SECTIONS) > 0)


def _pack(hit: npt.NDArray[np.bool_]) -> bytes:
    # bit i % 8 of byte i // 8 is section i: little-endian bit order within each byte
    return np.packbits(hit, bitorder="little").tobytes()


def mask_sections(mask: bytes | bytearray | Sequence[int]) -> frozenset[int]:
    """Inverse of :func:`completion_mask`: the sections set in a 10-byte mask."""
    b = bytes(mask)
    if len(b) != MASK_BYTES:
        raise ValueError(f"completion mask must be {MASK_BYTES} bytes, got {len(b)}")
    return frozenset(i for i in range(N_SECTIONS) if b[i // 8] >> (i % 8) & 1)


@dataclass(frozen=True, slots=True)
class Coverage:
    """Which grid sections the samples reach.

    ``mask`` is MAG_CAL_PROGRESS.completion_mask; ``percent`` is the share of
    the 80 sections hit; ``counts`` holds samples per section (80 ints).
    """

    mask: bytes
    sections_hit: frozenset[int]
    counts: tuple[int, ...]

    @property
    def percent(self) -> float:
        """Sections hit as a percentage of all 80."""
        return 100.0 * len(self.sections_hit) / N_SECTIONS

    @property
    def missing(self) -> frozenset[int]:
        """Sections still without a sample (what the operator has to point at)."""
        return frozenset(range(N_SECTIONS)) - self.sections_hit


def coverage(
    samples_G: npt.ArrayLike,
    centre_G: npt.ArrayLike = (0.0, 0.0, 0.0),
    matrix: npt.ArrayLike | None = None,
) -> Coverage:
    """Sphere coverage of raw samples seen from ``centre_G`` (through ``matrix`` when given).

    ``samples_G`` is (N, 3); non-finite rows and samples at the centre are
    ignored. ``matrix`` is the current soft-iron estimate (applied as
    ``matrix @ (sample - centre)``), so coverage follows the fit as it improves.
    """
    x = np.asarray(samples_G, dtype=np.float64).reshape(-1, 3)
    d = x - np.asarray(centre_G, dtype=np.float64).reshape(3)
    if matrix is not None:
        d = d @ np.asarray(matrix, dtype=np.float64).reshape(3, 3).T
    s = sections(d)
    valid = s[s >= 0]
    counts = np.bincount(valid, minlength=N_SECTIONS)
    return Coverage(
        mask=_pack(counts > 0),
        sections_hit=frozenset(np.flatnonzero(counts).tolist()),
        counts=tuple(int(c) for c in counts),
    )
