"""What every stepping method offers the simulator, and what it hands back.

A method advances a :class:`~feeder_sim.model.world.State` in place to a given time and returns
the contacts it used on the way with the impulses they transmitted; ``reset`` tells it that the
prescribed motion changed (a vibration command), so anything it derived from that motion is
stale. The simulator sees nothing else of a method.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from feeder_sim.contact.dynamics import ContactSet, SolverStats
from feeder_sim.model.scene import SolverSpec
from feeder_sim.model.world import State, World


@dataclass
class StepContacts:
    """Contacts of one step (or event) and the impulses (N s) they transmitted."""

    cs: ContactSet
    normal_impulse: np.ndarray
    tangent_impulse: np.ndarray


class Stepper(Protocol):
    """A stepping method, built as ``Method(world, spec, stats, settings)``."""

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: object | None = None) -> None: ...

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Move ``state`` to simulated time ``t_end`` (s); the contacts of every step taken."""
        ...

    def reset(self) -> None:
        """The prescribed motion changed at ``state.t``: forget what was derived from it."""
        ...


class StepperBase:
    """What every method keeps: the world, the scene's solver spec, the counters it adds to,
    and its own settings (``settings_type()`` when none are given). A method derives what it
    needs from them in ``prepare``."""

    settings_type: type
    # Called with the state and the contacts reported since the previous call at every event a
    # method locates (event_driven); the energy check of :mod:`feeder_sim.simulator` uses it.
    after_event: Callable[[State, list[StepContacts]], None] | None = None

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: object | None = None) -> None:
        self.world = world
        self.spec = spec
        self.stats = stats
        self.settings = settings or self.settings_type()
        self.prepare()

    def prepare(self) -> None:
        """Build what the method derives from its world, spec and settings."""
