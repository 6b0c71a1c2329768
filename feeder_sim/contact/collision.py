"""Collision detection for rigid polygonal bodies (vertex–edge contact model).

Contact model (Kawachi et al.; Baraff 1989): every body is a compound of convex pieces and a
contact is a *vertex* of one body against an *edge* of another.  An edge lying on an edge is
represented by the two vertex–edge contacts of the end vertices that lie on the other edge.

There is no fixed slop: gaps are exact to floating point and the only tolerances are the
caller's ``margin`` / ``depth`` and a few tiny relative tolerances (``param_tol`` and
``angle_tol``, both 1e-9 by default, plus rounding-level tie breaking).

Pipeline of :func:`find_contacts`
---------------------------------
1. World coordinates of all vertices, exact per-piece AABBs (:func:`body_bounds`).
2. Broad phase (:func:`candidate_pairs`): sort-and-sweep along the axis over which the piece
   centres spread most, fully vectorised (``argsort`` + ``searchsorted`` + a CSR expansion), so
   the cost is O(P log P + pairs overlapping on the sweep axis).
3. Narrow phase, vectorised over all candidate pairs with the same vertex counts
   (``(pairs, m_a, m_b)`` arrays), both directions (vertices of P against edges of Q and
   vertices of Q against edges of P).  A vertex v is in contact with edge j of the other piece
   when

   * d_j(v) = n_j·(v − q_j) is the largest over that piece's edges that pass the two tests
     below (the least-penetrated face v can touch; among faces tied to rounding level the
     first is taken).  The least-penetrated face of all may fail them: a corner sunk into a
     face while lying exactly on the line of the end face next to it (boxes stacked flush,
     cups sitting rim on rim) is 0 from that end face, which its own edges point into; it
     takes the face it actually entered, where taking none let it sink through,
   * the vertex is inside or within ``margin`` of the piece: the largest d over *all* its
     edges is at most ``margin`` (plus the tie),
   * ``-depth <= d_j(v) <= margin``,
   * the projection parameter t lies in ``[-param_tol, 1 + param_tol]`` (the *unclipped* t is
     stored in ``Contacts.edge_param``),
   * v is a supporting vertex: for both neighbours u of v in its piece
     n_j·(u − v) >= −max(margin, angle_tol·|u − v|), i.e. the piece lies on the far side of the
     edge locally.  An exactly (or nearly) parallel adjacent edge therefore counts, so a box
     resting flat yields both bottom corners.
4. Clean-up (deterministic): contacts on parts of edges that are internal to a compound body
   are removed, vertex-on-vertex pairs are reduced to one contact, duplicates of the same
   body-frame vertex against parallel edges of one body are merged, and the result is sorted.

Steps 2-4 run in numba kernels (``_collision_kernels.narrow_phase``, ``clean_contacts``);
their sweep finds the pairs of :func:`candidate_pairs`, the vectorised broad phase kept here
for callers that want the pairs alone. They are compiled because a scene of few pieces, such
as one box on a track, gives a search little work: vectorised in numpy, its cost would be
mostly numpy's fixed cost per call (``benchmarks/conveying.py`` runs such a scene).

Compound bodies (concave parts, segmented tracks)
-------------------------------------------------
:attr:`ShapeSet.derived` analyses the pieces of each body once:

* A vertex is *active* (may be a contact vertex) only if it is a strictly convex corner of the
  union of its body's pieces.  Vertices on a flat stretch (the seam vertices where two pieces
  of a cup or a segmented track meet on the outer boundary, collinear vertices of a single
  piece) and reflex corners are never contact vertices: an edge resting on such a flat
  stretch is fully represented by the real corners at the ends.  Hence a vertex shared by two
  pieces at a seam produces **no** contact at all (rather than one per piece); no
  world-position de-duplication is needed for it.
* Edge portions whose outer side is covered by another piece of the same body are
  *internal*.  Fully internal edges take no part in the least-penetrated-face search and a
  contact whose (clipped) projection falls on an internal portion is dropped.  This removes
  phantom "walls" at seams of segmented tracks.
* Vertices of different pieces of one body that coincide (relative tolerance 1e-10 of the
  body size) share a canonical id.  Contacts of the same canonical vertex against edges of the
  same body with parallel normals (angle < ``angle_tol``) are merged, keeping the smallest gap
  (ties: lowest vertex index, then lowest edge index).

Vertex on vertex
----------------
When a corner v of body A touches a corner w of body B, both "v against an edge of B ending
at w" and "w against an edge of A ending at v" may qualify (both projection parameters
within ``param_tol`` of the respective end).  Only one is kept: **the contact whose edge
belongs to the lower-numbered body** (so its vertex belongs to the higher-numbered body).
With a static track numbered first, the normal is then the track's.

Ordering
--------
Contacts are sorted by body pair (min body, max body), then ``piece_a``, ``vertex_a``,
``piece_b``, ``edge_b``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math

import numpy as np

from feeder_sim.compiled.arena import heap_state
from feeder_sim.contact._collision_kernels import (
    clean_contacts,
    narrow_phase,
    NarrowPhaseTolerances,
)
from feeder_sim.model.shapes import ANGLE_TOL, PARAM_TOL, ShapeSet

__all__ = [
    "ANGLE_TOL",
    "DEPTH_FRACTION",
    "PARAM_TOL",
    "TIE_REL",
    "Contacts",
    "body_bounds",
    "candidate_pairs",
    "evaluate_gaps",
    "find_contacts",
]

#: Default ``depth`` = DEPTH_FRACTION * the smaller minimum width of the two pieces.
DEPTH_FRACTION = 0.25
#: Tie tolerance for the least-penetrated-face search, relative to the coordinate scale.
TIE_REL = 1e3 * np.finfo(float).eps

_INT = np.intp


# --------------------------------------------------------------------------------------------
# Contacts
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Contacts:
    """Vertex–edge contacts. Body a owns the vertex, body b owns the edge; the normal is the
    edge's outward normal (points from b toward a)."""

    body_a: np.ndarray  # (k,) int
    piece_a: np.ndarray  # (k,) int
    vertex_a: np.ndarray  # (k,) int, global index into ShapeSet.vertices
    body_b: np.ndarray  # (k,) int
    piece_b: np.ndarray  # (k,) int
    edge_b: np.ndarray  # (k,) int, global index of the edge's first vertex
    point: np.ndarray  # (k, 2) world position of the vertex, m
    normal: np.ndarray  # (k, 2) world unit normal of the edge
    gap: np.ndarray  # (k,) signed distance of the vertex from the edge's line, m (<0: penetration)
    edge_param: np.ndarray  # (k,) unclipped projection parameter along the edge (0 = first vertex)

    @property
    def n(self) -> int:
        return len(self.gap)

    @staticmethod
    def empty() -> Contacts:
        i = np.empty(0, dtype=_INT)
        return Contacts(i, i.copy(), i.copy(), i.copy(), i.copy(), i.copy(),
                        np.empty((0, 2)), np.empty((0, 2)), np.empty(0), np.empty(0))

    def take(self, index: np.ndarray) -> Contacts:
        """Subset (or reordering) of the contacts selected by an index or boolean mask."""
        return Contacts(*(np.asarray(getattr(self, f))[index] for f in CONTACT_FIELDS))


