"""One simulated world and the way to drive it: the API the CLI, the ROS node and scripts share.

>>> sim = Simulator('track_one_box')
>>> sim.advance(0.5)                 # integrate to t = 0.5 s of simulated time
>>> names, origins, angles = sim.part_poses()
>>> sim.command_vibration(amplitude_m=0.5e-3, frequency_hz=50.0)
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
import logging
import math
import os

import numpy as np

from feeder_sim.contact.dynamics import SolverStats
from feeder_sim.model.scene import load_scene, METHODS, Scene
from feeder_sim.model.world import State, World
from feeder_sim.stepping import StepContacts, STEPPERS

log = logging.getLogger('feeder_sim')


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
    """Sums impulses per vertex-edge feature between two reports.

    A pile has hundreds of contacts per step, so nothing is done per contact in Python:
    ``add`` keeps each step's arrays and they are reduced by feature with numpy (a stable sort
    by feature key) every ``_REDUCE_STEPS`` steps, which bounds the memory when nobody takes
    reports, and in ``take``. The report is what summing step by step gives: features in order
    of first appearance since the previous report (deterministic, so recordings are too), the
    latest point and normal, impulses summed in step order (``np.add.at`` from -0.0, so even
    the bits and the sign of a zero match a running ``+=``).
    """

    _REDUCE_STEPS = 64

    def __init__(self) -> None:
        # the reduced part (if any) first, then one per step since the last reduction:
        # (key, point, normal, p_n, p_t, body_a, body_b)
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._steps = 0             # parts added since the last reduction

    def add(self, sc: StepContacts) -> None:
        c = sc.cs.contacts
        if not c.n:
            return
        key = (c.vertex_a.astype(np.int64) << 32) | c.edge_b.astype(np.int64)
        self._parts.append((key, c.point, c.normal, sc.normal_impulse, sc.tangent_impulse,
                            c.body_a, c.body_b))
        self._steps += 1
        if self._steps >= self._REDUCE_STEPS:
            self._reduce()

    def _reduce(self) -> None:
        """Replace the parts by one with a row per feature."""
        if not self._steps:
            return
        self._steps = 0
        key, point, normal, p_n, p_t, body_a, body_b = (
            np.concatenate(f) for f in zip(*self._parts, strict=True))
        o = np.argsort(key, kind='stable')
        ks = key[o]
        head = np.empty(len(ks), bool)
        head[0] = True
        np.not_equal(ks[1:], ks[:-1], out=head[1:])
        starts = np.flatnonzero(head)
        first = o[starts]                                   # first row of each feature
        last = o[np.append(starts[1:], len(ks)) - 1]         # latest row of each feature
        # features numbered in order of first appearance
        rank = np.empty(len(starts), np.int64)
        by_first = np.argsort(first)
        rank[by_first] = np.arange(len(starts))
        group = np.empty(len(key), np.int64)
        group[o] = rank[np.cumsum(head) - 1]
        # ufunc.at adds in row order, i.e. step order, like a running sum
        sum_n = np.full(len(starts), -0.0)
        sum_t = np.full(len(starts), -0.0)
        np.add.at(sum_n, group, p_n)
        np.add.at(sum_t, group, p_t)
        latest = last[by_first]
        # (ndarray.take: fancy indexing of (k, 2) rows is ~10x slower)
        self._parts = [(key[first[by_first]], point.take(latest, axis=0),
                        normal.take(latest, axis=0), sum_n, sum_t, body_a[latest],
                        body_b[latest])]

    def take(self) -> ContactReport:
        self._reduce()
        parts, self._parts = self._parts, []
        if parts:
            _, point, normal, p_n, p_t, body_a, body_b = parts[0]
            on = p_n > 0.0
            if on.any():
                return ContactReport(point.compress(on, axis=0), normal.compress(on, axis=0),
                                     p_n[on], p_t[on], body_a[on].astype(np.int64),
                                     body_b[on].astype(np.int64))
        z = np.zeros(0)
        return ContactReport(np.zeros((0, 2)), np.zeros((0, 2)), z, z.copy(),
                             np.zeros(0, int), np.zeros(0, int))


class Simulator:
    """A world, its state, the chosen stepping method and the bookkeeping around them."""

    def __init__(self, scene: Scene | str | os.PathLike, *, method: str | None = None,
                 time_step: float | None = None, tolerance: float | None = None,
                 friction_impulse: bool | None = None, settings=None) -> None:
        """``settings``: the stepping method's own settings (``TimeStepSettings``,
        ``EventSettings`` or ``ImpulseSettings``), for what the scene file does not set."""
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
        self._told: set[str] = set()     # kinds of inexact answers already logged
        self.state = self.world.initial_state()
        self._log = _ImpulseLog()
        self._settings = settings
        self._stepper = self._make_stepper()
        self.initial_energy_j = self.mechanical_energy()

    def _make_stepper(self):
        spec = self.scene.solver
        settings = None if self._settings is None else copy.deepcopy(self._settings)
        return STEPPERS[spec.method](self.world, spec, self.stats, settings)

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
        for report in self._stepper.advance(self.state, t_end):
            self._log.add(report)
        for kind, line in self.stats.inexact().items():
            if kind not in self._told:
                # once per kind and run; the counts go on in the summary and /diagnostics
                self._told.add(kind)
                log.error('%s: by t = %.6f s, %s', self.scene.name, self.state.t, line)

    def command_vibration(self, amplitude_m: float, frequency_hz: float) -> None:
        """New amplitude (m) and frequency (Hz) for every vibrating body, from now on.

        A command that changes nothing (a controller republishing its setpoint) leaves the
        motion and the stepper as they are."""
        drives = [self.world.drives[i] for i in self.world.driven]
        if all(d.amplitude_m == amplitude_m and d.frequency_hz == frequency_hz for d in drives):
            return
        for i in self.world.driven:
            self.world.drives[i].command(self.state.t, amplitude_m, frequency_hz)
        self.world.apply_prescribed_motion(self.state)
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
