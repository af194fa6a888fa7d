"""Sphere coverage: ArduPilot's 80-section geodesic grid and the MAG_CAL_PROGRESS mask layout."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.calibration.fits.coverage import (
    MASK_BYTES,
    N_SECTIONS,
    completion_mask,
    coverage,
    face_vertices,
    mask_sections,
    section,
    section_vertices,
    sections,
)

G = (1.0 + math.sqrt(5.0)) / 2.0


# Expected sections from ArduPilot's libraries/AP_Math/tests/test_geodesic_grid.cpp
# ("hardcoded vectors", described there by their construction).
@pytest.mark.parametrize(
    ("vector", "expected"),
    [
        ((0.25 * G, -0.25 * (13.0 * G + 1.0), -1.25), 17),  # a + 2 m_a + .5 m_c of T_4
        ((-0.2667, 0.1667 * G, 2.2667 * G + 0.1667), 55),  # 2 m_c + m_b / 3 + .1 c of T_13
        ((-0.875, 6.125 * G, -1.125 * G - 6.125), 34),  # .25 m_a + 5 b + 2 m_b of T_8
    ],
)
def test_ardupilot_reference_vectors(vector: tuple[float, float, float], expected: int) -> None:
    assert section(vector) == expected


# Icosahedron vertices touch five sections; ArduPilot's test lists which (inclusive mode).
@pytest.mark.parametrize(
    ("vertex", "allowed"),
    [
        ((G, 1.0, 0.0), {27, 30, 43, 46, 49}),
        ((G, -1.0, 0.0), {19, 23, 25, 41, 78}),
        ((-G, 1.0, 0.0), {1, 38, 59, 63, 65}),
        ((1.0, 0.0, -G), {15, 22, 26, 29, 33}),
        ((0.0, -G, 1.0), {11, 18, 71, 74, 77}),
        ((0.0, -G, -1.0), {7, 10, 14, 17, 21}),
    ],
)
def test_vertices_fall_in_a_touching_section(
    vertex: tuple[float, float, float], allowed: set[int]
) -> None:
    assert section(vertex) in allowed


def test_ardupilot_first_face_inverse() -> None:
    # AP_GeodesicGrid::_inverses[0], as published in AP_GeodesicGrid.cpp
    published = np.array(
        [[-0.309017, 0.5, 0.190983], [0.0, 0.0, -0.618034], [-0.309017, -0.5, 0.190983]]
    )
    assert np.allclose(np.linalg.inv(face_vertices(0).T), published, atol=1e-6)
    assert np.allclose(face_vertices(13), -face_vertices(3))


def test_every_section_classifies_its_own_centroid_and_corner_regions() -> None:
    for s in range(N_SECTIONS):
        a, b, c = section_vertices(s)
        probes = [a + b + c, a + b + 0.01 * c, a + 0.01 * b + c, 0.01 * a + b + c]
        assert sections(np.array(probes)).tolist() == [s] * 4, s


def test_uniform_directions_fill_every_section_roughly_equally() -> None:
    rng = np.random.default_rng(7)
    s = sections(rng.normal(size=(40_000, 3)))
    counts = np.bincount(s, minlength=N_SECTIONS)
    # Sections differ in area (the middle triangles are larger), but by < 35 %.
    assert counts.min() > 0.6 * counts.mean() and counts.max() < 1.5 * counts.mean()


def test_null_and_non_finite_vectors_cross_no_section() -> None:
    v = np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s = sections(v)
    assert s[:3].tolist() == [-1, -1, -1] and s[3] >= 0


def test_mask_bit_layout_matches_mag_cal_progress() -> None:
    mask = completion_mask([0, 9, 79, 9, -1])
    assert len(mask) == MASK_BYTES
    # bit i % 8 of byte i // 8
    assert mask == bytes([0x01, 0x02, 0, 0, 0, 0, 0, 0, 0, 0x80])
    assert mask_sections(mask) == {0, 9, 79}
    with pytest.raises(ValueError):
        mask_sections(b"\x00" * 9)


def test_coverage_is_relative_to_the_centre_and_through_the_matrix() -> None:
    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre = np.array([0.3, -0.2, 0.5])
    stretch = np.diag([1.5, 0.7, 1.0])
    raw = centre + 0.45 * d @ np.linalg.inv(stretch).T
    seen_from_origin = coverage(raw)
    seen_from_centre = coverage(raw, centre, stretch)
    assert seen_from_centre.percent == 100.0 and not seen_from_centre.missing
    # From the origin the offset sphere subtends only part of the sky.
    assert seen_from_origin.percent < 60.0
    assert sum(seen_from_centre.counts) == 3000


def test_a_hemisphere_lights_about_half_of_the_sections() -> None:
    rng = np.random.default_rng(5)
    d = rng.normal(size=(5000, 3))
    d[:, 2] = np.abs(d[:, 2])  # only the lower (z down > 0) half
    cov = coverage(d)
    assert 45.0 <= cov.percent <= 65.0
    assert cov.mask == completion_mask(sorted(cov.sections_hit))
    for s in cov.sections_hit:  # every section hit reaches into the z > 0 half
        assert np.max(section_vertices(s)[:, 2]) > 0.0
    for s in cov.missing:
        assert np.sum(section_vertices(s), axis=0)[2] < 0.3
