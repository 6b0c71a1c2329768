"""Tests of feeder_sim.model.geometry against closed-form answers.

Tolerances: 1e-12 relative for areas, centroids (relative to the part size), second moments and
masses; 1e-15 absolute for rotation matrices.
"""

import math

from hypothesis import assume, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from feeder_sim.model.geometry import (
    convex_decomposition,
    convex_overlap,
    drop_collinear,
    edge_normals,
    is_convex,
    is_simple,
    mass_properties,
    MassProperties,
    polygon_area,
    polygon_centroid,
    polygon_second_moment,
    reflex_vertices,
    rotation,
)

REL = 1e-12


def rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def union_of_rectangles(rects):
    """Area, centroid and polar second moment about the centroid of disjoint rectangles."""
    areas = np.array([(x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in rects])
    centres = np.array([[(x0 + x1) / 2, (y0 + y1) / 2] for x0, y0, x1, y1 in rects])
    area = areas.sum()
    centroid = (areas[:, None] * centres).sum(axis=0) / area
    second = sum(a * ((x1 - x0) ** 2 + (y1 - y0) ** 2) / 12 + a * np.sum((c - centroid) ** 2)
                 for a, c, (x0, y0, x1, y1) in zip(areas, centres, rects))
    return area, centroid, second


# A 2 x 3 L and a cup 20 mm wide, 12 mm tall, with 2 mm walls and floor (both CCW).
L_SHAPE = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 3], [0, 3]], dtype=float)
L_RECTS = [(0, 0, 2, 1), (0, 1, 1, 3)]
CUP = np.array([[0, 0], [20, 0], [20, 12], [18, 12], [18, 2], [2, 2], [2, 12], [0, 12]],
               dtype=float) * 1e-3
CUP_RECTS = [tuple(np.array(r) * 1e-3) for r in [(0, 0, 20, 2), (0, 2, 2, 12), (18, 2, 20, 12)]]


def points_in_polygon(points, poly):
    """Even-odd ray casting for many points (independent of the code under test)."""
    poly = np.asarray(poly, dtype=float)
    x, y = points[:, :1], points[:, 1:]
    (x0, y0), (x1, y1) = poly.T, np.roll(poly, -1, axis=0).T
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide='ignore', invalid='ignore'):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.sum(straddles & (x_cross > x), axis=1) % 2 == 1


def assert_valid_decomposition(poly, pieces, samples=2000, seed=0):
    for piece in pieces:
        assert is_convex(piece), piece
        assert polygon_area(piece) > 0
        assert len(reflex_vertices(piece)) == 0
        # No collinear vertices are left in the pieces.
        assert len(drop_collinear(piece)) == len(piece)
    total = sum(polygon_area(p) for p in pieces)
    assert total == pytest.approx(polygon_area(poly), rel=REL)
    for i in range(len(pieces)):
        for j in range(i + 1, len(pieces)):
            assert not convex_overlap(pieces[i], pieces[j])
    # Union equals the polygon: every sample point is in exactly one piece iff in the polygon.
    rng = np.random.default_rng(seed)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    points = rng.uniform(lo, hi, size=(samples, 2))
    count = sum(points_in_polygon(points, piece).astype(int) for piece in pieces)
    np.testing.assert_array_equal(count, points_in_polygon(points, poly).astype(int))


def assert_same_mass_properties(a: MassProperties, b: MassProperties, size: float):
    assert a.mass == pytest.approx(b.mass, rel=REL)
    assert a.inertia == pytest.approx(b.inertia, rel=REL)
    np.testing.assert_allclose(a.centroid, b.centroid, rtol=0, atol=REL * size)


# ---------------------------------------------------------------- area, centroid, inertia

def test_rectangle_mass_properties():
    w, h, m = 0.03, 0.012, 0.0125
    poly = rect(0.5, -0.2, 0.5 + w, -0.2 + h)
    assert polygon_area(poly) == pytest.approx(w * h, rel=REL)
    assert polygon_area(poly[::-1]) == pytest.approx(-w * h, rel=REL)
    np.testing.assert_allclose(polygon_centroid(poly), [0.5 + w / 2, -0.2 + h / 2],
                               rtol=0, atol=REL * w)
    props = mass_properties([poly], mass=m)
    assert props.mass == m
    assert props.inertia == pytest.approx(m * (w * w + h * h) / 12, rel=REL)
    # Parallel-axis theorem about the origin.
    c = polygon_centroid(poly)
    assert polygon_second_moment(poly, [0, 0]) == pytest.approx(
        w * h * (w * w + h * h) / 12 + w * h * c @ c, rel=REL)


