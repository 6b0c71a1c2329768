"""A body's shape: an outline (``polygon:``) checked to be simple and counter-clockwise and
decomposed into convex pieces, or convex pieces as given (``polygons:``) checked."""

from __future__ import annotations

import functools

import numpy as np

from feeder_sim.model import geometry
from feeder_sim.model.scene.errors import _describe, _Invalid, _is_list
from feeder_sim.model.scene.fields import _vec
from feeder_sim.model.scene.specs import (
    MAX_LENGTH_M,
    MAX_PIECES,
    MAX_POLYGON_VERTICES,
    MIN_OUTLINE_M,
)

_SIMPLE_HINT = ('give the outline as a simple counter-clockwise polygon '
                '(edge k joins vertex k to vertex k+1, counting from 0)')


def _vertices(value, path: str) -> np.ndarray:
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of [x, y] vertices (m), got {_describe(value)}')
    if len(value) < 3:
        raise _Invalid(path, f'a polygon needs at least 3 [x, y] vertices, got {len(value)}')
    if len(value) > MAX_POLYGON_VERTICES:
        raise _Invalid(path, f'{len(value)} vertices; an outline may have at most '
                             f'{MAX_POLYGON_VERTICES}: simplify it (drop vertices closer than '
                             'the contact detail you need, e.g. 10 um)')
    return np.array([_vec(p, f'{path}[{k}]', 2, '[x, y] (m)', (MAX_LENGTH_M,) * 2)
                     for k, p in enumerate(value)])


def _orientation(v: np.ndarray, path: str, noun: str) -> None:
    problem = _outline_problem(_outline_key(v), noun)
    if problem is not None:
        raise _Invalid(path, problem)


def _outline_key(v: np.ndarray) -> bytes:
    return np.ascontiguousarray(v, dtype=float).tobytes()


# The geometry of an outline is checked and decomposed once per distinct outline: a scene of
# a thousand identical parts would otherwise check and decompose the same outline a thousand
# times.
@functools.lru_cache(maxsize=1024)
def _outline_problem(key: bytes, noun: str) -> str | None:
    """What is wrong with the outline whose float64 (x, y) vertices are ``key``, or None."""
    v = np.frombuffer(key).reshape(-1, 2)
    extent = float(np.max(v.max(axis=0) - v.min(axis=0)))
    if extent < MIN_OUTLINE_M:
        return (f'{noun} is {extent:.3g} m across; outlines must span at least '
                f'{MIN_OUTLINE_M:g} m (coordinates are in metres)')
    ok, reason = geometry.is_simple(v)
    if not ok:
        return f'{noun} is {reason}; {_SIMPLE_HINT}'
    area = geometry.polygon_area(v)
    if area < 0:
        return (f'{noun} vertices must be counter-clockwise; reverse the list (signed area '
                f'{area:.6g} m^2)')
    return None


@functools.lru_cache(maxsize=1024)
def _decomposed(key: bytes) -> tuple[tuple[np.ndarray, ...], tuple[float, ...]]:
    """The convex pieces of the simple outline ``key`` (see ``_outline_problem``), read-only,
    and the width of each."""
    pieces = tuple(geometry.convex_decomposition(np.frombuffer(key).reshape(-1, 2)))
    for piece in pieces:
        piece.flags.writeable = False
    return pieces, tuple(geometry.min_width(piece) for piece in pieces)


def _polygon(value, path: str) -> np.ndarray:
    v = _vertices(value, path)
    _orientation(v, path, 'polygon')
    return v


def _pieces(value, path: str) -> tuple[np.ndarray, ...]:
    if not _is_list(value) or len(value) == 0:
        raise _Invalid(path, 'expected a non-empty list of convex pieces, each a list of [x, y] '
                             f'vertices (m), got {_describe(value)}')
    if len(value) > MAX_PIECES:
        raise _Invalid(path, f'{len(value)} pieces; a body may have at most {MAX_PIECES}: merge '
                             'them into fewer convex pieces')
    pieces = []
    for k, item in enumerate(value):
        sub = f'{path}[{k}]'
        v = _vertices(item, sub)
        _orientation(v, sub, 'piece')
        if not geometry.is_convex(v):
            bad = geometry.reflex_vertices(v)
            raise _Invalid(sub, f'piece is not convex (it turns inward at vertex {bad[0]}); '
                                'split it into convex pieces, or give the whole outline as '
                                '`polygon:` and let feeder_sim decompose it')
        pieces.append(v)
    clean = [geometry.drop_collinear(p) for p in pieces]
    for i in range(len(clean)):
        for j in range(i + 1, len(clean)):
            if geometry.convex_overlap(clean[i], clean[j]):
                raise _Invalid(path, f'pieces {i} and {j} overlap; pieces of one body may touch '
                                     'but must not overlap (the overlap would count twice in '
                                     'the mass)')
    return tuple(pieces)
