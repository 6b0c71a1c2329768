"""Outcome measures a feeder designer reads directly: feed rate, exit orientation, jams.

Fed frame by frame with each part's progress towards the exit (m, see ``OutcomeSpec``), its
centre of mass (m, world) and its angle relative to the track (rad). A part *exits* the first
time its progress reaches the scene's ``outcomes.exit_position``; its angle then is its exit
orientation, named after the nearest of the scene's ``orientations``. A part that has not
exited and whose centre of mass moved less than ``jam_distance`` over the last ``jam_time`` is
*jammed* (reported once, at the first frame the condition holds).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math

import numpy as np

from feeder_sim.model.scene import OutcomeSpec

OTHER = 'other'   # an exit orientation farther than the tolerance from every named one


@dataclass
class PartOutcome:
    name: str
    exit_time_s: float | None = None
    exit_angle_rad: float | None = None   # relative to the track, in (-pi, pi]
    exit_orientation: str | None = None   # the nearest named orientation, or 'other'
    exit_point_m: list[float] | None = None   # centre of mass (world) as it crossed the exit
    #                                           line: which lane or chute the part took
    jam_time_s: float | None = None       # first time the part was found jammed
    jam_position_m: list[float] | None = None   # its centre of mass then (world)


def classify(angle_rad: float, spec: OutcomeSpec) -> str | None:
    """The name of the orientation nearest to ``angle_rad`` within the tolerance, ``'other'``
    when none is near enough, None when the scene names no orientations."""
    if not spec.orientations:
        return None
    name, angle = min(spec.orientations,
                      key=lambda item: abs(math.remainder(angle_rad - item[1], 2 * math.pi)))
    off = abs(math.remainder(angle_rad - angle, 2 * math.pi))
    return name if off <= spec.orientation_tolerance else OTHER


@dataclass
class OutcomeTracker:
    names: tuple[str, ...]
    spec: OutcomeSpec
    parts: list[PartOutcome] = field(init=False)
    _history: deque = field(init=False, repr=False)
    _t0: float | None = field(default=None, init=False, repr=False)
    _t: float = field(default=0.0, init=False, repr=False)

    def __post_init__(self) -> None:
        self.parts = [PartOutcome(n) for n in self.names]
        self._history = deque()

    def update(self, t_s: float, progress_m: np.ndarray, position_m: np.ndarray,
               angle_rad: np.ndarray, names: tuple[str, ...] | None = None) -> None:
        """One frame: simulated time, progress towards the exit, centres of mass (n, 2) and
        angles to the track of the parts ``names`` (default: those given at construction;
        parts that come and go are followed by name)."""
        if names is not None and tuple(names) != self.names:
            known = {p.name for p in self.parts}
            self.parts += [PartOutcome(n) for n in names if n not in known]
            self.names = tuple(names)
        by_name = {p.name: p for p in self.parts}
        current = [by_name[n] for n in self.names]
        if self._t0 is None:
            self._t0 = t_s
        self._t = t_s
        exit_at = self.spec.exit_position
        position = np.array(position_m, dtype=float).reshape(-1, 2)
        for part, s, a, p in zip(current, progress_m, angle_rad, position):
            if part.exit_time_s is None and exit_at is not None and s >= exit_at:
                part.exit_time_s = float(t_s)
                part.exit_point_m = [float(p[0]), float(p[1])]
                part.exit_angle_rad = float(math.remainder(a, 2.0 * math.pi))
                part.exit_orientation = classify(part.exit_angle_rad, self.spec)
        # by name: parts may come and go; one that came later is judged from when it came
        self._history.append((t_s, dict(zip(self.names, position))))
        # Keep just enough history to look back one jam_time.
        while len(self._history) > 1 and self._history[1][0] <= t_s - self.spec.jam_time:
            self._history.popleft()
        t_old, p_old = self._history[0]
        if t_s - t_old < self.spec.jam_time - 1e-12:
            return
        for part, p in zip(current, position):
            if part.name not in p_old:
                continue
            dist = math.hypot(*(p - p_old[part.name]))
            if part.exit_time_s is None and part.jam_time_s is None and \
                    dist < self.spec.jam_distance:
                part.jam_time_s = float(t_s)
                part.jam_position_m = [float(p[0]), float(p[1])]

    def summary(self) -> dict:
        """Counts, feed rate (parts per minute over the run), orientations and jams."""
        span = (self._t - self._t0) if self._t0 is not None else 0.0
        exited = [p for p in self.parts if p.exit_time_s is not None]
        jammed = [p for p in self.parts if p.jam_time_s is not None]
        counts: dict[str, int] = {}
        if self.spec.orientations:
            counts = {name: 0 for name, _ in self.spec.orientations} | {OTHER: 0}
            for p in exited:
                counts[p.exit_orientation] += 1
        return {
            'exit_position_m': self.spec.exit_position,
            'exit_axis': None if self.spec.exit_axis is None else list(self.spec.exit_axis),
            'jam_time_s': self.spec.jam_time,
            'jam_distance_m': self.spec.jam_distance,
            'parts_exited': len(exited),
            'feed_rate_parts_per_min': 60.0 * len(exited) / span if span > 0 else 0.0,
            'feed_rate_steady_parts_per_min': steady_feed_rate(
                [p.exit_time_s for p in exited]),
            'exit_orientations': counts,
            'jams': len(jammed),
            'parts': [vars(p).copy() for p in self.parts],
        }


def steady_feed_rate(exit_times_s: list[float]) -> float | None:
    """Parts per minute between the first exit and the last: the rate once parts arrive,
    without the time the first one took to get there (None with fewer than two exits, or
    all at one instant)."""
    span = max(exit_times_s) - min(exit_times_s) if len(exit_times_s) > 1 else 0.0
    return 60.0 * (len(exit_times_s) - 1) / span if span > 0 else None

