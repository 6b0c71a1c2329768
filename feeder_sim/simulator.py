"""One simulated world and the way to drive it: the API the CLI, the ROS node and scripts share.

>>> sim = Simulator('track_one_box')
>>> sim.advance(0.5)                 # integrate to t = 0.5 s of simulated time
>>> names, origins, angles = sim.part_poses()
>>> sim.command_vibration(amplitude_m=0.5e-3, frequency_hz=50.0)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
import os

import numpy as np

from feeder_sim.dynamics import SolverStats
from feeder_sim.event_driven import EventDriven
from feeder_sim.scene import load_scene, Scene
from feeder_sim.time_stepping import StepContacts, TimeStepper
from feeder_sim.world import State, World

METHODS = ('event_driven', 'time_stepping', 'impulse_based')


@dataclass
class ContactReport:
    """Contacts active since the previous report, with the impulses (N s) they transmitted."""

    point: np.ndarray            # (k, 2) m, latest position
    normal: np.ndarray           # (k, 2)
    normal_impulse: np.ndarray   # (k,) N s, summed over the interval (collisions included)
    tangent_impulse: np.ndarray  # (k,) N s
    body_a: np.ndarray           # (k,) vertex body
    body_b: np.ndarray           # (k,) edge body

    @property
    def n(self) -> int:
        return len(self.normal_impulse)


class _ImpulseLog:
    """Sums impulses per vertex-edge feature between two reports."""

    def __init__(self) -> None:
        self._rows: dict[tuple[int, int], list] = {}

    def add(self, sc: StepContacts) -> None:
        c = sc.cs.contacts
        for i in range(c.n):
            key = (int(c.vertex_a[i]), int(c.edge_b[i]))
            row = self._rows.get(key)
            if row is None:
                self._rows[key] = [c.point[i], c.normal[i], float(sc.normal_impulse[i]),
                                   float(sc.tangent_impulse[i]), int(c.body_a[i]),
                                   int(c.body_b[i])]
            else:
                row[0], row[1] = c.point[i], c.normal[i]
                row[2] += float(sc.normal_impulse[i])
                row[3] += float(sc.tangent_impulse[i])

    def take(self) -> ContactReport:
        rows = [r for r in self._rows.values() if r[2] > 0.0]
        self._rows = {}
        if not rows:
            z = np.zeros(0)
            return ContactReport(np.zeros((0, 2)), np.zeros((0, 2)), z, z.copy(),
                                 np.zeros(0, int), np.zeros(0, int))
        return ContactReport(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                             np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                             np.array([r[4] for r in rows]), np.array([r[5] for r in rows]))


class Simulator:
    """A world, its state, the chosen stepping method and the bookkeeping around them."""

    def __init__(self, scene: Scene | str | os.PathLike, *, method: str | None = None,
                 time_step: float | None = None, tolerance: float | None = None,
                 friction_impulse: bool | None = None) -> None:
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        changes = {k: v for k, v in (('method', method), ('time_step', time_step),
                                     ('tolerance', tolerance),
                                     ('friction_impulse', friction_impulse)) if v is not None}
        if changes:
            scene = replace(scene, solver=replace(scene.solver, **changes))
        if scene.solver.method not in METHODS:
            raise ValueError(f'solver.method must be one of {", ".join(METHODS)}, '
                             f'got {scene.solver.method!r}')
        self.scene = scene
        self.world = World.from_scene(scene)
        self.stats = SolverStats()
        self.state = self.world.initial_state()
        self._log = _ImpulseLog()
        self._stepper = self._make_stepper()
        self.initial_energy_j = self.mechanical_energy()

    def _make_stepper(self):
        spec = self.scene.solver
        if spec.method == 'time_stepping':
            return TimeStepper(self.world, spec, self.stats)
        if spec.method == 'event_driven':
            return EventDriven(self.world, spec, self.stats)
        raise NotImplementedError(
            "solver.method 'impulse_based' (Mirtich & Canny) is not available in this "
            "version; use 'event_driven' or 'time_stepping'")

    @property
    def t(self) -> float:
        """Simulated time, s."""
        return self.state.t

    @property
    def method(self) -> str:
        return self.scene.solver.method

    def advance(self, t_end: float) -> None:
        """Integrate to simulated time ``t_end`` (s); no-op if already there."""
        if not math.isfinite(t_end):
            raise ValueError(f't_end must be finite, got {t_end!r}')
        if isinstance(self._stepper, TimeStepper):
            h = self.scene.solver.time_step
            # Round to whole steps so a publish period that is a multiple of the step costs
            # no extra short steps.
            while t_end - self.state.t > 1e-9 * h:
                report = self._stepper.step(self.state, min(h, t_end - self.state.t))
                if report is not None:
                    self._log.add(report)
        else:
            for report in self._stepper.advance(self.state, t_end):
                self._log.add(report)

    def command_vibration(self, amplitude_m: float, frequency_hz: float) -> None:
        """New amplitude (m) and frequency (Hz) for every vibrating body, from now on."""
        for i in self.world.driven:
            self.world.drives[i].command(self.state.t, amplitude_m, frequency_hz)
        self.world.apply_prescribed_motion(self.state)
        if isinstance(self._stepper, EventDriven):
            self._stepper.reset()

    def reset(self) -> None:
        """Back to the scene's initial state and vibration; statistics are kept."""
        for d in self.world.drives:
            if d is not None:
                d.reset()
        self.state = self.world.initial_state()
        self._log = _ImpulseLog()
        self._stepper = self._make_stepper()

    def take_contacts(self) -> ContactReport:
        """Contacts and impulses since the previous call."""
        return self._log.take()

    @property
    def part_indices(self) -> np.ndarray:
        return np.flatnonzero(self.world.dynamic)

    def part_poses(self) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
        """Names, body-frame origins (m) and angles (rad) of dynamic bodies, scene order."""
        origin, angle = self.world.body_frame_pose(self.state)
        idx = self.part_indices
        return tuple(self.world.names[i] for i in idx), origin[idx], angle[idx]

    def track_coordinates(self, state: State | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and speed (m/s) of each part's centre of mass along the track's x axis."""
        s = self.state if state is None else state
        origin, axis = self.world.track_frame()
        idx = self.part_indices
        return (s.position[idx] - origin) @ axis, s.velocity[idx] @ axis

    def mechanical_energy(self) -> float:
        """Kinetic plus gravitational potential energy of the parts, J."""
        return self.world.kinetic_energy(self.state) + self.world.potential_energy(self.state)
