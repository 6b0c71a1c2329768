"""The shape model: every body as a compound of convex pieces, analysed once.

A :class:`ShapeSet` holds all pieces of all bodies in body frames (vertices counter-clockwise,
outward edge normals); :attr:`ShapeSet.derived` (a :class:`ShapeTopology`) says which vertices
are real corners of each body's outline (active), which edge portions are internal to a
compound body, which vertices of different pieces coincide, and each piece's minimum width.
The contact stage (:mod:`feeder_sim.contact.collision`) reads it; the world owns it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from functools import cached_property
import math

import numpy as np

__all__ = ['ANGLE_TOL', 'PARAM_TOL', 'ShapeSet', 'ShapeTopology']

#: Default tolerance on the edge parameter t (dimensionless).
PARAM_TOL = 1e-9
#: Default angular tolerance (rad) for "parallel" tests.
ANGLE_TOL = 1e-9
#: Relative (to the body's radius) tolerance for coincidence of body-frame features.
_GEOM_REL_TOL = 1e-10

_INT = np.intp


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class ShapeTopology:
    """Per-vertex / per-piece data derived from a :class:`ShapeSet` (computed once, lazily)."""

    vertex_piece: np.ndarray  # (V,) piece owning each vertex
    vertex_body: np.ndarray  # (V,) body owning each vertex
    next_vertex: np.ndarray  # (V,) global index of the next vertex of the same piece
    prev_vertex: np.ndarray  # (V,) global index of the previous vertex of the same piece
    piece_size: np.ndarray  # (P,) number of vertices of each piece
    edge_length: np.ndarray  # (V,) length of edge i (vertex i -> next_vertex[i])
    piece_width: np.ndarray  # (P,) minimum width of each piece
    vertex_active: np.ndarray  # (V,) bool: strictly convex corner of the body's union
    edge_internal: np.ndarray  # (V,) bool: edge entirely covered by other pieces of its body
    cover_start: np.ndarray  # (V+1,) CSR into cover_lo/cover_hi: internal portions of edge i
    cover_lo: np.ndarray  # (c,) start parameter of an internal portion
    cover_hi: np.ndarray  # (c,) end parameter of an internal portion
    vertex_canon: np.ndarray  # (V,) lowest global index of a coincident vertex of the same body
    max_edge_length: float

    def __post_init__(self) -> None:
        # read-only: one topology is shared by every caller of the shape set
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                _frozen(value)


@dataclass(frozen=True, eq=False)
class ShapeSet:
    """All convex pieces of all bodies, in each body's centre-of-mass frame."""

    vertices: np.ndarray  # (V, 2) m; piece p is vertices[piece_start[p]:piece_start[p+1]], CCW
    piece_start: np.ndarray  # (P+1,) int
    piece_body: np.ndarray  # (P,) int, owning body index
    normals: np.ndarray  # (V, 2) outward unit normal of the edge from vertex i to the next one
    radius: np.ndarray  # (P,) max distance of the piece's vertices from its body's COM

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float).reshape(-1, 2)
        ps = np.asarray(self.piece_start, dtype=_INT).reshape(-1)
        pb = np.asarray(self.piece_body, dtype=_INT).reshape(-1)
        nm = np.asarray(self.normals, dtype=float).reshape(-1, 2)
        rd = np.asarray(self.radius, dtype=float).reshape(-1)
        if ps.size == 0 or ps[0] != 0 or ps[-1] != len(v):
            raise ValueError("piece_start must start at 0 and end at len(vertices)")
        if np.any(np.diff(ps) < 3):
            raise ValueError("every piece needs at least 3 vertices")
        if len(pb) != len(ps) - 1 or len(rd) != len(pb) or len(nm) != len(v):
            raise ValueError("inconsistent ShapeSet array lengths")
        if len(pb) and pb.min() < 0:
            raise ValueError("negative body index")
        for name, val in (("vertices", v), ("piece_start", ps), ("piece_body", pb),
                          ("normals", nm), ("radius", rd)):
            object.__setattr__(self, name, val)

    @property
    def n_pieces(self) -> int:
        return len(self.piece_body)

    @property
    def n_bodies(self) -> int:
        """1 + the largest body index that owns a piece (0 if there are no pieces)."""
        return int(self.piece_body.max()) + 1 if len(self.piece_body) else 0

    @classmethod
    def from_pieces(cls, pieces_per_body: Sequence[Sequence[np.ndarray]]) -> ShapeSet:
        """Build from ``pieces_per_body[b] = [piece, ...]``, each piece an (m, 2) convex polygon
        already expressed in body b's centre-of-mass frame.

        Clockwise pieces are reversed (stored CCW).  Collinear vertices are accepted (they are
        never contact vertices); reflex vertices, repeated vertices, zero area and
        self-overlapping vertex sequences raise ``ValueError``.  A body may have no pieces.
        """
        verts: list[np.ndarray] = []
        norms: list[np.ndarray] = []
        start = [0]
        body: list[int] = []
        radius: list[float] = []
        memo: dict[tuple, tuple[np.ndarray, np.ndarray, float]] = {}
        for b, pieces in enumerate(pieces_per_body):
            for piece in pieces:
                raw = np.array(piece, dtype=float)
                key = (raw.shape, raw.tobytes())
                if key not in memo:
                    p = _check_convex_piece(raw)
                    e = np.roll(p, -1, axis=0) - p
                    length = np.hypot(e[:, 0], e[:, 1])
                    memo[key] = (p, np.column_stack((e[:, 1], -e[:, 0])) / length[:, None],
                                 float(np.hypot(p[:, 0], p[:, 1]).max()))
                p, nm, r = memo[key]
                verts.append(p)
                norms.append(nm)
                start.append(start[-1] + len(p))
                body.append(b)
                radius.append(r)
        return cls(
            vertices=_frozen(np.concatenate(verts) if verts else np.empty((0, 2))),
            piece_start=_frozen(np.array(start, dtype=_INT)),
            piece_body=_frozen(np.array(body, dtype=_INT)),
            normals=_frozen(np.concatenate(norms) if norms else np.empty((0, 2))),
            radius=_frozen(np.array(radius, dtype=float)),
        )

    def with_body(self, body: int, pieces: Sequence[np.ndarray]) -> ShapeSet:
        """This set and ``pieces`` (checked as :meth:`from_pieces`' are) owned by ``body``,
        a body index above every one here: a part added to a running world, in time
        proportional to the arrays, not to the bodies' checks."""
        extra = ShapeSet.from_pieces([pieces])
        return ShapeSet(
            vertices=_frozen(np.concatenate((self.vertices, extra.vertices))),
            piece_start=_frozen(np.concatenate(
                (self.piece_start, extra.piece_start[1:] + len(self.vertices)))),
            piece_body=_frozen(np.concatenate((self.piece_body, extra.piece_body + body))),
            normals=_frozen(np.concatenate((self.normals, extra.normals))),
            radius=_frozen(np.concatenate((self.radius, extra.radius))),
        )

    def without_body(self, body: int) -> ShapeSet:
        """This set without the pieces of ``body``; the bodies above it move down by one."""
        keep = self.piece_body != body
        sizes = np.diff(self.piece_start)
        vertex_kept = np.repeat(keep, sizes)
        piece_body = self.piece_body[keep]
        return ShapeSet(
            vertices=_frozen(self.vertices[vertex_kept]),
            piece_start=_frozen(np.concatenate(([0], np.cumsum(sizes[keep]))).astype(_INT)),
            piece_body=_frozen(np.where(piece_body > body, piece_body - 1, piece_body)),
            normals=_frozen(self.normals[vertex_kept]),
            radius=_frozen(self.radius[keep]),
        )

    @cached_property
    def derived(self) -> ShapeTopology:
        """Derived topology (next/prev vertex, active corners, internal edges, ...)."""
        return _build_topology(self)


