"""Planar polygon geometry: areas, centroids, second moments, validity tests, convex decomposition.

Conventions used throughout:

* A polygon is an (n, 2) array-like of vertices in metres, without a repeated closing vertex.
  Counter-clockwise (CCW) order gives a positive signed area.
* Edge k joins vertex k to vertex k + 1 (mod n); vertices and edges are counted from 0, like the
  list indices of a scene file.
* Predicates are tolerant at the level of floating-point round-off, scaled by the polygon's size
  (the larger side of its bounding box): points closer than ``REL_TOL * size`` coincide, and a
  vertex whose turning angle has a sine below ``ANGLE_TOL`` is collinear with its neighbours.

Pure numpy, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    'ANGLE_TOL', 'REL_TOL', 'MassProperties', 'convex_decomposition', 'convex_overlap',
    'drop_collinear', 'edge_normals', 'is_convex', 'is_simple', 'mass_properties',
    'polygon_area', 'polygon_centroid', 'polygon_second_moment', 'reflex_vertices', 'rotation',
]

#: Relative size below which lengths (times the polygon size) and areas (times size**2) are zero.
#: Far below any meaningful feature of a part, yet well above float64 round-off.
REL_TOL = 1e-12
#: Sine of a turning angle below which a vertex counts as collinear (a straight-through vertex).
ANGLE_TOL = 1e-12


def _as_vertices(vertices, min_count: int = 3) -> np.ndarray:
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2:
        raise ValueError(f'expected an (n, 2) array of vertices, got shape {v.shape}')
    if len(v) < min_count:
        raise ValueError(f'a polygon needs at least {min_count} vertices, got {len(v)}')
    if not np.all(np.isfinite(v)):
        raise ValueError('vertex coordinates must be finite')
    return v


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _size(v: np.ndarray) -> float:
    return float(np.max(np.ptp(v, axis=0)))


def _turn_sines(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sine and cosine of the turning angle at every vertex (positive sine = left turn).

    Zero-length edges give nan, so callers must reject repeated vertices first or treat nan as
    invalid.
    """
    e_in = v - np.roll(v, 1, axis=0)
    e_out = np.roll(v, -1, axis=0) - v
    norm = np.hypot(*e_in.T) * np.hypot(*e_out.T)
    with np.errstate(invalid='ignore', divide='ignore'):
        sin = _cross(e_in, e_out) / norm
        cos = np.sum(e_in * e_out, axis=1) / norm
    return sin, cos


def rotation(theta: float) -> np.ndarray:
    """2x2 matrix rotating vectors counter-clockwise by ``theta`` (rad)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def polygon_area(vertices) -> float:
    """Signed area (m^2) by the shoelace formula; positive for CCW vertices."""
    v = _as_vertices(vertices)
    # Measuring from the first vertex keeps the products small for parts far from the origin.
    p = v - v[0]
    return 0.5 * float(np.sum(_cross(p, np.roll(p, -1, axis=0))))


def polygon_centroid(vertices) -> np.ndarray:
    """Centroid (m) of the polygon's area, shape (2,). Raises ValueError for zero area."""
    v = _as_vertices(vertices)
    ref = v[0]
    p = v - ref
    q = np.roll(p, -1, axis=0)
    c = _cross(p, q)
    twice_area = float(np.sum(c))
    if abs(twice_area) <= REL_TOL * _size(v) ** 2:
        raise ValueError('polygon has zero area, so its centroid is undefined')
    return ref + np.sum((p + q) * c[:, None], axis=0) / (3.0 * twice_area)


def polygon_second_moment(vertices, about) -> float:
    """Polar second moment of area ∫ r² dA (m^4) about the point ``about`` (m).

    This is the moment of inertia per unit areal density. Signed like the area: positive for CCW.
    """
    v = _as_vertices(vertices)
    p = v - np.asarray(about, dtype=float).reshape(2)
    q = np.roll(p, -1, axis=0)
    c = _cross(p, q)
    x0, y0, x1, y1 = p[:, 0], p[:, 1], q[:, 0], q[:, 1]
    return float(np.sum(c * (x0 * x0 + x0 * x1 + x1 * x1 + y0 * y0 + y0 * y1 + y1 * y1))) / 12.0


def edge_normals(vertices) -> np.ndarray:
    """Outward unit normals (n, 2) of the edges k -> k+1 of a CCW polygon."""
    v = _as_vertices(vertices)
    e = np.roll(v, -1, axis=0) - v
    length = np.hypot(e[:, 0], e[:, 1])
    if np.any(length <= REL_TOL * _size(v)):
        raise ValueError('polygon has a zero-length edge (repeated vertex)')
    return np.column_stack([e[:, 1], -e[:, 0]]) / length[:, None]


