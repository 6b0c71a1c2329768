"""The energy invariant of passive contact, checked while a simulation runs (a debug mode)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from feeder_sim.model.checks import is_number
from feeder_sim.model.world import State
from feeder_sim.stepping import StepContacts

if TYPE_CHECKING:
    from feeder_sim.simulator.simulator import Simulator

# the environment variable that turns the check on for every Simulator: a tolerance
CHECK_ENERGY_VAR = 'FEEDER_SIM_CHECK_ENERGY'


class EnergyInvariantError(AssertionError):
    """Mechanical energy rose by more than the check allows where nothing could supply it."""


class EnergyCheck:
    """Asserts the invariant of passive contact: between impacts with e <= 1 and without drive
    work, the parts' mechanical energy never rises.

    Checked after every step of a time-stepped method and at every event of ``event_driven``
    (and at the end of each call). The rise is measured from the energy at the last point
    where the invariant could not be applied: a step or event interval in which a part touched
    a moving driven body takes energy from the drive, so the reference is taken again after
    it. ``tolerance`` is relative to the scene's energy scale (:meth:`Simulator.energy_scale_j`).
    With ``raise_error`` a violation raises :class:`EnergyInvariantError`; otherwise the
    largest rise is kept in ``largest_rise`` for a report.
    """

    def __init__(self, sim: Simulator, tolerance: float, *, raise_error: bool = True) -> None:
        if not (is_number(tolerance) and tolerance >= 0.0):
            raise ValueError('check_energy must be a tolerance >= 0 (relative to the energy '
                             f'scale, e.g. 1e-6), got {tolerance!r}')
        self.sim = sim
        self.tolerance = float(tolerance)
        self.raise_error = raise_error
        self.scale_j = sim.energy_scale_j()
        self.reference_j = sim.mechanical_energy()
        self.largest_rise = 0.0          # of scale_j
        self.checks = 0
        self.rebased = 0                 # intervals with drive work
        self._seen = 0                   # reports of this advance already checked per event

    def _drive_work(self, reports: list[StepContacts], t: float) -> bool:
        w = self.sim.world
        if not len(w.driven):
            return False
        seg = w.drive_segments(t)
        moving = w.driven[(seg.amplitude_m * seg.omega_rad_s > 0.0) | (seg.offset_m != 0.0)]
        if not len(moving):
            return False
        for r in reports:
            c = r.cs.contacts
            pushed = (r.normal_impulse != 0.0) | (r.tangent_impulse != 0.0)
            if np.any(pushed & (np.isin(c.body_a, moving) | np.isin(c.body_b, moving))):
                return True
        return False

    def check(self, state: State, reports: list[StepContacts]) -> None:
        """The invariant after an interval whose contacts were ``reports``."""
        self.checks += 1
        energy = (self.sim.world.kinetic_energy(state)
                  + self.sim.world.potential_energy(state))
        if self._drive_work(reports, state.t):
            self.rebased += 1
            self.reference_j = energy
            return
        rise = (energy - self.reference_j) / self.scale_j
        if rise > self.largest_rise:
            self.largest_rise = rise
        if rise > self.tolerance:
            if self.raise_error:
                raise EnergyInvariantError(
                    f'{self.sim.scene.name} ({self.sim.method}): mechanical energy rose by '
                    f'{rise:.3g} of the energy scale {self.scale_j:.3g} J at t = '
                    f'{state.t:.9f} s (tolerance {self.tolerance:.3g}) without drive work')
        # energy lost stays lost: a later rise is measured from the lowest level
        self.reference_j = min(self.reference_j, energy)

    def after_event(self, state: State, reports: list[StepContacts]) -> None:
        self._seen += len(reports)
        self.check(state, reports)

    def after_advance(self, state: State, reports: list[StepContacts]) -> None:
        self.check(state, reports[self._seen:])
        self._seen = 0


def env_tolerance(text: str) -> float:
    """The tolerance set by ``FEEDER_SIM_CHECK_ENERGY``, or a ValueError naming it."""
    try:
        tolerance = float(text)
    except ValueError:
        tolerance = math.nan
    if not tolerance >= 0.0:
        raise ValueError(f'{CHECK_ENERGY_VAR} must be a tolerance >= 0 (e.g. 1e-6), '
                         f'got {text!r}')
    return tolerance
