"""Sensors of a feeder cell, read off the parts' poses frame by frame (see ``SensorSpec``).

A *beam* across the track answers what a photo-eye does: whether a part is in the beam now
(any part's outline cuts the sensor's segment) and how many parts have passed it. An
*inspection* line answers what a camera at the track does: each part that passes, and the
orientation it passes in (the scene's ``outcomes.orientations``, relative to the track).

A part passes when its centre of mass crosses the segment from the left side to the right
(looking from ``start`` to ``end``: a line drawn upwards across a track that runs along +x is
passed by parts moving along +x) between two frames; the crossing point on the straight path
between the two frames must lie on the segment. Crossings back (right to left) are not
counted, as a counter that knows the direction of flow would not. A part is followed by name,
so parts that come and go (sources, sinks, services) are counted from the frame after they
came.

A crossing in either direction disarms the sensor for that part until the part's outline lies
entirely on one side of the sensor's line again (touching it is allowed): a part resting
across the line, sliding along it or vibrating about it has a centre of mass that wanders
from side to side at every frame or every period of the drive, and a photo-eye would see one
part that never left the beam, not one per wobble. A part that appears with its outline
across the line is armed once it has been seen clear of it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import math

import numpy as np

from feeder_sim.model.scene import OutcomeSpec, SensorSpec
from feeder_sim.output.outcomes import classify

UNCLASSIFIED = 'unclassified'   # an inspection line in a scene that names no orientations


@dataclass(frozen=True)
class SensorReading:
    """One sensor at one frame."""

    name: str
    kind: str                              # 'beam' or 'inspection'
    blocked: bool                          # an outline cuts the segment (beam)
    count: int                             # parts passed since the start (or the last reset)
    passed: tuple[tuple[str, str], ...]    # (part, orientation) passed since the last frame;
    #                                        orientation '' for a beam


def _side(a: np.ndarray, d: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Twice the signed area of (a, a + d, p): > 0 where p is left of the directed line."""
    return d[0] * (p[..., 1] - a[1]) - d[1] * (p[..., 0] - a[0])


def segment_cuts_polygon(a: np.ndarray, b: np.ndarray, polygon: np.ndarray) -> bool:
    """Whether segment ab meets the closed polygon (k, 2) (world, m): an end inside it, or
    an edge crossing or touching the segment."""
    d = b - a
    p, q = polygon, np.roll(polygon, -1, axis=0)
    e = q - p
    # edges against the segment: each straddles the other's line (touching counts)
    s_p, s_q = _side(a, d, p), _side(a, d, q)
    s_a = e[:, 0] * (a[1] - p[:, 1]) - e[:, 1] * (a[0] - p[:, 0])
    s_b = e[:, 0] * (b[1] - p[:, 1]) - e[:, 1] * (b[0] - p[:, 0])
    if np.any((s_p * s_q <= 0.0) & (s_a * s_b <= 0.0)
              & ~((s_p == 0.0) & (s_q == 0.0) & (s_a == 0.0) & (s_b == 0.0))):
        return True
    # collinear overlap, or the segment inside: the polygon contains an end (even-odd rule)
    return bool(_inside(a, p, q)) or bool(_inside(b, p, q))


def _inside(x: np.ndarray, p: np.ndarray, q: np.ndarray) -> bool:
    up = (p[:, 1] > x[1]) != (q[:, 1] > x[1])
    with np.errstate(divide='ignore', invalid='ignore'):
        cross_x = p[:, 0] + (x[1] - p[:, 1]) * (q[:, 0] - p[:, 0]) / (q[:, 1] - p[:, 1])
    return bool(np.count_nonzero(up & (x[0] < cross_x)) % 2)