def reflex_vertices(vertices, tol: float = ANGLE_TOL) -> np.ndarray:
    """Indices of the vertices where a CCW polygon turns right (interior angle above 180°)."""
    sin, _ = _turn_sines(_as_vertices(vertices))
    return np.flatnonzero(~(sin >= -tol))


def is_convex(vertices, tol: float = ANGLE_TOL) -> bool:
    """True if the polygon is convex, counter-clockwise and non-degenerate.

    Collinear (straight-through, 180°) vertices are allowed: they do not change the shape, and
    :func:`drop_collinear` removes them. A vertex counts as collinear when the sine of its turning
    angle is within ``tol``. Spikes (an edge that doubles back), repeated vertices, clockwise order
    and outlines that wind around more than once (a pentagram) are not convex.
    """
    v = _as_vertices(vertices)
    sin, cos = _turn_sines(v)
    if not np.all(np.isfinite(sin)):
        return False
    straight = np.abs(sin) <= tol
    if np.any(sin < -tol) or np.any(straight & (cos < 0)):
        return False
    # All turns are left turns; a convex polygon turns through exactly one full circle.
    total_turn = float(np.sum(np.arctan2(sin, cos)))
    return abs(total_turn - 2 * np.pi) < 1e-6 and polygon_area(v) > REL_TOL * _size(v) ** 2


def drop_collinear(vertices, tol: float = ANGLE_TOL) -> np.ndarray:
    """The polygon without its straight-through vertices (turning-angle sine within ``tol``)."""
    v = _as_vertices(vertices)
    sin, cos = _turn_sines(v)
    keep = ~((np.abs(sin) <= tol) & (cos > 0))
    return v[keep].copy()


def _points_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """Which points p lie on the segments ab (element-wise), given that they are collinear."""
    lo = np.minimum(a, b) - tol
    hi = np.maximum(a, b) + tol
    return np.all((p >= lo) & (p <= hi), axis=-1)


def is_simple(vertices) -> tuple[bool, str]:
    """Whether the polygon is simple (and non-degenerate), with a reason when it is not.

    Simple means: at least 3 finite vertices, no two vertices at the same point, non-zero area,
    no edge doubling back over its neighbour, and no two edges meeting except neighbours at their
    shared vertex. Either orientation is accepted. The reason reads after "polygon is", for
    example ``'self-intersecting (edges 1 and 3 cross)'``.
    """
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2:
        return False, f'not an (n, 2) array of vertices (shape {v.shape})'
    n = len(v)
    if n < 3:
        return False, f'too small (at least 3 vertices are needed, got {n})'
    if not np.all(np.isfinite(v)):
        return False, 'invalid (vertex coordinates must be finite)'
    size = _size(v)
    if size == 0.0:
        return False, 'degenerate (all vertices are at the same point)'
    len_tol = REL_TOL * size
    area_tol = REL_TOL * size * size

    gap = np.hypot(*(v[:, None, :] - v[None, :, :]).transpose(2, 0, 1))
    i, j = np.nonzero(np.triu(gap <= len_tol, k=1))
    if len(i):
        if (i[0], j[0]) == (0, n - 1):
            return False, (f'degenerate (the last vertex {n - 1} repeats the first; '
                           'do not close the outline)')
        return False, f'degenerate (vertices {i[0]} and {j[0]} coincide)'

    spread = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
    if spread[1] <= len_tol * np.sqrt(n):
        return False, 'degenerate (zero area: all vertices lie on one line)'

    sin, cos = _turn_sines(v)
    back = np.flatnonzero((np.abs(sin) <= ANGLE_TOL) & (cos < 0))
    if len(back):
        k = int(back[0])
        return False, (f'degenerate (the outline doubles back at vertex {k}: edges {(k - 1) % n} '
                       f'and {k} overlap)')

    a, b = v, np.roll(v, -1, axis=0)
    ii, jj = np.triu_indices(n, k=2)
    non_adjacent = ~((ii == 0) & (jj == n - 1))
    ii, jj = ii[non_adjacent], jj[non_adjacent]
    if len(ii) == 0:
        return True, ''  # a triangle with distinct, non-collinear vertices
    pa, pb, pc, pd = a[ii], b[ii], a[jj], b[jj]
    o1 = _cross(pb - pa, pc - pa)
    o2 = _cross(pb - pa, pd - pa)
    o3 = _cross(pd - pc, pa - pc)
    o4 = _cross(pd - pc, pb - pc)
    s1, s2, s3, s4 = (np.where(np.abs(o) <= area_tol, 0, np.sign(o)) for o in (o1, o2, o3, o4))
    crossing = (s1 * s2 < 0) & (s3 * s4 < 0)
    # A vertex lying on a non-adjacent edge makes the outline touch itself.
    touch_c = (s1 == 0) & _points_on_segments(pc, pa, pb, len_tol)
    touch_d = (s2 == 0) & _points_on_segments(pd, pa, pb, len_tol)
    touch_a = (s3 == 0) & _points_on_segments(pa, pc, pd, len_tol)
    touch_b = (s4 == 0) & _points_on_segments(pb, pc, pd, len_tol)
    bad = np.flatnonzero(crossing | touch_a | touch_b | touch_c | touch_d)
    if len(bad) == 0:
        if abs(polygon_area(v)) <= area_tol:
            return False, 'degenerate (zero area)'
        return True, ''
    k = int(bad[0])
    e1, e2 = int(ii[k]), int(jj[k])
    if crossing[k]:
        return False, f'self-intersecting (edges {e1} and {e2} cross)'
    for touch, vertex, edge in ((touch_c, e2, e1), (touch_d, (e2 + 1) % n, e1),
                                (touch_a, e1, e2), (touch_b, (e1 + 1) % n, e2)):
        if touch[k]:
            return False, f'self-touching (vertex {vertex} lies on edge {edge})'
    raise AssertionError('unreachable')


