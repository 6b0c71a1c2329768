"""A validated scene as frozen dataclasses (:class:`Scene`, :class:`BodySpec`, ...), and the
limits its values are checked against. Units are SI (m, s, kg, rad)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
import math

import numpy as np

from feeder_sim.model import geometry

METHODS = ('event_driven', 'time_stepping', 'impulse_based')
BODY_TYPES = ('static', 'kinematic', 'dynamic')
RESTITUTION_LAWS = ('stronge', 'poisson', 'newton')
DEFAULT_GRAVITY = (0.0, -9.81)
MAX_FRICTION = 10.0
# Bounds that keep a run finite and its numbers meaningful; far beyond any feeder.
MAX_LENGTH_M = 1e4           # |coordinate| of a pose or a vertex
MAX_ANGLE_RAD = 1e3          # |pose angle|: beyond it sin/cos lose the part's orientation
MAX_SPEED_MPS = 1e3          # |initial velocity component|
MAX_SPIN_RAD_S = 1e5         # |initial angular velocity|
MAX_GRAVITY_MPS2 = 1e4       # |gravity component|, about 1000 g
POSE_BOUNDS = (MAX_LENGTH_M, MAX_LENGTH_M, MAX_ANGLE_RAD)        # |x|, |y|, |theta| of a pose
VELOCITY_BOUNDS = (MAX_SPEED_MPS, MAX_SPEED_MPS, MAX_SPIN_RAD_S)  # |vx|, |vy|, |omega|
MIN_TIME_STEP_S = 1e-7       # below it a simulated second costs over 1e7 steps
# `time_step: auto` (time_stepping): the Simulator picks the step by a pilot run, halving from
# 1/AUTO_FIRST_STEPS_PER_PERIOD of the fastest drive's period until the conveying speed's
# estimated relative error is within solver.tolerance (AUTO_TOLERANCE when the file gives none)
AUTO_FIRST_STEPS_PER_PERIOD = 50
AUTO_TOLERANCE = 0.01
AUTO_MIN_TOLERANCE = 1e-4    # 100 times finer than 1 %: already 2^7 halvings of the step


@dataclass(frozen=True)
class StepRule:
    """A step (s) from a scene's drives: ``steps_per_period`` steps in a period of the fastest
    drive, and never more than ``longest_s``."""

    steps_per_period: float
    longest_s: float = math.inf

    def step(self, frequencies_hz: Iterable[float]) -> float:
        h = self.longest_s
        for f in frequencies_hz:
            if f > 0.0:
                h = min(h, 1.0 / (self.steps_per_period * f))
        return h


# Each method's step rule, the one home of these numbers (its stepper carries it as policy).
# event_driven: its largest step, within which it locates every event. time_stepping: the
# fixed step it takes on a scene whose step was chosen for another method; it is first order,
# about 2 % off on a conveying speed at 400 steps per drive period (docs/performance.md), and
# a scene without a drive gets 1 ms. impulse_based: a scene builder's default step, as
# event_driven's (its own steps adapt below it).
STEP_RULES: dict[str, StepRule] = {
    'event_driven': StepRule(16),
    'time_stepping': StepRule(400, 1e-3),
    'impulse_based': StepRule(16),
}
# time_step: auto (time_stepping): the pilot's first candidate step
AUTO_FIRST_STEP = StepRule(AUTO_FIRST_STEPS_PER_PERIOD)


def within_bounds(pose: np.ndarray, velocity: np.ndarray) -> bool:
    """Whether a body at ``pose`` moving at ``velocity`` is one a scene can hold (the bounds
    its ``pose`` and ``velocity`` fields are checked against; NaN is not)."""
    return bool(np.all(np.abs(pose) <= POSE_BOUNDS)
                and np.all(np.abs(velocity) <= VELOCITY_BOUNDS))


# What the loader reads: checking a polygon costs O(n^2) time and memory (100 MB at 1000
# vertices); a scene file of thousands of parts is well under a megabyte.
MAX_POLYGON_VERTICES = 1000
MAX_PIECES = 200
MAX_FILE_BYTES = 2 * 2 ** 20
MAX_NESTING = 32
MAX_VALUES = 1_000_000     # values a file may expand to through YAML aliases
MIN_MASS_KG, MAX_MASS_KG = 1e-9, 1e6       # a dust grain to a machine base
MIN_DENSITY, MAX_DENSITY = 1e-6, 1e6       # kg/m^2
MIN_OUTLINE_M = 1e-6                       # an outline's extent: below it m r^2 underflows
MIN_PIECE_WIDTH_M = 1e-6                   # thinner convex pieces leave contacts no depth
# A part may start at most this fraction of its thinner piece inside another body: the
# contact search looks no deeper (contact.collision.DEPTH_FRACTION).
MAX_START_OVERLAP = 0.25


# --------------------------------------------------------------------------------------------
# Dataclasses


def _frozen(value, shape: tuple) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if shape and arr.shape != shape:
        arr = arr.reshape(shape)
    arr.flags.writeable = False
    return arr


def _equal(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return a is not None and b is not None and bool(np.array_equal(a, b))
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


class _ArrayFieldsEq:
    """Field-wise equality for dataclasses holding numpy arrays (which makes them unhashable)."""

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return all(_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))


@dataclass(frozen=True)
class Vibration:
    """Prescribed displacement ``amplitude * sin(2 pi frequency t + phase)`` of a kinematic body.

    ``amplitude`` in m (0-peak), ``frequency`` in Hz, ``angle`` (rad) is the direction of the
    displacement measured from the body's own x axis, ``phase`` in rad.
    """

    amplitude: float
    frequency: float
    angle: float
    phase: float = 0.0


@dataclass(frozen=True)
class SolverSpec:
    """Integrator settings: ``time_step`` in s (the fixed step of time_stepping, the largest step
    of event_driven), ``tolerance`` the event_driven integrator's relative tolerance.

    ``time_step_auto`` (``time_step: auto``, time_stepping only): the step is still to be picked
    by the Simulator's pilot run, starting from ``time_step``; ``tolerance`` is then the
    relative error of the conveying speed it must meet."""

    method: str = 'event_driven'
    time_step: float = 1e-4
    friction_impulse: bool = True
    tolerance: float = 1e-9
    restitution_law: str = 'stronge'   # impulse_based: stronge | poisson | newton
    time_step_auto: bool = False


@dataclass(frozen=True, eq=False)
class BodySpec(_ArrayFieldsEq):
    """One body as written in the scene file, validated.

    ``pieces``: convex CCW pieces (m) in the body frame, exactly where the file puts them (not
    shifted to the centroid). ``outlines``: the shape as given, for drawing and for writing the
    scene back: ``(polygon,)`` for ``polygon:`` input, the pieces as written for ``polygons:``.
    ``pose`` = (x m, y m, theta rad) of the body frame in the world; ``velocity`` = (vx, vy m/s,
    omega rad/s). Dynamic bodies have exactly one of ``mass`` (kg) / ``density`` (kg/m^2); other
    bodies have neither. Arrays are read-only.
    """

    name: str
    type: str
    pieces: tuple[np.ndarray, ...]
    outlines: tuple[np.ndarray, ...]
    pose: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mass: float | None = None
    density: float | None = None
    mu_static: float = 0.0
    mu_dynamic: float = 0.0
    restitution: float = 0.0
    vibration: Vibration | None = None

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, 'pieces', tuple(_frozen(p, ()) for p in self.pieces))
        set_(self, 'outlines', tuple(_frozen(p, ()) for p in self.outlines))
        set_(self, 'pose', _frozen(self.pose, (3,)))
        set_(self, 'velocity', _frozen(self.velocity, (3,)))

    @property
    def mass_properties(self) -> geometry.MassProperties | None:
        """Mass (kg), central inertia (kg m^2) and centroid (body frame, m); None if massless."""
        if self.mass is None and self.density is None:
            return None
        return geometry.mass_properties(self.pieces, mass=self.mass, density=self.density)


@dataclass(frozen=True)
class OutcomeSpec:
    """What a designer reads off a run.

    A part *exits* when its centre of mass reaches ``exit_position`` (m; None: no exit),
    measured along the track's x axis from the track's origin, or, when ``exit_axis`` (a world
    direction [x, y]) is given, along that direction from the world origin (an orienter's exit
    chute points down: ``[0, -1]``). Its angle relative to the track then is its exit
    orientation, named after the nearest entry of ``orientations`` (name -> angle in rad)
    within ``orientation_tolerance`` (rad), else ``other``. A part that has not exited and
    whose centre of mass moved less than ``jam_distance`` (m) during ``jam_time`` (s) is
    *jammed*.
    """

    exit_position: float | None = None
    jam_time: float = 1.0
    jam_distance: float = 1e-3
    exit_axis: tuple[float, float] | None = None
    orientations: tuple[tuple[str, float], ...] = ()
    orientation_tolerance: float = 0.35


@dataclass(frozen=True)
class SourceSpec:
    """Parts added while the scene runs: copies of the dynamic body ``template`` (its shape and
    material), one every ``interval`` s from ``start`` s on, ``count`` of them at most (0:
    no limit); each body frame at a point drawn uniformly in ``region`` ((x_lo, x_hi), (y_lo,
    y_hi), m, world) and at an angle drawn from ``orientations`` (name -> (angle rad, share)),
    seeded by ``seed``. An arrival whose place is taken waits for the next one."""

    template: str
    interval: float
    region: tuple[tuple[float, float], tuple[float, float]]
    orientations: tuple[tuple[str, float, float], ...]
    start: float = 0.0
    count: int = 0
    seed: int = 0


@dataclass(frozen=True)
class SinkSpec:
    """Parts taken away: those whose centre of mass falls ``below`` a height (m, world: back
    to the bowl), and, with ``past_exit``, those that have passed the outcomes' exit."""

    below: float | None = None
    past_exit: bool = False


