"""One simulated world and the way to drive it: the API the CLI, the ROS node and scripts share.

>>> sim = Simulator('track_one_box')
>>> sim.advance_to(0.5)              # integrate to t = 0.5 s of simulated time
>>> sim.advance_by(0.1)              # and 0.1 s more
>>> names, origins, angles = sim.part_poses()
>>> sim.command_vibration(amplitude_m=0.5e-3, frequency_hz=50.0)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import copy
from dataclasses import dataclass, replace
import logging
import math
import os
import time

import numpy as np

from feeder_sim import _jit
from feeder_sim.contact._feature_kernels import sum_by_feature
from feeder_sim.contact.dynamics import SolverStats
from feeder_sim.model.checks import is_number
from feeder_sim.model.scene import (
    check_placement,
    load_scene,
    MAX_ANGLE_RAD,
    MAX_LENGTH_M,
    MAX_SPEED_MPS,
    MAX_SPIN_RAD_S,
    MIN_TIME_STEP_S,
    overlap_problem,
    override_solver,
    parse_scene,
    Scene,
    SceneError,
)
from feeder_sim.model.vibration import check_command
from feeder_sim.model.world import State, World
from feeder_sim.stepping import StepContacts, STEPPERS

log = logging.getLogger('feeder_sim')

CHECK_ENERGY_VAR = 'FEEDER_SIM_CHECK_ENERGY'
# A run of more steps than this loses the step in the round-off of the time itself (float64
# resolves t to 1e-16 t): it would not end.
MAX_STEPS_PER_RUN = 1e12
MAX_PUBLISH_RATE_HZ = 1e5


# time_stepping is first order: about 2 % off on conveying speed at 400 steps per drive period
# (README, Validation); a scene without a drive gets 1 ms
STEPS_PER_PERIOD = 400
FIXED_STEP_S = 1e-3


def fixed_time_step(scene: Scene) -> float:
    """A time_stepping step for a scene whose own step was chosen for another method (s)."""
    frequencies = [b.vibration.frequency for b in scene.bodies
                   if b.vibration is not None and b.vibration.frequency > 0.0]
    return min([FIXED_STEP_S] + [1.0 / (STEPS_PER_PERIOD * f) for f in frequencies])


# time_step: auto (model/scene/parse.py): each candidate step and its half run a pilot of the
# scene; the conveying speed is measured over AUTO_MEASURE_PERIODS drive periods after
# AUTO_WARMUP_PERIODS (the parts' start-up is not what the step must resolve, and a part that
# slides back and forth without sticking builds its step's error up over some ten periods:
# after 5, three steps agreed to 0.3 % on a speed 6.8 % off in its steady state), and at most
# AUTO_MAX_HALVINGS halvings are tried (50 -> 12 800 steps per period)
AUTO_WARMUP_PERIODS = 20
AUTO_MEASURE_PERIODS = 10
AUTO_MAX_HALVINGS = 8
# below this share of the drive's peak speed a conveying speed counts as standing still: the
# error is then relative to it (a part that sticks has no speed to be 1 % of)
AUTO_SPEED_FLOOR = 0.01


def auto_time_step(scene: Scene) -> tuple[Scene, dict]:
    """``solver.time_step: auto``: the scene with the largest step of the halving ladder from
    its first candidate whose conveying speed (the mean along-track speed of the parts present
    at the start, over a short pilot) has a Richardson estimate of its relative error within
    ``solver.tolerance`` over two halvings (time_stepping is first order: error(h) ~
    2 |v(h/2) - v(h)| ~ 4 |v(h/4) - v(h/2)|, the larger taken); and what the pilot found and
    cost."""
    solver = scene.solver
    drives = [b.vibration for b in scene.bodies
              if b.vibration is not None and b.vibration.frequency > 0.0]
    period = 1.0 / max(d.frequency for d in drives)
    floor = AUTO_SPEED_FLOOR * max(d.amplitude * 2.0 * math.pi * d.frequency for d in drives)
    warm, end = AUTO_WARMUP_PERIODS * period, (AUTO_WARMUP_PERIODS + AUTO_MEASURE_PERIODS) * period
    wall0 = time.perf_counter()
    candidates: list[dict] = []

    def speed(h: float) -> float:
        sim = Simulator(replace(scene, solver=replace(solver, time_step=h, time_step_auto=False)))
        sim.advance_to(warm)
        before = dict(zip(sim.part_poses()[0], sim.track_coordinates()[0]))
        sim.advance_to(end)
        after = dict(zip(sim.part_poses()[0], sim.track_coordinates()[0]))
        # by name: parts that a source adds or a sink takes on the way are not measured
        moved = [after[n] - before[n] for n in before if n in after]
        if not moved:
            raise SceneError('auto measures the conveying speed of the parts on the track, '
                             f'and no part is there from t = {warm:g} to {end:g} s: give a step '
                             'in s', 'solver.time_step', scene.source)
        v = float(np.mean(moved)) / (end - warm)
        candidates.append({'time_step_s': h, 'conveying_speed_mps': v})
        return v

    # A step is taken when two halvings agree that it is within the tolerance: its own
    # difference to its half, 2 |v(h) - v(h/2)|, and the next one's scaled to it,
    # 4 |v(h/2) - v(h/4)|. One halving alone can agree by chance while the error still
    # changes sign with the step (near lift-off at Gamma 0.95: an estimate of 0.02 % at 100
    # steps per period that was 1.2 % off).
    h, chosen, error = solver.time_step, None, math.nan
    diff, scale = math.nan, 1.0
    speeds = [speed(h)]
    for _ in range(AUTO_MAX_HALVINGS):
        if h / 4 < MIN_TIME_STEP_S:
            break
        while len(speeds) < 3:
            speeds.append(speed(h / 2 ** len(speeds)))
        v_h, v_half, v_quarter = speeds
        diff, scale = abs(v_half - v_h), max(abs(v_quarter), floor)
        estimate = max(2.0 * diff, 4.0 * abs(v_quarter - v_half))
        if estimate <= solver.tolerance * scale:
            chosen, error = h, estimate / scale
            break
        h = h / 2
        speeds = speeds[1:]
    met = chosen is not None
    if not met:
        chosen = candidates[-1]['time_step_s']
        log.warning('%s: time_step auto: no step down to %g s keeps the conveying speed within '
                    '%g (the last halving changed it by %.3g %%); using %g s', scene.name,
                    chosen, solver.tolerance, 100.0 * diff / scale, chosen)
    wall = time.perf_counter() - wall0
    steps = sum((end / c['time_step_s']) for c in candidates)
    report = {'time_step_s': chosen, 'steps_per_period': period / chosen,
              'tolerance': solver.tolerance, 'met': met,
              'estimated_relative_error': error,
              'fixed_steps_per_period': STEPS_PER_PERIOD,
              'pilot': {'simulated_s_each': end, 'candidates': candidates,
                        'steps': int(round(steps)), 'wall_s': wall}}
    log.info('%s: time_step auto: %g s (%.0f steps per drive period, fixed: %d), conveying '
             'speed within %.2g %% by the pilot: %d runs of %g s, %d steps, %.2f s wall',
             scene.name, chosen, period / chosen, STEPS_PER_PERIOD, 100.0 * error,
             len(candidates), end, steps, wall)
    return replace(scene, solver=replace(solver, time_step=chosen, time_step_auto=False)), report


def _env_tolerance(text: str) -> float:
    try:
        tolerance = float(text)
    except ValueError:
        tolerance = math.nan
    if not tolerance >= 0.0:
        raise ValueError(f'{CHECK_ENERGY_VAR} must be a tolerance >= 0 (e.g. 1e-6), '
                         f'got {text!r}')
    return tolerance


def _plain(x: object) -> object:
    """A numpy scalar as the Python float it stands for; anything else as it is.

    A float32 would make ``t`` a float32 (NumPy 2 keeps the narrower type of a Python float
    and a numpy scalar), so every kernel compiled anew, for a minute, and the time drifted
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
    ``add`` keeps each step's arrays and they are reduced by feature (compiled:
    ``contact._feature_kernels.sum_by_feature``) every ``_REDUCE_STEPS`` steps, which bounds
    the memory when nobody takes reports, and in ``take``. The report is what summing step by
    step gives: features in order of first appearance since the previous report
    (deterministic, so recordings are too), the latest point and normal, impulses summed in
    step order from -0.0, so even the bits and the sign of a zero match a running ``+=``.
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
        self._parts = [sum_by_feature(*(np.concatenate(f)
                                        for f in zip(*self._parts, strict=True)))]

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


