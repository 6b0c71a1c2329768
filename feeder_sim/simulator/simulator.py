"""The facade of a simulation: :class:`Simulator` (see the package's docstring for its use)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import copy
from dataclasses import replace
import logging
import math
import os

import numpy as np

from feeder_sim.compiled import jit as compiled_jit
from feeder_sim.contact.dynamics import SolverStats
from feeder_sim.model.checks import is_number
from feeder_sim.model.scene import (
    check_placement,
    load_scene,
    MAX_ANGLE_RAD,
    MAX_LENGTH_M,
    MAX_SPEED_MPS,
    MAX_SPIN_RAD_S,
    overlap_problem,
    override_solver,
    parse_scene,
    Scene,
    SceneError,
)
from feeder_sim.model.vibration import check_command
from feeder_sim.model.world import State, World
from feeder_sim.simulator.energy_check import CHECK_ENERGY_VAR, EnergyCheck, env_tolerance
from feeder_sim.simulator.feed import Feed
from feeder_sim.simulator.impulse_log import ContactReport, ImpulseLog
from feeder_sim.simulator.time_step_pilot import auto_time_step
from feeder_sim.stepping import Stepper, STEPPERS

log = logging.getLogger('feeder_sim')

# A run of more steps than this loses the step in the round-off of the time itself (float64
# resolves t to 1e-16 t): it would not end.
MAX_STEPS_PER_RUN = 1e12
MAX_PUBLISH_RATE_HZ = 1e5


def _plain(x: object) -> object:
    """A numpy scalar as the Python float it stands for; anything else as it is.

    A float32 would make ``t`` a float32 (NumPy 2 keeps the narrower type of a Python float
    and a numpy scalar), so every kernel would compile anew and the time would drift
    (0.01 + np.float32(0.01) is 0.0199999995): it is read as the decimal it prints as."""
    if isinstance(x, np.floating) and x.dtype.itemsize < 8:
        return float(str(x))
    if isinstance(x, (np.floating, np.integer)):
        return float(x)
    return x


# What a state may hold, as a scene file's bodies may (the bounds of model/scene/specs.py): the
# check of values changed from outside (Simulator._check_state).
_STATE_BOUNDS = (('position', MAX_LENGTH_M, 'm'), ('angle', MAX_ANGLE_RAD, 'rad'),
                 ('velocity', MAX_SPEED_MPS, 'm/s'), ('omega', MAX_SPIN_RAD_S, 'rad/s'))


_TRIPLES = {'pose': '[x, y, angle] in m and rad', 'velocity': '[vx, vy, omega] in m/s and rad/s'}


def _triple(value: Sequence[float], what: str) -> np.ndarray:
    """A part's ``pose`` or ``velocity`` as three floats (their range is the scene check's),
    or a ValueError naming it."""
    if isinstance(value, (str, bytes)) or not all(
            is_number(x) for x in np.ravel(np.asarray(value, dtype=object))) or np.shape(
            value) != (3,):
        raise ValueError(f'{what} must be {_TRIPLES[what]}, got {value!r}')
    return np.asarray(value, dtype=float)


def _extent_m(body) -> float:
    """Largest extent (m) of a body's outline."""
    pts = np.concatenate(body.pieces)
    return float(np.max(pts.max(0) - pts.min(0)))


class UnknownPart(ValueError):
    """A part or part template named that the simulation does not have."""