#: Names of the :class:`Contacts` arrays, in constructor order.
CONTACT_FIELDS = tuple(f.name for f in fields(Contacts))


# --------------------------------------------------------------------------------------------
# Geometry helpers (shared by find_contacts and evaluate_gaps so both give identical bits)
# --------------------------------------------------------------------------------------------


def _rotate(local: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    x, y = local[..., 0], local[..., 1]
    return np.stack((c * x - s * y, s * x + c * y), axis=-1)


def _world(local: np.ndarray, pos: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    x, y = local[..., 0], local[..., 1]
    return np.stack((pos[..., 0] + (c * x - s * y), pos[..., 1] + (s * x + c * y)), axis=-1)


def _check_state(shapes: ShapeSet, position, angle) -> tuple[np.ndarray, np.ndarray]:
    position = np.asarray(position, dtype=float)
    angle = np.asarray(angle, dtype=float)
    if position.ndim != 2 or position.shape[1] != 2 or angle.shape != (len(position),):
        raise ValueError("position must be (n, 2) and angle (n,)")
    if len(position) < shapes.n_bodies:
        raise ValueError(f"{shapes.n_bodies} bodies own pieces but only {len(position)} given")
    return position, angle


def _world_geometry(shapes: ShapeSet, position, angle):
    position, angle = _check_state(shapes, position, angle)
    vb = shapes.derived.vertex_body
    c, s = np.cos(angle), np.sin(angle)
    w = _world(shapes.vertices, position[vb], c[vb], s[vb])
    nw = _rotate(shapes.normals, c[vb], s[vb])
    return position, w, nw


def _piece_aabb(w: np.ndarray, piece_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(piece_start) < 2:
        return np.empty((0, 2)), np.empty((0, 2))
    idx = piece_start[:-1]
    return np.minimum.reduceat(w, idx, axis=0), np.maximum.reduceat(w, idx, axis=0)


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR expansion: (owner, k) for k in range(counts[owner]), owner ascending."""
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(counts), dtype=_INT), counts)
    offset = np.arange(total, dtype=_INT) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, offset


# --------------------------------------------------------------------------------------------
# Broad phase
# --------------------------------------------------------------------------------------------


def _pieces_taking_part(body: np.ndarray, collides: np.ndarray,
                        dynamic: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Which pieces (of owning bodies ``body``) take part, and which of those are dynamic.

    Without ``dynamic`` every piece takes part and the colliding ones count as dynamic."""
    if dynamic is None:
        return np.ones(len(body), dtype=bool), collides[body]
    take = collides[body]
    return take, np.asarray(dynamic, dtype=bool).reshape(-1)[body] & take


def body_bounds(shapes: ShapeSet, position: np.ndarray,
                angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact world AABBs of every piece: ``(lo, hi)``, each (P, 2)."""
    _, w, _ = _world_geometry(shapes, position, angle)
    return _piece_aabb(w, shapes.piece_start)


def candidate_pairs(lo: np.ndarray, hi: np.ndarray, piece_body: np.ndarray,
                    collides: np.ndarray, margin: float, *,
                    dynamic: np.ndarray | None = None) -> np.ndarray:
    """Piece pairs ``(p, q)``, p < q, whose AABBs are within ``margin`` of each other.

    Two boxes qualify when on both axes ``lo_p <= hi_q + margin`` and ``lo_q <= hi_p + margin``
    (closed: touching boxes qualify).  Pieces of the same body are never paired.

    ``collides`` (n_bodies,) bool.  Without ``dynamic`` it is the dynamic-body mask: a pair is
    reported when at least one of its two bodies has ``collides`` True (so two static or
    kinematic bodies are never paired).  With ``dynamic`` given, ``collides`` selects the bodies
    that take part at all and a pair needs both bodies taking part and at least one dynamic.

    Sort-and-sweep along the axis over which the AABB centres spread most (ties: x); the
    result is sorted lexicographically.
    """
    lo = np.asarray(lo, dtype=float).reshape(-1, 2)
    hi = np.asarray(hi, dtype=float).reshape(-1, 2)
    body = np.asarray(piece_body, dtype=_INT).reshape(-1)
    collides = np.asarray(collides, dtype=bool).reshape(-1)
    margin = float(margin)
    if not margin >= 0.0 or not math.isfinite(margin):
        raise ValueError("margin must be finite and >= 0")
    if lo.shape != hi.shape or len(body) != len(lo):
        raise ValueError("lo, hi and piece_body must describe the same pieces")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ValueError("bounds must be finite with lo <= hi")
    out = np.empty((0, 2), dtype=_INT)
    if len(body) < 2:
        return out
    take, dyn = _pieces_taking_part(body, collides, dynamic)
    if not dyn.any():
        return out
    ids = np.flatnonzero(take)
    lo_t, hi_t = lo[ids], hi[ids]
    centre = 0.5 * (lo_t + hi_t)
    extent = centre.max(axis=0) - centre.min(axis=0)
    axis = 1 if extent[1] > extent[0] else 0
    other = 1 - axis
    order = np.argsort(lo_t[:, axis], kind="stable")
    ls, hs = lo_t[order, axis], hi_t[order, axis]
    end = np.searchsorted(ls, hs + margin, side="right")
    counts = end - np.arange(len(ls)) - 1
    first, offset = _expand(counts)
    a = ids[order[first]]
    b = ids[order[first + 1 + offset]]
    keep = ((lo[a, other] <= hi[b, other] + margin) & (lo[b, other] <= hi[a, other] + margin)
            & (body[a] != body[b]) & (dyn[a] | dyn[b]))
    a, b = a[keep], b[keep]
    p, q = np.minimum(a, b), np.maximum(a, b)
    o = np.lexsort((q, p))
    return np.column_stack((p[o], q[o])).astype(_INT, copy=False)


def find_contacts(shapes: ShapeSet, position: np.ndarray, angle: np.ndarray,
                  collides: np.ndarray, *, margin: float, depth: float | None = None,
                  dynamic: np.ndarray | None = None, param_tol: float = PARAM_TOL,
                  angle_tol: float = ANGLE_TOL) -> Contacts:
    """All vertex–edge contacts with ``-depth <= gap <= margin`` (see the module docstring).

    ``collides`` / ``dynamic``: as in :func:`candidate_pairs`.  ``depth`` defaults, per piece
    pair, to ``DEPTH_FRACTION`` times the smaller of the two pieces' minimum widths.
    """
    margin = float(margin)
    if not margin >= 0.0 or not math.isfinite(margin):
        raise ValueError("margin must be finite and >= 0")
    if depth is not None and not float(depth) >= 0.0:
        raise ValueError("depth must be >= 0")
    position, w, nw = _world_geometry(shapes, position, angle)
    topo = shapes.derived
    lo, hi = _piece_aabb(w, shapes.piece_start)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("bounds must be finite with lo <= hi")
    # widen by the edge-parameter tolerance so the broad phase never drops a narrow-phase hit
    bp_margin = margin + 2.0 * param_tol * topo.max_edge_length
    collides = np.asarray(collides, dtype=bool).reshape(-1)
    body = shapes.piece_body
    take, dyn = _pieces_taking_part(body, collides, dynamic)
    if len(body) < 2 or not dyn.any():
        return Contacts.empty()
    coord = np.abs(position).max(axis=1)
    tol = NarrowPhaseTolerances(
        bp_margin_m=bp_margin, margin_m=margin, depth_m=-1.0 if depth is None else float(depth),
        depth_fraction=DEPTH_FRACTION, tie_rel=TIE_REL, param_tol=float(param_tol),
        angle_tol=float(angle_tol))
    vert, edge, gap, t, _ = narrow_phase(
        heap_state(), w, nw, lo, hi, shapes.piece_start, body, take, dyn, topo.piece_width,
        coord, shapes.radius, topo.vertex_active, topo.edge_internal, topo.next_vertex,
        topo.prev_vertex, topo.edge_length, tol)
    if len(vert) == 0:
        return Contacts.empty()
    o = clean_contacts(heap_state(), vert, edge, gap, t, topo.cover_start, topo.cover_lo,
                       topo.cover_hi, topo.next_vertex, topo.vertex_canon, topo.vertex_body, nw,
                       len(shapes.vertices), int(body.max()) + 1, float(param_tol),
                       float(angle_tol))
    vert, edge = vert[o], edge[o]
    body_a, body_b = topo.vertex_body[vert], topo.vertex_body[edge]
    piece_a, piece_b = topo.vertex_piece[vert], topo.vertex_piece[edge]
    return Contacts(body_a=body_a, piece_a=piece_a, vertex_a=vert,
                    body_b=body_b, piece_b=piece_b, edge_b=edge,
                    point=w[vert], normal=nw[edge], gap=gap[o], edge_param=t[o])


# --------------------------------------------------------------------------------------------
# Re-evaluation of known features
# --------------------------------------------------------------------------------------------


def evaluate_gaps(shapes: ShapeSet, contacts: Contacts, position: np.ndarray,
                  angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(gap, edge_param)`` of the same vertex/edge features at another configuration.

    Smooth in the configuration (no feature switching, no clipping); at the configuration
    where ``contacts`` were found it reproduces their ``gap`` and ``edge_param`` bit for bit.
    """
    position, angle = _check_state(shapes, position, angle)
    topo = shapes.derived
    va = np.asarray(contacts.vertex_a, dtype=_INT)
    eb = np.asarray(contacts.edge_b, dtype=_INT)
    ba, bb = topo.vertex_body[va], topo.vertex_body[eb]
    c, s = np.cos(angle), np.sin(angle)
    p = _world(shapes.vertices[va], position[ba], c[ba], s[ba])
    q0 = _world(shapes.vertices[eb], position[bb], c[bb], s[bb])
    q1 = _world(shapes.vertices[topo.next_vertex[eb]], position[bb], c[bb], s[bb])
    n = _rotate(shapes.normals[eb], c[bb], s[bb])
    dx, dy = p[:, 0] - q0[:, 0], p[:, 1] - q0[:, 1]
    ex, ey = q1[:, 0] - q0[:, 0], q1[:, 1] - q0[:, 1]
    return n[:, 0] * dx + n[:, 1] * dy, (dx * ex + dy * ey) / (ex * ex + ey * ey)