def test_density_gives_mass_and_inertia():
    w, h, rho = 0.02, 0.01, 7.85   # kg/m^2
    props = mass_properties([rect(0, 0, w, h)], density=rho)
    assert props.mass == pytest.approx(rho * w * h, rel=REL)
    assert props.inertia == pytest.approx(rho * w * h * (w * w + h * h) / 12, rel=REL)


def test_scalene_triangle():
    tri = np.array([[0.1, 0.2], [0.9, 0.35], [0.4, 1.3]])
    (x0, y0), (x1, y1), (x2, y2) = tri
    area = 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
    assert polygon_area(tri) == pytest.approx(area, rel=REL)
    np.testing.assert_allclose(polygon_centroid(tri), tri.mean(axis=0), rtol=0, atol=1e-15)
    # Polar moment about the centroid: A (a^2 + b^2 + c^2) / 36 with side lengths a, b, c.
    sides2 = sum(np.sum((tri[k] - tri[k - 1]) ** 2) for k in range(3))
    assert polygon_second_moment(tri, tri.mean(axis=0)) == pytest.approx(area * sides2 / 36,
                                                                          rel=REL)
    props = mass_properties([tri], mass=2.0)
    assert props.inertia == pytest.approx(2.0 * sides2 / 36, rel=REL)


@pytest.mark.parametrize('poly, rects', [(L_SHAPE, L_RECTS), (CUP, CUP_RECTS)], ids=['L', 'cup'])
def test_concave_polygon_matches_sum_of_rectangles(poly, rects):
    area, centroid, second = union_of_rectangles(rects)
    size = np.ptp(poly, axis=0).max()
    assert polygon_area(poly) == pytest.approx(area, rel=REL)
    np.testing.assert_allclose(polygon_centroid(poly), centroid, rtol=0, atol=REL * size)
    assert polygon_second_moment(poly, centroid) == pytest.approx(second, rel=REL)
    props = mass_properties([poly], mass=0.004)
    assert props.inertia == pytest.approx(0.004 * second / area, rel=REL)
    # The same body given as its rectangles.
    by_rects = mass_properties([rect(*r) for r in rects], mass=0.004)
    assert_same_mass_properties(by_rects, props, size)


def test_mass_properties_rejects_bad_input():
    square = rect(0, 0, 1, 1)
    with pytest.raises(ValueError, match='exactly one'):
        mass_properties([square])
    with pytest.raises(ValueError, match='exactly one'):
        mass_properties([square], mass=1.0, density=1.0)
    with pytest.raises(ValueError, match='positive'):
        mass_properties([square], mass=0.0)
    with pytest.raises(ValueError, match='clockwise'):
        mass_properties([square[::-1]], mass=1.0)


def test_mass_properties_is_frozen():
    props = mass_properties([rect(0, 0, 1, 1)], mass=1.0)
    with pytest.raises(ValueError):
        props.centroid[0] = 3.0
    assert props == mass_properties([rect(0, 0, 1, 1)], mass=1.0)


def test_zero_area_centroid_raises():
    with pytest.raises(ValueError, match='zero area'):
        polygon_centroid([[0, 0], [1, 0], [2, 0]])


# ---------------------------------------------------------------- simplicity and convexity

@pytest.mark.parametrize('poly, expected', [
    ([[0, 0], [1, 1], [1, 0], [0, 1]], 'self-intersecting (edges 0 and 2 cross)'),   # bow-tie
    ([[0, 0], [2, 0], [2, 2], [0, 2], [3, 1]], 'self-intersecting (edges 1 and 3 cross)'),
    ([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]], 'self-touching (vertex 3 lies on edge 0)'),
    ([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], 'the last vertex 4 repeats the first'),
    ([[0, 0], [2, 0], [1, 1], [2, 2], [0, 2], [1, 1]], 'vertices 2 and 5 coincide'),
    ([[0, 0], [1, 0], [2, 0]], 'zero area'),
    ([[0, 0], [2, 0], [1, 0], [1, 1]], 'doubles back at vertex 1'),
    ([[0, 0], [1, 0]], 'at least 3 vertices'),
    ([[0, 0], [1, 0], [np.nan, 1]], 'finite'),
], ids=['bow-tie', 'crossing', 'touching', 'closed', 'repeated', 'collinear', 'spike', 'short',
        'nan'])
