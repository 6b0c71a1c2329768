"""A world's constants as the compiled stepping methods take them: one pair of named tuples of
arrays, :class:`BodyArrays` (per body) and :class:`ShapeArrays` (the shape set and its
topology), built once per world by :func:`body_arrays` and :func:`shape_arrays`.

Every field is a fact of the :class:`~feeder_sim.model.world.World` (it does not change while
the simulation runs): what a method derives from its settings or from the time (the drive
table, step sizes, tolerances) travels in its own tuples.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from feeder_sim.model.world import DRIVEN, FIXED, MOVING, World


class BodyArrays(NamedTuple):
    """Per-body constants of a world, in the kernels' terms."""

    dynamic: np.ndarray        # (n,) bool
    dyn_idx: np.ndarray        # (nm,) indices of dynamic bodies
    driven_idx: np.ndarray     # (nd,) indices of driven bodies, the drive table's row order
    inv_mass: np.ndarray       # (n,) 1/kg
    inv_inertia: np.ndarray    # (n,) 1/(kg m^2)
    radius_m: np.ndarray       # (n,) largest distance of a vertex from the centre of mass
    mu_static: np.ndarray      # (n,)
    mu_dynamic: np.ndarray     # (n,)
    restitution: np.ndarray    # (n,)
    gravity: np.ndarray        # (2,) m/s^2
    g: float                   # |gravity|
    kind: np.ndarray           # (n,) int64: FIXED, DRIVEN (has a drive) or MOVING (dynamic)
    drive_row: np.ndarray      # (n,) int64: a driven body's row of the drive table, else -1


class ShapeArrays(NamedTuple):
    """The shape set and its topology (``ShapeSet``, ``ShapeTopology``)."""

    vertices: np.ndarray
    normals: np.ndarray
    piece_start: np.ndarray
    piece_body: np.ndarray
    piece_radius: np.ndarray
    vertex_body: np.ndarray
    vertex_piece: np.ndarray
    next_vertex: np.ndarray
    prev_vertex: np.ndarray
    edge_length: np.ndarray
    piece_width: np.ndarray
    vertex_active: np.ndarray
    edge_internal: np.ndarray
    cover_start: np.ndarray
    cover_lo: np.ndarray
    cover_hi: np.ndarray
    vertex_canon: np.ndarray
    n_piece_bodies: int        # one more than the largest body index owning a piece


def _floats(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=float)


def body_arrays(world: World) -> BodyArrays:
    """The per-body constants of ``world``."""
    dynamic = world.dynamic
    driven = world.driven
    kind = np.where(dynamic, MOVING, FIXED).astype(np.int64)
    kind[driven] = DRIVEN
    drive_row = np.full(world.n, -1, np.int64)
    drive_row[driven] = np.arange(len(driven))
    return BodyArrays(
        np.ascontiguousarray(dynamic, dtype=bool), np.flatnonzero(dynamic).astype(np.int64),
        driven.astype(np.int64), _floats(world.inv_mass), _floats(world.inv_inertia),
        _floats(world.radius), _floats(world.mu_static), _floats(world.mu_dynamic),
        _floats(world.restitution), _floats(world.gravity),
        float(np.linalg.norm(world.gravity)), kind, drive_row)


def shape_arrays(world: World) -> ShapeArrays:
    """The shape set and topology of ``world``."""
    shapes, topo = world.shapes, world.shapes.derived
    n_piece_bodies = int(shapes.piece_body.max()) + 1 if len(shapes.piece_body) else 0
    return ShapeArrays(
        shapes.vertices, shapes.normals, shapes.piece_start, shapes.piece_body,
        shapes.radius, topo.vertex_body, topo.vertex_piece, topo.next_vertex,
        topo.prev_vertex, topo.edge_length, topo.piece_width, topo.vertex_active,
        topo.edge_internal, topo.cover_start, topo.cover_lo, topo.cover_hi,
        topo.vertex_canon, n_piece_bodies)