def convex_overlap(a, b, tol: float = 1e-9) -> bool:
    """True if two convex CCW polygons overlap with positive area.

    Separating-axis test over both polygons' edge normals. Polygons that only touch (share an edge
    or a vertex, or are apart by less than ``tol`` times their size) do not overlap.
    """
    a = _as_vertices(a)
    b = _as_vertices(b)
    gap_tol = tol * max(_size(a), _size(b))
    for axis in np.vstack([edge_normals(a), edge_normals(b)]):
        pa, pb = a @ axis, b @ axis
        if pb.min() - pa.max() >= -gap_tol or pa.min() - pb.max() >= -gap_tol:
            return False
    return True


def convex_penetration(a, b) -> float:
    """How deep two convex polygons overlap (m): the smallest overlap of their projections on
    either polygon's edge normals (separating-axis test); <= 0 when they are apart."""
    a = _as_vertices(a)
    b = _as_vertices(b)
    depth = np.inf
    for axis in np.vstack([edge_normals(a), edge_normals(b)]):
        pa, pb = a @ axis, b @ axis
        depth = min(depth, pa.max() - pb.min(), pb.max() - pa.min())
        if depth <= 0.0:
            break
    return float(depth)


def min_width(vertices) -> float:
    """The smallest width of a convex polygon (m): its thinnest projection on an edge normal."""
    v = _as_vertices(vertices)
    spans = v @ edge_normals(v).T
    return float(np.min(spans.max(axis=0) - spans.min(axis=0)))


def _triangulate(v: np.ndarray) -> list[tuple[int, int, int]]:
    """Ear-clipping triangulation of a simple CCW polygon, as CCW index triples."""
    area_tol = REL_TOL * _size(v) ** 2
    remaining = list(range(len(v)))
    triangles = []

    def find_ear(strict: bool) -> int | None:
        idx = np.array(remaining)
        p = v[idx]
        prev, nxt = np.roll(p, 1, axis=0), np.roll(p, -1, axis=0)
        convex = _cross(p - prev, nxt - p) > area_tol
        m = len(idx)
        for k in np.flatnonzero(convex):
            a, b, c = prev[k], p[k], nxt[k]
            others = np.delete(p, [(k - 1) % m, k, (k + 1) % m], axis=0)
            # Another vertex inside the triangle (or on it, unless strict) blocks the ear: clipping
            # it would cut through the polygon or leave a degenerate remainder.
            lim = area_tol if strict else -area_tol
            inside = ((_cross(b - a, others - a) > lim) & (_cross(c - b, others - b) > lim)
                      & (_cross(a - c, others - c) > lim))
            if not np.any(inside):
                return int(k)
        return None

    while len(remaining) > 3:
        k = find_ear(strict=False)
        if k is None:
            # Only near-degenerate input gets here: accept ears with vertices on their boundary.
            k = find_ear(strict=True)
        if k is None:
            raise ValueError('triangulation failed: is the polygon simple and counter-clockwise?')
        m = len(remaining)
        triangles.append((remaining[(k - 1) % m], remaining[k], remaining[(k + 1) % m]))
        del remaining[k]
    triangles.append(tuple(remaining))
    return triangles