class UnknownPart(ValueError):
    """A part or part template named that the simulation does not have."""


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
        if time_step is None and method == 'time_stepping' != scene.solver.method:
            step = fixed_time_step(scene)
            if step < scene.solver.time_step:
                time_step = step
                log.info("%s: %s's step %g s is too coarse for time_stepping; using %g s "
                         '(%d steps per drive period; a time step given sets another)',
                         scene.name, scene.solver.method, scene.solver.time_step, step,
                         STEPS_PER_PERIOD)
        changes = {k: v for k, v in (('method', method), ('time_step', time_step),
                                     ('tolerance', tolerance),
                                     ('friction_impulse', friction_impulse)) if v is not None}
        if changes:
            scene = replace(scene, solver=override_solver(scene.solver, changes,
                                                          f'{scene.name} (override)'))
        self.time_step_pilot: dict | None = None      # what time_step: auto found and cost
        if scene.solver.time_step_auto:
            scene, self.time_step_pilot = auto_time_step(scene)
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
        self._log = _ImpulseLog()
        self._settings = settings
        self.initial_energy_j = self.mechanical_energy()
        if check_energy is None and os.environ.get(CHECK_ENERGY_VAR):
            check_energy = _env_tolerance(os.environ[CHECK_ENERGY_VAR])
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
        _jit.expect(spec.method)
        stepper = STEPPERS[spec.method](self.world, spec, self.stats, settings)
        if self.energy_check is not None:
            stepper.after_event = self.energy_check.after_event
        return stepper

    @property
    def t(self) -> float:
        """Simulated time, s."""
        return self.state.t

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
        by one of another type, shape or memory layout (compiled steppers would compile anew for
        a minute, or read the array as float64 of the world's size in C order: wrong bodies,
        wrong memory), or a part's value set to one a scene file could not hold (NaN, infinite,
        beyond the bounds of model/scene/specs.py: a run on from there gives NaN poses or numbers
        of 1e298 m).

        Values are checked where they differ from what the last advance left (its bytes are
        kept): the simulation's own numbers may leave the bounds (a part that fell off a track
        falls on) and are the stepper's, not a caller's. Unchanged, this and ``_trust_state``
        cost 2.7 us per advance on a 10-part scene (track_ten_boxes: ``timeit`` of the two
        calls, best of 7 x 1e5, on a 2-core machine under a load of 3.6), under the 5 us
        allowed; the arrays' types are checked only when they are not the ones checked last."""
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
        h = math.inf if self.method == 'event_driven' else self.scene.solver.time_step
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
        self._log = _ImpulseLog()
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
        self._log = _ImpulseLog()
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