class Simulator:
    """A world, its state, the chosen stepping method and the bookkeeping around them."""

    def __init__(self, scene: Scene | str | os.PathLike, *, method: str | None = None,
                 time_step: float | None = None, tolerance: float | None = None,
                 friction_impulse: bool | None = None, settings=None,
                 check_energy: float | None = None) -> None:
        """``settings``: the stepping method's own settings (``TimeStepSettings``,
        ``EventSettings`` or ``ImpulseSettings``), for what the scene file does not set.

        ``check_energy``: a tolerance (relative to :meth:`energy_scale_j`) for the energy
        invariant checked after every step or event (:class:`EnergyCheck`); a debug mode,
        also set by the environment variable ``FEEDER_SIM_CHECK_ENERGY``."""
        if isinstance(scene, Mapping):
            scene = parse_scene(scene)
        elif isinstance(scene, (str, os.PathLike)):
            scene = load_scene(scene)
        elif not isinstance(scene, Scene):
            raise TypeError('scene must be a Scene, the data of a scene file (a mapping), a '
                            f'scene file path or a shipped scene name, got {type(scene).__name__}')
        if time_step is None and method not in (None, scene.solver.method):
            time_step = STEPPERS[method].step_for(scene)
            if time_step is not None:
                log.info("%s: %s's step %g s is too coarse for %s; using %g s (%g steps per "
                         'drive period; a time step given sets another)', scene.name,
                         scene.solver.method, scene.solver.time_step, method, time_step,
                         STEPPERS[method].step_rule.steps_per_period)
        changes = {k: v for k, v in (('method', method), ('time_step', time_step),
                                     ('tolerance', tolerance),
                                     ('friction_impulse', friction_impulse)) if v is not None}
        if changes:
            scene = replace(scene, solver=override_solver(scene.solver, changes,
                                                          f'{scene.name} (override)'))
        self.time_step_pilot: dict | None = None      # what time_step: auto found and cost
        if scene.solver.time_step_auto:
            scene, self.time_step_pilot = auto_time_step(scene, Simulator)
        self.scene = scene
        self._scene_at_start = scene
        self.world = World.from_scene(scene)
        # index in self.world of each body of the starting scene (parts come and go)
        self._start_index = list(range(len(scene.bodies)))
        self._next_name: dict[str, int] = {}     # free_name's next k per base
        self.stats = SolverStats()
        self.lost_parts: list[tuple[float, str]] = []    # (t s, name) of parts that left
        self._told: set[str] = set()     # kinds of inexact answers already logged
        self.state = self.world.initial_state()
        self._checked_arrays: tuple[np.ndarray, ...] | None = None   # see _check_state
        self._trusted: tuple[bytes, ...] | None = None                # see _check_state
        self._log = ImpulseLog()
        self._settings = settings
        self.initial_energy_j = self.mechanical_energy()
        if check_energy is None and os.environ.get(CHECK_ENERGY_VAR):
            check_energy = env_tolerance(os.environ[CHECK_ENERGY_VAR])
        self.energy_check = None if check_energy is None else EnergyCheck(self, check_energy)
        self._stepper_made = self._make_stepper()
        self.feed = Feed(scene) if scene.sources or scene.sinks else None

    @property
    def _stepper(self):
        """The stepping method of the world as it is, made at its first use after the world
        changed: parts added or taken away between two frames make it once."""
        if self._stepper_made is None:
            self._stepper_made = self._make_stepper()
        return self._stepper_made

    def _make_stepper(self):
        spec = self.scene.solver
        settings = None if self._settings is None else copy.deepcopy(self._settings)
        compiled_jit.expect(spec.method)
        stepper = STEPPERS[spec.method](self.world, spec, self.stats, settings)
        if self.energy_check is not None:
            stepper.after_event = self.energy_check.after_event
        return stepper

    @property
    def t(self) -> float:
        """Simulated time, s."""
        return self.state.t

    @property
    def stepping(self) -> type[Stepper]:
        """The stepping method's class: its policy (``fixed_steps``, ``order``, ...)."""
        return STEPPERS[self.scene.solver.method]

    @property
    def method(self) -> str:
        return self.scene.solver.method

    def advance_to(self, t_end: float) -> None:
        """Integrate to simulated time ``t_end`` (s); nothing happens if the simulation is
        already there or past it (see :meth:`advance_by` to go on by a duration)."""
        t_end = _plain(t_end)
        if not is_number(t_end) or not math.isfinite(t_end):
            raise ValueError(f't_end must be a finite number of seconds, got {t_end!r}')
        self._check_state()
        h = self.scene.solver.time_step
        if (t_end - self.t) / h > MAX_STEPS_PER_RUN:
            raise ValueError(f't_end {t_end:g} s is more than {MAX_STEPS_PER_RUN:.0e} steps of '
                             f'{h:g} s ahead of t = {self.t:g} s; go on by at most '
                             f'{MAX_STEPS_PER_RUN * h:g} s per call')
        self._advance_to(t_end)
        self._trust_state()

    def _advance_to(self, t_end: float) -> None:
        """advance_to once t_end and the state are known to be fit for it."""
        if self.feed is None:
            self._step_to(t_end)
        elif t_end > self.t:
            # sinks take away what the previous frame showed past them; sources add parts at
            # their arrival times on the way
            self.feed.take_away(self)
            while True:
                arrival = self.feed.next_arrival()
                self._step_to(min(t_end, arrival))
                self._trust_state()        # the simulation's own values, not a caller's
                if arrival > t_end or arrival > self.t + 1e-12:
                    break
                self.feed.arrive(self)
        for kind, line in self.stats.inexact().items():
            if kind not in self._told:
                # once per kind and run; the counts go on in the summary and /diagnostics
                self._told.add(kind)
                log.error('%s: by t = %.6f s, %s', self.scene.name, self.state.t, line)

    def _check_state(self) -> None:
        """Refuse, with the field and the fix, a state a caller changed into one no stepper can
        take: its time not a finite number or beyond the round-off of a step, an array replaced
        by one of another type, shape or memory layout (compiled steppers would compile anew,
        as on a cold cache, or read the array as float64 of the world's size in C order: wrong
        bodies, wrong memory), or a part's value set to one a scene file could not hold (NaN,
        infinite, beyond the bounds of model/scene/specs.py: a run on from there gives NaN
        poses or numbers of 1e298 m).

        Values are checked where they differ from what the last advance left (its bytes are
        kept): the simulation's own numbers may leave the bounds (a part that fell off a track
        falls on) and are the stepper's, not a caller's. When nothing changed, this and
        ``_trust_state`` only take and compare the arrays' bytes, little beside even a short
        frame's steps (``benchmarks/throughput.py``'s one-part case in 1 ms frames, where each
        call counts); the arrays' types are checked only when they are not the ones checked
        last."""
        s = self.state
        if type(s.t) is not float:
            s.t = _plain(s.t)
            if not (is_number(s.t) and math.isfinite(s.t)):
                raise ValueError(f'state.t must be a finite number of seconds, got {s.t!r}')
        h = self.scene.solver.time_step
        if not -MAX_STEPS_PER_RUN * h <= s.t <= MAX_STEPS_PER_RUN * h:
            if math.isnan(s.t) or math.isinf(s.t):
                raise ValueError(f'state.t must be a finite number of seconds, got {s.t!r}')
            raise ValueError(f'state.t must be within +-{MAX_STEPS_PER_RUN * h:g} s (beyond, a '
                             f'step of {h:g} s is lost in the round-off of the time and a run '
                             f'does nothing), got {s.t!r}: set it back, e.g. state.t = 0.0')
        arrays = (s.position, s.angle, s.velocity, s.omega)
        last = self._checked_arrays
        if (last is None or arrays[0] is not last[0] or arrays[1] is not last[1]
                or arrays[2] is not last[2] or arrays[3] is not last[3]):
            self._check_arrays()
            self._trusted = None
        elif (self._trusted is not None and s.position.tobytes() == self._trusted[0]
              and s.angle.tobytes() == self._trusted[1]
              and s.velocity.tobytes() == self._trusted[2]
              and s.omega.tobytes() == self._trusted[3]):
            return
        self._check_values()
        self._trust_state()

    def _check_arrays(self) -> None:
        s = self.state
        n = self.world.n
        for name, shape in (('position', (n, 2)), ('angle', (n,)), ('velocity', (n, 2)),
                            ('omega', (n,))):
            x = getattr(s, name)
            if (isinstance(x, np.ndarray) and x.dtype == np.float64 and x.shape == shape
                    and x.flags.c_contiguous and x.flags.writeable):
                continue
            got = type(x).__name__
            if isinstance(x, np.ndarray):
                got = f'{x.dtype} array of shape {x.shape}' + (
                    '' if x.flags.c_contiguous else ', not C-contiguous') + (
                    '' if x.flags.writeable else ', read-only')
            raise ValueError(f'state.{name} must be a writable, C-contiguous float64 array of '
                             f'shape {shape}, got a {got}: assign np.array(value, dtype=float) '
                             f'of that shape')
        self._checked_arrays = (s.position, s.angle, s.velocity, s.omega)

    def _check_values(self) -> None:
        """The parts' values that differ from the last trusted ones (all, after the arrays
        changed) are finite and within the bounds of a scene file's (model/scene/specs.py)."""
        s, dynamic = self.state, self.world.dynamic
        for k, (name, bound, unit) in enumerate(_STATE_BOUNDS):
            x = getattr(s, name)
            check = dynamic if x.ndim == 1 else dynamic[:, None]
            if self._trusted is not None:
                check = check & (x != np.frombuffer(self._trusted[k]).reshape(x.shape))
            bad = check & ~(np.abs(x) <= bound)
            if bad.any():
                at = tuple(int(i) for i in np.argwhere(bad)[0])
                index = ', '.join(map(str, at))
                raise ValueError(
                    f'state.{name}[{index}] (part {self.world.names[at[0]]!r}) must be finite '
                    f'and within +-{bound:g} {unit}, as in a scene file, got {float(x[at])!r}: '
                    'set a value within it')

    def _trust_state(self) -> None:
        """What the simulation left: values that differ from these were set from outside."""
        s = self.state
        if self._checked_arrays is None or s.position is not self._checked_arrays[0] or (
                s.angle is not self._checked_arrays[1]
                or s.velocity is not self._checked_arrays[2]
                or s.omega is not self._checked_arrays[3]):
            self._trusted = None     # new arrays (a part came or went): checked next time
            return
        self._trusted = (s.position.tobytes(), s.angle.tobytes(), s.velocity.tobytes(),
                         s.omega.tobytes())

    def _step_to(self, t_end: float) -> None:
        if self.energy_check is None:
            for report in self._stepper.advance(self.state, t_end):
                self._log.add(report)
        else:
            self._advance_checked(t_end)

    def check_duration(self, duration_s: float, what: str = 'duration') -> None:
        """Refuse (ValueError naming ``what``) a run length that is not positive and finite or
        takes more than :data:`MAX_STEPS_PER_RUN` steps of ``solver.time_step``."""
        if not (is_number(duration_s) and duration_s > 0 and math.isfinite(duration_s)):
            raise ValueError(f'{what} must be a positive number of seconds, got {duration_s!r}')
        h = self.scene.solver.time_step
        if duration_s / h > MAX_STEPS_PER_RUN:
            raise ValueError(f'{what} {duration_s:g} s is more than {MAX_STEPS_PER_RUN:.0e} '
                             f'steps of {h:g} s; give at most {MAX_STEPS_PER_RUN * h:g} s')

    def advance_by(self, duration_s: float) -> None:
        """Integrate ``duration_s`` (s, > 0) of simulated time from now on."""
        duration_s = _plain(duration_s)
        self._check_state()
        self.check_duration(duration_s)
        self._advance_to(self.t + duration_s)
        self._trust_state()

    # the first name of advance_to, kept for scripts that use it
    advance = advance_to

    def _advance_checked(self, t_end: float) -> None:
        """``advance`` with the energy check after every step (every event: ``after_event``).

        A time-stepped method is advanced one ``time_step`` per call, on the grid it steps on
        anyway; only ``impulse_based``, whose own steps adapt, has them cut there too."""
        h = self.scene.solver.time_step if self.stepping.fixed_steps else math.inf
        while t_end - self.state.t > 1e-9 * self.scene.solver.time_step:
            reports = self._stepper.advance(self.state, min(t_end, self.state.t + h))
            for report in reports:
                self._log.add(report)
            self.energy_check.after_advance(self.state, reports)

    def command_vibration(self, amplitude_m: float, frequency_hz: float) -> None:
        """New amplitude (m) and frequency (Hz) for every vibrating body, from now on.

        A command that changes nothing (a controller republishing its setpoint) leaves the
        motion and the stepper as they are."""
        check_command(amplitude_m, frequency_hz)
        drives = [self.world.drives[i] for i in self.world.driven]
        if all(d.amplitude_m == amplitude_m and d.frequency_hz == frequency_hz for d in drives):
            return
        for i in self.world.driven:
            self.world.drives[i].command(self.state.t, amplitude_m, frequency_hz)
        self.world.apply_prescribed_motion(self.state)
        self._stepper.reset()

    def reset(self) -> None:
        """Back to the scene's initial state, parts and vibration; statistics are kept."""
        if self.scene is not self._scene_at_start:
            drives = self.world.drives
            self.scene = self._scene_at_start
            # the drives go on as objects (a removed body is a part: it had none)
            self.world = replace(World.from_scene(self.scene), drives=tuple(
                None if j is None else drives[j] for j in self._start_index))
            self._start_index = list(range(len(self.scene.bodies)))
        for d in self.world.drives:
            if d is not None:
                d.reset()
        self.state = self.world.initial_state()
        self._next_name = {}
        self._log = ImpulseLog()
        self._stepper_made = self._make_stepper()
        if self.energy_check is not None:
            self.energy_check.reference_j = self.mechanical_energy()
        if self.feed is not None:
            self.feed = Feed(self.scene)

    # -- parts that come and go -----------------------------------------------------------

    def add_part(self, template: str, name: str, pose: Sequence[float],
                 velocity: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        """From now on, a new dynamic part shaped and made as the scene's body ``template``,
        its body frame at ``pose`` ([x, y, angle], m and rad) moving at ``velocity`` ([vx, vy,
        omega], m/s and rad/s). Its fields are checked as a scene file's, and its place
        against the world as it is now (SceneError: a taken name, a pose inside another
        body, ...); what was accepted before is not checked again, and the cost does not
        depend on the drive's phase."""
        self._check_state()
        body = self.template_body(template)
        name, pose, velocity = check_placement(name, _triple(pose, 'pose'),
                                               _triple(velocity, 'velocity'))
        if name in self.world.name_index:
            raise SceneError(f'duplicate body name {name!r}: a body of the world has it; give '
                             f'the part a name no body has (e.g. {self.free_name(template)!r})',
                             'name', source='')
        body = replace(body, name=name, pose=pose, velocity=velocity)
        world = self.world.with_part(body)
        index = world.n - 1
        s = self.state
        # its centre of mass at ``pose``: where with_part put it at rest
        com = world.base_position[index]
        state = State(s.t, np.vstack((s.position, com)), np.append(s.angle, pose[2]),
                      np.vstack((s.velocity, velocity[:2])), np.append(s.omega, velocity[2]))
        self._check_clear(world, state, index, name)
        self._change_world(world, state, index)

    def template_body(self, template: str):
        """The dynamic body ``template`` of the scene now or as it started: a template may
        itself have left (a sink, a part taken away) and still be copied."""
        found = [b for b in (*self.scene.bodies, *self._scene_at_start.bodies)
                 if b.name == template]
        if not found or found[0].type != 'dynamic':
            parts = ', '.join(self.world.names[i] for i in self.part_indices)
            raise UnknownPart(f'template must name a dynamic body of the scene ({parts}), got '
                              f'{template!r}')
        return found[0]

    def free_name(self, base: str, first: int = 1) -> str:
        """``<base>_<k>`` for the first k from ``first`` on that no body has (k counts on
        from the last one given for ``base``: a burst of additions costs each a few
        lookups, not a scan of every name)."""
        taken = self.world.name_index
        k = max(first, self._next_name.get(base, first))
        while f'{base}_{k}' in taken:
            k += 1
        self._next_name[base] = k
        return f'{base}_{k}'

    def remove_part(self, name: str) -> None:
        """The dynamic part ``name`` leaves the simulation (a sink, a part taken away)."""
        self._check_state()
        self._remove(self._part_index(name))
        self._change_world(self.world, self.state)

    def set_part_pose(self, name: str, pose: Sequence[float],
                      velocity: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        """Put the part ``name`` at ``pose`` moving at ``velocity`` (units and checks of
        add_part)."""
        self._check_state()
        index = self._part_index(name)
        _, pose, velocity = check_placement(name, _triple(pose, 'pose'),
                                            _triple(velocity, 'velocity'))
        s = self.state.copy()
        s.position[index] = self.world.centre_of_mass(index, pose)
        s.angle[index] = pose[2]
        s.velocity[index] = velocity[:2]
        s.omega[index] = velocity[2]
        self._check_clear(self.world, s, index, name)
        self._change_world(self.world, s, index)

    def _part_index(self, name: str) -> int:
        index = self.world.name_index.get(name)
        if index is None or not self.world.dynamic[index]:
            parts = ', '.join(self.world.names[i] for i in self.part_indices)
            raise UnknownPart(f'no part named {name!r}; parts: {parts}')
        return index

    def _check_clear(self, world: World, state: State, index: int, name: str) -> None:
        """Refuse (SceneError on ``pose``) a part ``index`` placed deeper than a scene file
        allows inside a body where the bodies are at ``state`` (a vibrating track where its
        drive has it now)."""
        position = state.position
        reach = world.radius + world.radius[index]
        near = np.flatnonzero(np.sum((position - position[index]) ** 2, axis=1) <= reach ** 2)
        mine = world.piece_outlines(state, index)
        for other in near[near != index].tolist():
            for piece in world.piece_outlines(state, other):
                for own in mine:
                    problem = overlap_problem(name, own, world.names[other], piece,
                                              f'at t = {state.t:.6g} s')
                    if problem:
                        raise SceneError(problem, 'pose', source='')

    def _remove(self, index: int) -> None:
        """Take body ``index`` out of the world and the state (the stepper is made anew by
        :meth:`_change_world`)."""
        s, keep = self.state, np.arange(self.world.n) != index
        self.world = self.world.without_body(index)
        self.state = State(s.t, s.position[keep], s.angle[keep], s.velocity[keep],
                           s.omega[keep])
        self.scene = replace(self.scene, bodies=self.world.scene.bodies)
        self._start_index = [None if j is None or j == index else j - (j > index)
                             for j in self._start_index]

    def _take_away_lost(self, keep: int | None) -> None:
        """Take away the parts that left the world (past the bounds a scene can hold,
        ``scene.within_bounds``, or not finite: a part that fell off a track with nothing
        below it), but not part ``keep``: each is listed in ``lost_parts`` (time, name),
        logged, and counted as ``lost`` by the feed."""
        s, dynamic = self.state, self.world.dynamic
        origin, _ = self.world.body_frame_pose(s)
        inside = (np.all(np.abs(origin) <= MAX_LENGTH_M, axis=1)
                  & np.all(np.abs(s.velocity) <= MAX_SPEED_MPS, axis=1)
                  & (np.abs(s.omega) <= MAX_SPIN_RAD_S) & np.isfinite(s.angle))
        lost = np.flatnonzero(dynamic & ~inside)
        for index in lost[::-1].tolist():
            if index == keep or self.world.n == 1:
                continue
            name = self.world.names[index]
            self.lost_parts.append((s.t, name))
            if self.feed is not None:
                self.feed.events.append((s.t, name, 'lost'))
            log.warning('%s: part %r left the world by t = %.6f s (at %s m, moving at %s m/s); '
                        'taken away', self.scene.name, name, s.t,
                        np.array2string(origin[index], precision=4),
                        np.array2string(s.velocity[index], precision=4))
            self._remove(index)
            keep = keep - (keep > index) if keep is not None else None

    def _change_world(self, world: World, state: State, placed: int | None = None) -> None:
        """From now on ``world`` at ``state``: drives go on with the commands they received,
        the parts that left the world are taken away (not part ``placed``, whose numbers are
        a caller's, checked), the stepper starts afresh; contacts not yet taken are dropped
        (their body indices may be stale)."""
        self.scene = replace(self.scene, bodies=world.scene.bodies)
        self.world, self.state = world, state
        world.apply_prescribed_motion(state)
        self._take_away_lost(placed)
        # the state was checked before the change, the placed part's numbers by the change:
        # the new arrays hold the simulation's own values (a part spun past the bounds a
        # caller may set is not refused at the next advance)
        self._check_arrays()
        self._trust_state()
        self._log = ImpulseLog()
        self._stepper_made = None
        if self.energy_check is not None:
            self.energy_check.reference_j = self.mechanical_energy()

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

    def exit_progress(self) -> tuple[np.ndarray, np.ndarray]:
        """Each part's progress towards the scene's exit (m: along the track's x axis, or
        along ``outcomes.exit_axis`` from the world origin) and its centre of mass (n, 2)."""
        com = self.state.position[self.part_indices]
        axis = self.scene.outcomes.exit_axis
        if axis is None:
            return self.track_coordinates()[0], com
        return com @ np.asarray(axis), com

    def track_coordinates(self, state: State | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and speed (m/s) of each part's centre of mass along the track's x axis."""
        s = self.state if state is None else state
        origin, axis = self.world.track_frame()
        idx = self.part_indices
        return (s.position[idx] - origin) @ axis, s.velocity[idx] @ axis

    def energy_scale_j(self) -> float:
        """A scale for the parts' energy, J: the sum over parts of m |g| d (d their largest
        extent) plus the initial kinetic energy; what energy changes are measured against."""
        w = self.world
        g = float(np.linalg.norm(w.gravity))
        size = np.array([_extent_m(self.scene.bodies[i]) for i in self.part_indices])
        e = float(np.sum(w.mass[self.part_indices] * g * size)) + w.kinetic_energy(
            self.world.initial_state())
        return e if e > 0.0 else 1.0

    def mechanical_energy(self) -> float:
        """Kinetic plus gravitational potential energy of the parts, J."""
        return self.world.kinetic_energy(self.state) + self.world.potential_energy(self.state)