def _check_convex_piece(p: np.ndarray) -> np.ndarray:
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise ValueError(f"a piece must be an (m>=3, 2) array, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("piece vertices must be finite")
    e = np.roll(p, -1, axis=0) - p
    area2 = float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    if area2 < 0:
        p = p[::-1].copy()
        e = np.roll(p, -1, axis=0) - p
    length = np.hypot(e[:, 0], e[:, 1])
    scale = float(np.abs(p).max())
    if not area2 or np.any(length <= 1e-12 * scale):
        raise ValueError("degenerate piece (zero area or repeated vertex)")
    ein = np.roll(e, 1, axis=0)
    cross = ein[:, 0] * e[:, 1] - ein[:, 1] * e[:, 0]
    dot = ein[:, 0] * e[:, 0] + ein[:, 1] * e[:, 1]
    if np.any(cross < -1e-12 * np.roll(length, 1) * length):
        raise ValueError("piece is not convex (or not simple)")
    turning = float(np.sum(np.arctan2(cross, dot)))
    if abs(turning - 2 * math.pi) > 1e-6:
        raise ValueError("piece is not a simple convex polygon")
    return p


def _circ_max_gap(angles: list[float]) -> float:
    a = np.sort(np.mod(np.asarray(angles), 2 * math.pi))
    gaps = np.diff(np.concatenate((a, [a[0] + 2 * math.pi])))
    return float(gaps.max())


def _build_topology(s: ShapeSet) -> ShapeTopology:
    v, nrm, start = s.vertices, s.normals, s.piece_start
    n_v, n_p = len(v), len(s.piece_body)
    size = np.diff(start)
    vertex_piece = np.repeat(np.arange(n_p, dtype=_INT), size)
    vertex_body = s.piece_body[vertex_piece]
    base = start[:-1][vertex_piece]
    local = np.arange(n_v, dtype=_INT) - base
    next_vertex = base + (local + 1) % size[vertex_piece]
    prev_vertex = base + (local - 1) % size[vertex_piece]
    e = v[next_vertex] - v
    length = np.hypot(e[:, 0], e[:, 1])
    ein = e[prev_vertex]
    sin_turn = (ein[:, 0] * e[:, 1] - ein[:, 1] * e[:, 0]) / (length[prev_vertex] * length)
    active = sin_turn > math.sin(ANGLE_TOL)

    width = np.zeros(n_p)
    for m in np.unique(size):
        ps = np.flatnonzero(size == m)
        idx = start[ps][:, None] + np.arange(m)
        pv, pn = v[idx], nrm[idx]
        # depth[g, j, i] = n_j . (q_j - v_i) >= 0
        rel = pv[:, :, None, :] - pv[:, None, :, :]
        depth = np.einsum("gjk,gjik->gji", pn, rel)
        width[ps] = depth.max(axis=2).min(axis=1)

    canon = np.arange(n_v, dtype=_INT)
    internal = np.zeros(n_v, dtype=bool)
    covers: list[tuple[int, float, float]] = []
    body_pieces: dict[int, list[int]] = {}
    for p, b in enumerate(s.piece_body.tolist()):
        body_pieces.setdefault(b, []).append(p)
    memo: dict[tuple, tuple] = {}  # identical compound bodies are analysed once
    for pieces in body_pieces.values():
        if len(pieces) < 2:
            continue
        tol = _GEOM_REL_TOL * max(float(s.radius[pieces].max()), np.finfo(float).tiny)
        gidx = np.concatenate([np.arange(start[p], start[p + 1]) for p in pieces])
        sizes = size[pieces]
        bv, bn = v[gidx], nrm[gidx]
        key = (tuple(sizes.tolist()), tol, bv.tobytes(), bn.tobytes())
        if key not in memo:
            memo[key] = _compound(bv, bn, np.concatenate(([0], np.cumsum(sizes))), tol,
                                  active[gidx])
        act, can, cov = memo[key]
        active[gidx] = act
        canon[gidx] = gidx[can]
        covers.extend((int(gidx[i]), lo_, hi_) for i, lo_, hi_ in cov)
    covers.sort()
    cover_edge = np.array([c[0] for c in covers], dtype=_INT)
    cover_lo = np.array([c[1] for c in covers], dtype=float)
    cover_hi = np.array([c[2] for c in covers], dtype=float)
    bounds = np.flatnonzero(np.diff(cover_edge)) + 1  # covers are sorted by (edge, lo)
    for grp in np.split(np.arange(len(covers)), bounds) if covers else ():
        reach = 0.0
        for lo_, hi_ in zip(cover_lo[grp], cover_hi[grp], strict=True):
            if lo_ > reach + PARAM_TOL:
                break
            reach = max(reach, hi_)
        internal[cover_edge[grp[0]]] = reach >= 1.0 - PARAM_TOL
    cover_start = np.zeros(n_v + 1, dtype=_INT)
    np.add.at(cover_start, cover_edge + 1, 1)
    cover_start = np.cumsum(cover_start)
    return ShapeTopology(
        vertex_piece=vertex_piece, vertex_body=vertex_body, next_vertex=next_vertex,
        prev_vertex=prev_vertex, piece_size=size, edge_length=length, piece_width=width,
        vertex_active=active, edge_internal=internal, cover_start=cover_start,
        cover_lo=cover_lo, cover_hi=cover_hi, vertex_canon=canon,
        max_edge_length=float(length.max()) if n_v else 0.0,
    )


def _compound(v, nrm, start, tol, active_in):
    """Analyse one compound body given as local arrays (its pieces back to back).

    Returns (active, canon, covers): active corners, canonical (lowest coincident) local
    vertex indices, and internal edge portions as (local edge, t_lo, t_hi).
    """
    n_v = len(v)
    active = active_in.copy()
    canon = np.arange(n_v)
    covers: list[tuple[int, float, float]] = []
    n_p = len(start) - 1
    piece_of = np.repeat(np.arange(n_p), np.diff(start))

    def ang(vec):
        return math.atan2(vec[1], vec[0])

    for i in range(n_v):
        p = piece_of[i]
        a0, a1 = int(start[p]), int(start[p + 1])
        x = v[i]
        nxt = i + 1 if i + 1 < a1 else a0
        prv = i - 1 if i > a0 else a1 - 1
        gens = [ang(v[prv] - x), ang(v[nxt] - x)]
        is_active = bool(active[i])
        ev = v[nxt] - x
        elen = math.hypot(ev[0], ev[1])
        for q in range(n_p):
            if q == p:
                continue
            b0, b1 = int(start[q]), int(start[q + 1])
            qv, qn = v[b0:b1], nrm[b0:b1]
            # -- vertex i against piece q: coincident vertex, outside, or inside/on an edge
            if np.einsum("ij,ij->i", x - qv, qn).max() <= tol:
                dist = np.hypot(qv[:, 0] - x[0], qv[:, 1] - x[1])
                k = int(dist.argmin())
                if dist[k] <= tol:
                    canon[i] = min(canon[i], b0 + k)
                    gens.append(ang(qv[k - 1] - qv[k]))
                    gens.append(ang(qv[(k + 1) % (b1 - b0)] - qv[k]))
                else:
                    is_active = False  # inside q or on one of its edges: not a corner
            # -- portion of edge i (x -> v[nxt]) whose outer side lies inside piece q
            f0 = np.einsum("ij,ij->i", x - qv, qn)
            f1 = qn @ ev
            par = np.abs(f1) <= ANGLE_TOL * elen
            col = par & (np.abs(f0) <= tol)
            if np.any(col & (qn @ nrm[i] > 0)) or np.any(par & ~col & (f0 > 0)):
                continue
            cut = ~par
            tstar = -f0[cut] / f1[cut]
            up = f1[cut] > 0
            hi_ = min(1.0, float(tstar[up].min())) if up.any() else 1.0
            lo_ = max(0.0, float(tstar[~up].max())) if (~up).any() else 0.0
            if hi_ - lo_ > PARAM_TOL:
                covers.append((i, lo_, hi_))
        if is_active:
            is_active = _circ_max_gap(gens) > math.pi + ANGLE_TOL
        active[i] = is_active
    return active, canon, covers