def test_is_simple_rejects(poly, expected):
    ok, reason = is_simple(poly)
    assert not ok
    assert expected in reason


@pytest.mark.parametrize('poly', [rect(0, 0, 1, 1), rect(0, 0, 1, 1)[::-1], L_SHAPE, CUP,
                                  [[0, 0], [1, 0], [2, 0], [1, 1]]],
                         ids=['square', 'clockwise square', 'L', 'cup', 'collinear vertex'])
def test_is_simple_accepts(poly):
    assert is_simple(poly) == (True, '')


PENTAGRAM = np.array([[np.cos(a), np.sin(a)] for a in np.pi / 2 + 4 * np.pi / 5 * np.arange(5)])


@pytest.mark.parametrize('poly, convex', [
    (rect(0, 0, 1, 1), True),
    ([[0, 0], [0.5, 0], [1, 0], [1, 1], [0, 1]], True),      # collinear vertex: allowed
    (rect(0, 0, 1, 1)[::-1], False),                          # clockwise
    (L_SHAPE, False),
    (PENTAGRAM, False),                                       # only left turns, but winds twice
    ([[0, 0], [2, 0], [1, 0], [1, 1]], False),                # spike
    ([[0, 0], [1, 0], [1, 0], [0, 1]], False),                # repeated vertex
])
def test_is_convex(poly, convex):
    assert is_convex(poly) is convex


def test_reflex_vertices_of_cup():
    assert reflex_vertices(CUP).tolist() == [4, 5]


