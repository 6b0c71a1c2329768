"""A scene's sources and sinks: parts that arrive and parts taken away while it runs."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from feeder_sim.model.scene import Scene, SceneError

if TYPE_CHECKING:
    from feeder_sim.simulator.simulator import Simulator


class Feed:
    """A scene's sources and sinks while it runs (see ``SourceSpec`` and ``SinkSpec``).

    New parts are named ``<template>_<k>``; ``events`` lists (t s, name, what) with what one
    of ``added``, ``blocked`` (the place was taken: the arrival waits for the next),
    ``fell_back`` (below a sink's height) and ``left`` (past the exit)."""

    def __init__(self, scene: Scene) -> None:
        self.sources = scene.sources
        self.sinks = scene.sinks
        self.rng = [np.random.default_rng(src.seed) for src in self.sources]
        self.next_t = [src.start for src in self.sources]
        self.added = [0] * len(self.sources)
        self.events: list[tuple[float, str, str]] = []

    def next_arrival(self) -> float:
        return min(self.next_t, default=math.inf)

    def counts(self) -> dict[str, int]:
        kinds = ('added', 'blocked', 'fell_back', 'left', 'lost')
        return {k: sum(e[2] == k for e in self.events) for k in kinds}

    def arrive(self, sim: Simulator) -> None:
        """The arrival due now (the earliest source's)."""
        k = int(np.argmin(self.next_t))
        src, rng, t = self.sources[k], self.rng[k], self.next_t[k]
        (x_lo, x_hi), (y_lo, y_hi) = src.region
        x, y = rng.uniform(x_lo, x_hi), rng.uniform(y_lo, y_hi)
        shares = np.array([share for _, _, share in src.orientations])
        _, angle, _ = src.orientations[rng.choice(len(shares), p=shares / shares.sum())]
        if math.isnan(angle):
            angle = sim.template_body(src.template).pose[2]
        name = sim.free_name(src.template, self.added[k] + 1)
        try:
            sim.add_part(src.template, name, [x, y, angle])
        except SceneError:
            self.events.append((t, name, 'blocked'))
        else:
            self.added[k] += 1
            self.events.append((t, name, 'added'))
        done = src.count and self.added[k] >= src.count
        self.next_t[k] = math.inf if done else t + src.interval

    def take_away(self, sim: Simulator) -> None:
        """Remove the parts below a sink's height or past the exit."""
        if not self.sinks:
            return
        names, _, _ = sim.part_poses()
        along, com = sim.exit_progress()
        exit_at = sim.scene.outcomes.exit_position
        gone = []
        for name, s, (_, y) in zip(names, along, com, strict=True):
            for sink in self.sinks:
                if sink.below is not None and y < sink.below:
                    gone.append((name, 'fell_back'))
                    break
                if sink.past_exit and exit_at is not None and s >= exit_at:
                    gone.append((name, 'left'))
                    break
        for name, what in gone:
            if sim.world.n == 1:
                break                 # a world keeps one body: the last part stays
            sim.remove_part(name)
            self.events.append((sim.t, name, what))