def _world_vertices(outlines: Sequence[np.ndarray], origin: np.ndarray,
                    angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return np.concatenate([np.asarray(o, dtype=float).reshape(-1, 2) for o in outlines]) \
        @ rot.T + origin


class SensorBank:
    """The scene's sensors, fed one frame at a time by :meth:`update`."""

    def __init__(self, specs: Sequence[SensorSpec], outcomes: OutcomeSpec,
                 track_angle_rad: float = 0.0) -> None:
        self.specs = tuple(specs)
        self.outcomes = outcomes
        self.track_angle_rad = float(track_angle_rad)
        self.reset()

    def reset(self) -> None:
        """Forget the parts' last positions and the counts (a reset of the simulation)."""
        self._last: dict[str, np.ndarray] = {}
        self.counts = [0] * len(self.specs)
        # crossings right to left, which a reading does not report (see the module's doc)
        self.counts_back = [0] * len(self.specs)
        self._armed: list[dict[str, bool]] = [{} for _ in self.specs]

    def update(self, names: Sequence[str], com: np.ndarray, origin: np.ndarray,
               angle: np.ndarray, outlines: Mapping[str, Sequence[np.ndarray]]
               ) -> tuple[SensorReading, ...]:
        """The readings at a frame: the parts ``names`` with centres of mass ``com`` (n, 2),
        body-frame origins ``origin`` (n, 2), angles ``angle`` (n,) (world, m and rad) and
        their outlines by name (body frame, as the scene gives them)."""
        com = np.asarray(com, dtype=float).reshape(-1, 2)
        origin = np.asarray(origin, dtype=float).reshape(-1, 2)
        angle = np.asarray(angle, dtype=float).reshape(-1)
        now = {n: com[k].copy() for k, n in enumerate(names)}
        prev = np.array([self._last.get(n, (math.nan, math.nan)) for n in names],
                        dtype=float).reshape(-1, 2)
        world: dict[int, np.ndarray] = {}

        def vertices(k: int) -> np.ndarray:
            if k not in world:
                world[k] = _world_vertices(outlines[names[k]], origin[k], float(angle[k]))
            return world[k]

        readings = []
        for s, spec in enumerate(self.specs):
            a, b = np.array(spec.start), np.array(spec.end)
            d = b - a
            s0, s1 = _side(a, d, prev), _side(a, d, com)
            # NaN (no last position) compares False: no crossing in a part's first frame
            forth = (s0 > 0.0) & (s1 <= 0.0)
            back = (s0 <= 0.0) & (s1 > 0.0)
            armed = self._armed[s]
            passed = []
            for k in np.flatnonzero(forth | back):
                if not armed.get(names[k], False):
                    continue
                lam = s0[k] / (s0[k] - s1[k])
                point = prev[k] + lam * (com[k] - prev[k])
                u = float(np.dot(point - a, d) / np.dot(d, d))
                if not 0.0 <= u <= 1.0:
                    continue
                armed[names[k]] = False
                if forth[k]:
                    passed.append((names[k], self._orientation(float(angle[k]))
                                   if spec.kind == 'inspection' else ''))
                else:
                    self.counts_back[s] += 1
            for k, n in enumerate(names):
                if not armed.get(n, False):
                    side = _side(a, d, vertices(k))
                    armed[n] = bool(np.all(side >= 0.0) or np.all(side <= 0.0))
            self.counts[s] += len(passed)
            blocked = False
            if spec.kind == 'beam':
                blocked = any(self._cuts(a, b, outlines[n], origin[k], angle[k])
                              for k, n in enumerate(names))
            readings.append(SensorReading(spec.name, spec.kind, blocked, self.counts[s],
                                          tuple(passed)))
        self._last = now
        for armed in self._armed:
            for n in [n for n in armed if n not in now]:
                del armed[n]
        return tuple(readings)

    def _orientation(self, angle_rad: float) -> str:
        name = classify(angle_rad - self.track_angle_rad, self.outcomes)
        return UNCLASSIFIED if name is None else name

    @staticmethod
    def _cuts(a: np.ndarray, b: np.ndarray, outlines: Sequence[np.ndarray],
              origin: np.ndarray, angle: float) -> bool:
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[c, -s], [s, c]])
        for outline in outlines:
            world = np.asarray(outline, dtype=float) @ rot.T + origin
            # cheap rejection on the bounding boxes first
            lo, hi = world.min(axis=0), world.max(axis=0)
            if (max(a[0], b[0]) < lo[0] or min(a[0], b[0]) > hi[0]
                    or max(a[1], b[1]) < lo[1] or min(a[1], b[1]) > hi[1]):
                continue
            if segment_cuts_polygon(a, b, world):
                return True
        return False