def test_drop_collinear():
    poly = [[0, 0], [0.5, 0], [1, 0], [1, 0.25], [1, 1], [0, 1]]
    np.testing.assert_array_equal(drop_collinear(poly), [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_convex_overlap():
    a = rect(0, 0, 1, 1)
    assert not convex_overlap(a, rect(1, 0, 2, 1))          # shared edge
    assert not convex_overlap(a, rect(1, 1, 2, 2))          # shared corner
    assert not convex_overlap(a, rect(1.5, 0, 2, 1))        # apart
    assert convex_overlap(a, rect(0.9, 0.9, 2, 2))
    assert convex_overlap(a, rect(0.25, 0.25, 0.5, 0.5))    # contained


# ---------------------------------------------------------------- decomposition

@pytest.mark.parametrize('poly, reflex', [(L_SHAPE, 1), (CUP, 2)], ids=['L', 'cup'])
def test_decomposition_of_known_shapes(poly, reflex):
    pieces = convex_decomposition(poly)
    # Hertel–Mehlhorn keeps at most two diagonals per reflex vertex.
    assert 2 <= len(pieces) <= 2 * reflex + 1
    assert_valid_decomposition(poly, pieces)
    size = np.ptp(poly, axis=0).max()
    assert_same_mass_properties(mass_properties(pieces, mass=0.01),
                                mass_properties([poly], mass=0.01), size)
    area, centroid, second = union_of_rectangles(L_RECTS if reflex == 1 else CUP_RECTS)
    props = mass_properties(pieces, density=1.0)
    assert props.mass == pytest.approx(area, rel=REL)
    assert props.inertia == pytest.approx(second, rel=REL)


def test_decomposition_of_convex_polygon_is_itself():
    pieces = convex_decomposition([[0, 0], [0.5, 0], [1, 0], [1, 1], [0, 1]])
    assert len(pieces) == 1
    np.testing.assert_array_equal(pieces[0], [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_decomposition_drops_collinear_vertices():
    with_midpoints = np.array([[0, 0], [1, 0], [2, 0], [2, 1], [1, 1], [1, 2], [1, 3], [0, 3],
                               [0, 1.5]], dtype=float)
    pieces = convex_decomposition(with_midpoints)
    assert_valid_decomposition(with_midpoints, pieces)
    assert polygon_area(with_midpoints) == pytest.approx(polygon_area(L_SHAPE), rel=REL)


def test_decomposition_of_comb():
    # A base 9 x 1 with five teeth 1 x 3 on top: eight reflex vertices and long thin ears.
    outline = [(0, 0), (9, 0)]
    for k in reversed(range(5)):
        x = 2 * k
        outline += [(x + 1, 4), (x, 4)] + ([(x, 1), (x - 1, 1)] if k > 0 else [])
    comb = np.array(outline, dtype=float)
    assert is_simple(comb)[0] and polygon_area(comb) > 0
    pieces = convex_decomposition(comb)
    assert_valid_decomposition(comb, pieces, samples=5000)
    assert polygon_area(comb) == pytest.approx(9 * 1 + 5 * 3, rel=REL)
    assert len(pieces) <= 2 * len(reflex_vertices(comb)) + 1


def test_decomposition_rejects_bad_input():
    with pytest.raises(ValueError, match='clockwise'):
        convex_decomposition(L_SHAPE[::-1])
    with pytest.raises(ValueError, match='self-intersecting'):
        convex_decomposition([[0, 0], [1, 1], [1, 0], [0, 1]])


@st.composite
def star_polygons(draw):
    """Random simple polygons, star-shaped about a random centre, in random scale and place."""
    n = draw(st.integers(min_value=3, max_value=24))
    gaps = np.array(draw(st.lists(st.floats(1.0, 10.0), min_size=n, max_size=n)))
    radii = np.array(draw(st.lists(st.floats(0.1, 1.0), min_size=n, max_size=n)))
    start = draw(st.floats(0.0, 2 * np.pi))
    scale = draw(st.sampled_from([1e-3, 1e-2, 1.0]))
    centre = np.array(draw(st.tuples(st.floats(-5, 5), st.floats(-5, 5))))
    angles = start + 2 * np.pi * np.cumsum(gaps) / gaps.sum()
    # A gap of pi or more would put the centre outside the kernel (the outline would fold).
    assume(np.max(gaps) / gaps.sum() < 0.45)
    poly = centre * scale + scale * radii[:, None] * np.column_stack([np.cos(angles),
                                                                      np.sin(angles)])
    # Keep clear of the collinear tolerance, which legitimately moves the outline by ~1e-12.
    e_in = poly - np.roll(poly, 1, axis=0)
    e_out = np.roll(poly, -1, axis=0) - poly
    sines = (e_in[:, 0] * e_out[:, 1] - e_in[:, 1] * e_out[:, 0]) / (
        np.hypot(*e_in.T) * np.hypot(*e_out.T))
    assume(np.min(np.abs(sines)) > 1e-6)
    return poly


@settings(max_examples=150, deadline=None)
@given(star_polygons())
def test_decomposition_of_random_star_polygons(poly):
    assert is_simple(poly) == (True, '')
    pieces = convex_decomposition(poly)
    reflex = len(reflex_vertices(poly))
    assert len(pieces) <= 2 * reflex + 1
    assert_valid_decomposition(poly, pieces, samples=500)
    size = np.ptp(poly, axis=0).max()
    assert_same_mass_properties(mass_properties(pieces, mass=0.02),
                                mass_properties([poly], mass=0.02), size)


# ---------------------------------------------------------------- frames and normals

@given(st.floats(-20.0, 20.0), st.floats(-20.0, 20.0))
def test_rotation_is_orthonormal_and_composes(a, b):
    r = rotation(a)
    np.testing.assert_allclose(r @ r.T, np.eye(2), rtol=0, atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(r @ [1.0, 0.0], [math.cos(a), math.sin(a)], rtol=0, atol=1e-15)
    np.testing.assert_allclose(rotation(a) @ rotation(b), rotation(a + b), rtol=0, atol=1e-14)


def test_rotation_quarter_turn():
    np.testing.assert_allclose(rotation(np.pi / 2), [[0, -1], [1, 0]], rtol=0, atol=1e-16)


def test_edge_normals_of_square():
    np.testing.assert_array_equal(edge_normals(rect(0, 0, 2, 2)),
                                  [[0, -1], [1, 0], [0, 1], [-1, 0]])


def test_edge_normals_are_outward_unit_and_perpendicular():
    hexagon = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 7)[:-1]])
    hexagon = hexagon * [2.0, 0.5] + [3.0, -1.0]
    normals = edge_normals(hexagon)
    edges = np.roll(hexagon, -1, axis=0) - hexagon
    midpoints = hexagon + edges / 2
    np.testing.assert_allclose(np.hypot(*normals.T), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.sum(normals * edges, axis=1), 0.0, rtol=0, atol=1e-15)
    assert np.all(np.sum(normals * (midpoints - polygon_centroid(hexagon)), axis=1) > 0)