SENSOR_KINDS = ('beam', 'inspection')


@dataclass(frozen=True)
class SensorSpec:
    """A line across the parts' path, fixed in the world, from ``start`` to ``end`` (m).

    A part *passes* it when its centre of mass crosses the segment from its left side to its
    right (looking from ``start`` to ``end``: drawn upwards across a track along +x, it is
    passed by parts moving along +x). A ``beam`` reports whether any part's outline
    cuts the segment (presence) and counts the parts that passed; an ``inspection`` line
    also names each passing part's orientation (the scene's ``outcomes.orientations``)."""

    name: str
    kind: str
    start: tuple[float, float]
    end: tuple[float, float]


@dataclass(frozen=True, eq=False)
class Scene(_ArrayFieldsEq):
    """A validated scene. ``gravity`` in m/s^2 (world frame, read-only); ``track`` names the body
    whose x axis is "along the track" in reports (None: no such body); ``source`` is the file."""

    name: str
    gravity: np.ndarray
    solver: SolverSpec
    bodies: tuple[BodySpec, ...]
    track: str | None = None
    source: str = '<dict>'
    description: str = ''             # one line: what the scene is (feeder-sim scenes)
    outcomes: OutcomeSpec = OutcomeSpec()
    # the values of the scene's named parameters this scene was built with
    parameters: Mapping[str, float] = field(default_factory=dict)
    sources: tuple[SourceSpec, ...] = ()
    sinks: tuple[SinkSpec, ...] = ()
    sensors: tuple[SensorSpec, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, 'gravity', _frozen(self.gravity, (2,)))
        object.__setattr__(self, 'bodies', tuple(self.bodies))

    def drive_frequencies_hz(self) -> list[float]:
        """The frequencies (Hz) of the bodies that vibrate (frequency > 0)."""
        return [b.vibration.frequency for b in self.bodies
                if b.vibration is not None and b.vibration.frequency > 0.0]

    def body(self, name: str) -> BodySpec:
        """The body called ``name`` (KeyError if there is none)."""
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(name)