def _merge_convex(v: np.ndarray, triangles: list[tuple[int, int, int]],
                  tol: float) -> list[list[int]]:
    """Hertel–Mehlhorn: drop every diagonal whose removal keeps both neighbouring pieces convex.

    The result has at most four times the minimum number of convex pieces.
    """
    pieces: dict[int, list[int]] = {}
    owner: dict[tuple[int, int], int] = {}
    for pid, tri in enumerate(triangles):
        pieces[pid] = list(tri)
        for s in range(3):
            owner[(tri[s], tri[(s + 1) % 3])] = pid
    diagonals = [(a, b) for (a, b) in owner if (b, a) in owner and a < b]
    next_id = len(triangles)

    def turns_left(prev: int, here: int, nxt: int) -> bool:
        e_in, e_out = v[here] - v[prev], v[nxt] - v[here]
        sin = _cross(e_in, e_out) / (np.hypot(*e_in) * np.hypot(*e_out))
        return bool(sin >= -tol)

    for a, b in diagonals:
        p_id, q_id = owner[(a, b)], owner[(b, a)]
        p, q = pieces[p_id], pieces[q_id]
        # Walk p from b round to a, then q from a round to b: the union's CCW boundary.
        ip, iq = p.index(b), q.index(a)
        p_run = p[ip:] + p[:ip]
        q_run = q[iq:] + q[:iq]
        merged = p_run + q_run[1:-1]
        m = len(merged)
        ia, ib = merged.index(a), merged.index(b)
        if not (turns_left(merged[ia - 1], a, merged[(ia + 1) % m])
                and turns_left(merged[ib - 1], b, merged[(ib + 1) % m])):
            continue
        del pieces[p_id], pieces[q_id]
        del owner[(a, b)], owner[(b, a)]
        pieces[next_id] = merged
        for s in range(m):
            owner[(merged[s], merged[(s + 1) % m])] = next_id
        next_id += 1
    return list(pieces.values())


def convex_decomposition(vertices, tol: float = ANGLE_TOL) -> list[np.ndarray]:
    """Split a simple CCW polygon into convex CCW pieces that tile it without overlap.

    Ear clipping into triangles, then Hertel–Mehlhorn merging across diagonals. Collinear
    vertices (see :func:`is_convex`) are removed from the input and the pieces. A convex input is
    returned as a single piece. Raises ValueError if the polygon is not simple or is clockwise.
    """
    v = _as_vertices(vertices)
    ok, reason = is_simple(v)
    if not ok:
        raise ValueError(f'polygon is {reason}')
    if polygon_area(v) <= 0:
        raise ValueError('polygon is clockwise; convex_decomposition needs counter-clockwise '
                         'order')
    v = drop_collinear(v, tol)
    if is_convex(v, tol):
        return [v]
    index_pieces = _merge_convex(v, _triangulate(v), tol)
    return [drop_collinear(v[idx], tol) for idx in index_pieces]


@dataclass(frozen=True, eq=False)
class MassProperties:
    """Rigid-body mass properties of a planar body.

    ``mass`` in kg, ``inertia`` in kg m^2 about the centroid (perpendicular axis), ``centroid`` in
    m in the body frame (read-only array of shape (2,)).
    """

    mass: float
    inertia: float
    centroid: np.ndarray

    def __post_init__(self):
        centroid = np.array(self.centroid, dtype=float).reshape(2)
        centroid.flags.writeable = False
        object.__setattr__(self, 'centroid', centroid)

    def __eq__(self, other):
        if not isinstance(other, MassProperties):
            return NotImplemented
        return (self.mass == other.mass and self.inertia == other.inertia
                and bool(np.array_equal(self.centroid, other.centroid)))


def mass_properties(pieces: Sequence[np.ndarray], *, mass: float | None = None,
                    density: float | None = None) -> MassProperties:
    """Mass, central moment of inertia and centroid of a body made of non-overlapping CCW pieces.

    Give exactly one of ``mass`` (kg) or ``density`` (areal, kg/m^2); the body is uniform.
    """
    if (mass is None) == (density is None):
        raise ValueError('give exactly one of mass or density')
    scale = mass if mass is not None else density
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f'mass/density must be positive and finite, got {scale!r}')
    if len(pieces) == 0:
        raise ValueError('a body needs at least one piece')
    polys = [_as_vertices(p) for p in pieces]
    areas = np.array([polygon_area(p) for p in polys])
    for k, (p, area) in enumerate(zip(polys, areas)):
        if area <= REL_TOL * _size(p) ** 2:
            raise ValueError(f'piece {k} is clockwise or has zero area (signed area {area:g} m^2)')
    total_area = float(np.sum(areas))
    centroids = np.array([polygon_centroid(p) for p in polys])
    centroid = np.sum(centroids * areas[:, None], axis=0) / total_area
    second_moment = sum(polygon_second_moment(p, centroid) for p in polys)
    rho = density if density is not None else mass / total_area
    return MassProperties(mass=float(rho * total_area) if mass is None else float(mass),
                          inertia=float(rho * second_moment), centroid=centroid)
