"""Outcome measures a feeder designer reads directly: feed rate, exit orientation, jams.

Fed frame by frame with each part's position along the track (m) and its angle relative to
the track (rad). A part *exits* the first time its position reaches the scene's
``outcomes.exit_position``; its angle then is its exit orientation. A part that has not exited
and moved less than ``jam_distance`` along the track over the last ``jam_time`` is *jammed*
(reported once, at the first frame the condition holds).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import math

import numpy as np

from feeder_sim.scene import OutcomeSpec


@dataclass
class PartOutcome:
    name: str
    exit_time_s: float | None = None
    exit_angle_rad: float | None = None   # relative to the track, in (-pi, pi]
    jam_time_s: float | None = None       # first time the part was found jammed
    jam_position_m: float | None = None


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

    def update(self, t_s: float, position_m: np.ndarray, angle_rad: np.ndarray) -> None:
        """One frame: simulated time, along-track positions and angles to the track."""
        if self._t0 is None:
            self._t0 = t_s
        self._t = t_s
        exit_at = self.spec.exit_position
        for part, s, a in zip(self.parts, position_m, angle_rad):
            if part.exit_time_s is None and exit_at is not None and s >= exit_at:
                part.exit_time_s = float(t_s)
                part.exit_angle_rad = float(math.remainder(a, 2.0 * math.pi))
        self._history.append((t_s, np.array(position_m, dtype=float)))
        # Keep just enough history to look back one jam_time.
        while len(self._history) > 1 and self._history[1][0] <= t_s - self.spec.jam_time:
            self._history.popleft()
        t_old, s_old = self._history[0]
        if t_s - t_old < self.spec.jam_time - 1e-12:
            return
        moved = np.abs(np.asarray(position_m) - s_old)
        for part, dist, s in zip(self.parts, moved, position_m):
            if part.exit_time_s is None and part.jam_time_s is None and \
                    dist < self.spec.jam_distance:
                part.jam_time_s = float(t_s)
                part.jam_position_m = float(s)

    def summary(self) -> dict:
        """Counts, feed rate (parts per minute over the run), orientations and jams."""
        span = (self._t - self._t0) if self._t0 is not None else 0.0
        exited = [p for p in self.parts if p.exit_time_s is not None]
        jammed = [p for p in self.parts if p.jam_time_s is not None]
        return {
            'exit_position_m': self.spec.exit_position,
            'jam_time_s': self.spec.jam_time,
            'jam_distance_m': self.spec.jam_distance,
            'parts_exited': len(exited),
            'feed_rate_parts_per_min': 60.0 * len(exited) / span if span > 0 else 0.0,
            'jams': len(jammed),
            'parts': [vars(p).copy() for p in self.parts],
        }
