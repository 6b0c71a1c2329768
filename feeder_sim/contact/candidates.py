"""Corner-versus-piece candidates: which active corners may touch which convex pieces soon.

The event-driven and the impulse-based methods watch every candidate pair continuously (gaps,
times of impact) between searches, so the search is coarse and cheap: a corner of one body
against a convex piece of another, at least one of them dynamic, when their pieces' bounding
boxes lie within a margin. A driven body's boxes may be widened by the stroke it covers until
the next search, so a candidate list stays valid while the drive moves it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.jit import inner
from feeder_sim.model.world import State, World


class CornerPieceCandidates(NamedTuple):
    """Corners near pieces at one configuration (arrays of equal length c, or per body/piece)."""

    vertex: np.ndarray      # (c,) global vertex index of the corner
    piece: np.ndarray       # (c,) piece index
    corner_x: np.ndarray    # (V,) world x of every vertex, m
    corner_y: np.ndarray    # (V,) world y of every vertex, m
    box_lo: np.ndarray      # (P, 2) lower corner of every piece's (widened) box, m
    box_hi: np.ndarray      # (P, 2) upper corner, m


def corner_piece_candidates(world: World, state: State, active: np.ndarray, margin_m: float,
                            grow_m: np.ndarray | None = None) -> CornerPieceCandidates:
    """Active corners (``active``: global vertex indices) against pieces of other bodies whose
    boxes lie within ``margin_m`` of the corner's piece's box; ``grow_m`` (n,) widens each
    body's piece boxes (m). Needs at least two pieces."""
    sh, topo = world.shapes, world.shapes.derived
    vb, ps, pb = topo.vertex_body, sh.piece_start, sh.piece_body
    ang = state.angle[vb]
    c, s = np.cos(ang), np.sin(ang)
    v = sh.vertices
    wx = state.position[vb, 0] + c * v[:, 0] - s * v[:, 1]
    wy = state.position[vb, 1] + s * v[:, 0] + c * v[:, 1]
    lo = np.stack([np.minimum.reduceat(wx, ps[:-1]), np.minimum.reduceat(wy, ps[:-1])], 1)
    hi = np.stack([np.maximum.reduceat(wx, ps[:-1]), np.maximum.reduceat(wy, ps[:-1])], 1)
    if grow_m is not None:
        grow = grow_m[pb][:, None]
        lo = lo - grow
        hi = hi + grow
    near = np.all((lo[:, None, :] <= hi[None, :, :] + margin_m) &
                  (lo[None, :, :] <= hi[:, None, :] + margin_m), axis=2)
    dyn = world.dynamic[pb]
    near &= (pb[:, None] != pb[None, :]) & (dyn[:, None] | dyn[None, :])
    rows, cols = np.nonzero(near[topo.vertex_piece[active]])
    return CornerPieceCandidates(active[rows], cols, wx, wy, lo, hi)


# A line of arithmetic, inlined: compiled on its own, it was compiled again for each
# combination of array flags (read-only or not) its callers pass.
@inner(inline='always')
def world_point(pos, ang, body, local):
    """World coordinates (m) of point ``local`` of body ``body`` at poses ``pos``, ``ang``."""
    c, s = math.cos(ang[body]), math.sin(ang[body])
    return (pos[body, 0] + c * local[0] - s * local[1],
            pos[body, 1] + s * local[0] + c * local[1])
