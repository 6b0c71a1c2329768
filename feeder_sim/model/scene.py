"""Scene files: YAML -> validated, frozen dataclasses.

A scene describes one world (see docs/interfaces.md §1). Everything is checked before anything
runs; the first problem raises :class:`SceneError`, whose message names the file, the key path
(``bodies[2].polygon``) and what is expected. Units are SI (m, s, kg, rad) throughout.

YAML is read with a safe loader that differs from ``yaml.safe_load`` in two ways, both aimed at
hand-written files: floats follow YAML 1.2 (``1e-3`` is a number, not the text "1e-3"), and a key
repeated in one mapping is an error instead of silently keeping the last value.

Optional blocks (``solver``, ``vibration``) written with no content (``solver:`` followed by only
comments) count as absent. ``track: null`` means "no track body".
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Mapping
from contextvars import ContextVar
from dataclasses import dataclass, field, fields, replace
import difflib
import functools
import math
from numbers import Real
import os
from pathlib import Path
import re
import sys
from typing import Any

import numpy as np
import simpleeval
import yaml

from feeder_sim.model import geometry
from feeder_sim.model.checks import is_number
from feeder_sim.model.vibration import (
    drive_value_problem,
    MAX_AMPLITUDE_M,
    MAX_FREQUENCY_HZ,
)

__all__ = [
    'BODY_TYPES', 'METHODS', 'BodySpec', 'Scene', 'SceneError', 'SolverSpec', 'Vibration',
    'load_scene', 'OutcomeSpec', 'parse_scene', 'scene_dirs', 'scene_to_dict', 'shipped_scenes',
    'within_bounds',
]

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


def within_bounds(pose: np.ndarray, velocity: np.ndarray) -> bool:
    """Whether a body at ``pose`` moving at ``velocity`` is one a scene can hold (the bounds
    its ``pose`` and ``velocity`` fields are checked against; NaN is not)."""
    return bool(np.all(np.abs(pose) <= POSE_BOUNDS)
                and np.all(np.abs(velocity) <= VELOCITY_BOUNDS))


# What the loader reads: checking a polygon costs O(n^2) time and memory (100 MB, 1 s at 1000
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


class SceneError(ValueError):
    """An invalid scene, with the offending key path and the file it came from.

    ``path`` is like ``'bodies[2].polygon'`` ('' for the file as a whole), ``source`` the file name
    (or ``'<dict>'``), ``message`` the bare explanation; ``line``/``column`` (1-based) are set for
    YAML syntax errors.
    """

    def __init__(self, message: str, path: str = '', source: str = '<dict>',
                 line: int | None = None, column: int | None = None):
        self.message = message
        self.path = path
        self.source = source
        self.line = line
        self.column = column
        super().__init__(': '.join(part for part in (source, path, message) if part))

    def __reduce__(self):
        return (SceneError, (self.message, self.path, self.source, self.line, self.column))


class _Invalid(Exception):
    """Raised by the checkers; parse_scene adds the source and turns it into a SceneError."""

    def __init__(self, path: str, message: str):
        super().__init__(path, message)
        self.path = path
        self.message = message


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

    def body(self, name: str) -> BodySpec:
        """The body called ``name`` (KeyError if there is none)."""
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(name)


# --------------------------------------------------------------------------------------------
# Checkers: one per kind of value. Each takes (value, path) and returns the clean value.


def _join(path: str, key: str) -> str:
    return f'{path}.{key}' if path else key


def _is_list(value) -> bool:
    return isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim > 0)


def _describe(value) -> str:
    if value is None:
        return 'nothing (null)'
    if isinstance(value, (bool, np.bool_)):
        return f'{str(bool(value)).lower()} (a boolean)'
    if isinstance(value, str):
        return f'the text {value!r}'
    if isinstance(value, Mapping):
        return 'a mapping'
    if _is_list(value):
        return f'a list of {len(value)} item' + ('' if len(value) == 1 else 's')
    if isinstance(value, Real):
        return f'{value!r}'
    return f'a {type(value).__name__}'


def _suggest(word: str, choices) -> str:
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ''


def _range_text(lo, hi, lo_open, hi_open) -> str:
    if lo is not None and hi is not None:
        return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"{'<' if hi_open else '<='} {hi:g}"


def _number(value, path: str, lo: float | None = None, hi: float | None = None, *,
            lo_open: bool = False, hi_open: bool = False, unit: str = '', hint: str = '') -> float:
    """A finite real number (bool is not a number), optionally within [lo, hi] (or open ends).

    In a scene with ``parameters``, text that is not a number is an expression of them."""
    names = _PARAMETER_VALUES.get()
    if names is not None and isinstance(value, str) and not _looks_numeric(value):
        value = _evaluate(value, path, names)
    expected = 'a number' + (f' ({unit})' if unit else '')
    if lo is not None or hi is not None:
        expected += ' ' + _range_text(lo, hi, lo_open, hi_open)
    if not is_number(value):
        extra = ''
        if isinstance(value, str) and _looks_numeric(value):
            extra = '; YAML read it as text: remove any quotes'
            if _yaml11_number(value) != value.strip():
                extra += f' (and write it as {_yaml11_number(value)} for YAML 1.1 readers)'
        raise _Invalid(path, f'expected {expected}, got {_describe(value)}{extra}')
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise _Invalid(path, f'expected {expected}, got {x!r}; only finite numbers are allowed')
    below = lo is not None and (x <= lo if lo_open else x < lo)
    above = hi is not None and (x >= hi if hi_open else x > hi)
    if below or above:
        raise _Invalid(path, f'{x:g} is out of range; expected {expected}'
                       + (f'; {hint}' if hint else ''))
    return x


# The values of the scene's parameters while its numbers are checked (None: it has none).
_PARAMETER_VALUES: ContextVar[dict[str, float] | None] = ContextVar('parameters', default=None)
EXPRESSION_FUNCTIONS = {name: getattr(math, name) for name in (
    'sin', 'cos', 'tan', 'asin', 'acos', 'atan', 'atan2', 'sqrt', 'exp', 'log', 'hypot',
    'radians', 'degrees', 'floor', 'ceil')} | {'abs': abs, 'min': min, 'max': max}
EXPRESSION_CONSTANTS = {'pi': math.pi, 'g': 9.81}


# An expression's length: a formula of a few parameters is tens of characters; Python's
# parser recurses per nesting level and runs out of stack (or memory) on ~100 000.
MAX_EXPRESSION_CHARS = 1000


def _evaluate(text: str, path: str, values: Mapping[str, float]) -> float:
    """A number from an expression of the scene's parameters (simpleeval: arithmetic, the
    functions above, no attribute access, no calls of anything else)."""
    if len(text) > MAX_EXPRESSION_CHARS:
        raise _Invalid(path, f'an expression of {len(text)} characters ({text[:40]!r}...); '
                             f'expressions are limited to {MAX_EXPRESSION_CHARS}: name a '
                             'parameter for the repeated part')
    evaluator = simpleeval.SimpleEval(names={**EXPRESSION_CONSTANTS, **values},
                                      functions=EXPRESSION_FUNCTIONS)
    try:
        _refuse_truth_values(text, path)
        result = evaluator.eval(text)
    except (RecursionError, MemoryError):
        raise _Invalid(path, f'{text[:40]!r}... is nested too deeply to evaluate; write it '
                             'with fewer parentheses or signs') from None
    except (simpleeval.InvalidExpression, SyntaxError, ArithmeticError, TypeError,
            ValueError) as err:
        known = ', '.join(sorted(values)) or 'none'
        reason = getattr(err, 'message', None) or str(err) or type(err).__name__
        raise _Invalid(path, f'cannot evaluate {text!r}: {reason}; parameters: {known}; '
                             'functions: ' + ', '.join(sorted(EXPRESSION_FUNCTIONS))) from None
    if not is_number(result):
        raise _Invalid(path, f'{text!r} gives {_describe(result)}, not a number')
    try:
        return float(result)
    except OverflowError:
        raise _Invalid(path, f'{text!r} gives a number beyond the largest double (1.8e308); '
                             'expressions must stay within the field\'s range') from None


# Python counts True as 1 and comparisons give truth values: in an expression, `True + h` or
# `(h > 1) * 2` would be taken as numbers; a scene's values are numbers, never truth values.
_TRUTH_NODES = (ast.Compare, ast.BoolOp, ast.Not)


def _refuse_truth_values(text: str, path: str) -> None:
    for node in ast.walk(ast.parse(text.strip(), mode='eval')):
        constant = isinstance(node, ast.Constant) and (node.value is None or isinstance(
            node.value, bool))
        if constant or isinstance(node, _TRUTH_NODES):
            what = (repr(node.value) if constant else 'a comparison or a logical operation')
            raise _Invalid(path, f'cannot evaluate {text!r}: {what} is not a number; '
                                 'expressions are arithmetic of numbers and parameters')


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _yaml11_number(text: str) -> str:
    # YAML 1.1 (PyYAML's safe_load) needs a dot in the mantissa and a sign in the exponent.
    mantissa, _, exponent = text.strip().lower().partition('e')
    if '.' not in mantissa:
        mantissa += '.0'
    if exponent and exponent[0] not in '+-':
        exponent = '+' + exponent
    return f'{mantissa}e{exponent}' if exponent else mantissa


def _vec(value, path: str, n: int, what: str = '',
         limits: tuple[float, ...] | None = None) -> np.ndarray:
    """A list of exactly n finite numbers, each within +-limits[k] if given."""
    shape = f'{n} numbers' + (f' {what}' if what else '')
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of {shape}, got {_describe(value)}')
    if len(value) != n:
        raise _Invalid(path, f'expected {shape}, got {_describe(value)}')
    if limits is None:
        return np.array([_number(x, f'{path}[{k}]') for k, x in enumerate(value)])
    return np.array([_number(x, f'{path}[{k}]', -lim, lim,
                             hint='larger values do not keep a run finite and meaningful')
                     for k, (x, lim) in enumerate(zip(value, limits, strict=True))])


def _string(value, path: str) -> str:
    if not isinstance(value, str):
        quote = '; put it in quotes' if isinstance(value, (Real, bool)) else ''
        raise _Invalid(path, f'expected text, got {_describe(value)}{quote}')
    if not value.strip():
        raise _Invalid(path, 'expected non-empty text')
    return value


def _choice(value, path: str, choices: tuple[str, ...]) -> str:
    options = ', '.join(choices)
    if not isinstance(value, str):
        raise _Invalid(path, f'expected one of {options}, got {_describe(value)}')
    if value not in choices:
        raise _Invalid(path, f'unknown value {value!r}{_suggest(value, choices)}; '
                             f'expected one of {options}')
    return value


def _boolean(value, path: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise _Invalid(path, f'expected true or false, got {_describe(value)}')
    return bool(value)


# Common misnamings that difflib cannot guess (too short or a different word).
_ALIASES = {
    'mu': 'mu_static', 'friction': 'mu_static', 'mu_s': 'mu_static', 'mu_d': 'mu_dynamic',
    'mu_k': 'mu_dynamic', 'mu_kinetic': 'mu_dynamic', 'e': 'restitution', 'cor': 'restitution',
    'vertices': 'polygon', 'shape': 'polygon', 'position': 'pose', 'vel': 'velocity',
    'dt': 'time_step', 'h': 'time_step', 'rtol': 'tolerance', 'freq': 'frequency',
    'f': 'frequency', 'a': 'amplitude', 'amp': 'amplitude', 'direction': 'angle', 'g': 'gravity',
    'kind': 'type', 'body': 'bodies', 'parts': 'bodies',
}


def _mapping(value, path: str, allowed) -> Mapping:
    """A mapping with text keys drawn from ``allowed``."""
    if not isinstance(value, Mapping):
        where = 'the top level of the file to be ' if not path else ''
        raise _Invalid(path, f'expected {where}a mapping with the keys {", ".join(allowed)}; '
                             f'got {_describe(value)}')
    for key in value:
        if not isinstance(key, str):
            raise _Invalid(path, f'keys must be text, got the key {_describe(key)}; '
                                 f'allowed keys: {", ".join(allowed)}')
        if key not in allowed:
            guess = _suggest(key, allowed)
            if not guess and _ALIASES.get(key) in allowed:
                guess = f" (did you mean '{_ALIASES[key]}'?)"
            raise _Invalid(_join(path, key), f'unknown key {key!r}{guess}; '
                                             f'allowed keys: {", ".join(allowed)}')
    return value


_REQUIRED = object()   # the key must be present
_AUTO = object()       # absent: the value is worked out later from the rest of the scene


@dataclass(frozen=True)
class _Field:
    check: Callable[[Any, str], Any]
    expected: str                     # shown when the key is missing or null
    default: Any = _REQUIRED
    nullable: bool = False            # pass null to ``check`` instead of rejecting it


def _fields(value, path: str, table: Mapping[str, _Field]) -> dict[str, Any]:
    """Check a mapping against a table of fields; returns every field, defaults filled in."""
    data = _mapping(value, path, table)
    out = {}
    for key, spec in table.items():
        sub = _join(path, key)
        if key not in data:
            if spec.default is _REQUIRED:
                raise _Invalid(sub, f'missing required key {key!r}; expected {spec.expected}')
            out[key] = spec.default
        elif data[key] is None and not spec.nullable:
            raise _Invalid(sub, f'{key!r} has no value; expected {spec.expected}')
        else:
            out[key] = spec.check(data[key], sub)
    return out


def _num(lo=None, hi=None, **kw) -> Callable[[Any, str], float]:
    return lambda value, path: _number(value, path, lo, hi, **kw)


# --------------------------------------------------------------------------------------------
# Shapes

_SIMPLE_HINT = ('give the outline as a simple counter-clockwise polygon '
                '(edge k joins vertex k to vertex k+1, counting from 0)')


def _vertices(value, path: str) -> np.ndarray:
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of [x, y] vertices (m), got {_describe(value)}')
    if len(value) < 3:
        raise _Invalid(path, f'a polygon needs at least 3 [x, y] vertices, got {len(value)}')
    if len(value) > MAX_POLYGON_VERTICES:
        raise _Invalid(path, f'{len(value)} vertices; an outline may have at most '
                             f'{MAX_POLYGON_VERTICES}: simplify it (drop vertices closer than '
                             'the contact detail you need, e.g. 10 um)')
    return np.array([_vec(p, f'{path}[{k}]', 2, '[x, y] (m)', (MAX_LENGTH_M,) * 2)
                     for k, p in enumerate(value)])


def _orientation(v: np.ndarray, path: str, noun: str) -> None:
    problem = _outline_problem(_outline_key(v), noun)
    if problem is not None:
        raise _Invalid(path, problem)


def _outline_key(v: np.ndarray) -> bytes:
    return np.ascontiguousarray(v, dtype=float).tobytes()


# The geometry of an outline is checked and decomposed once per distinct outline: a scene of
# a thousand identical parts took 2 ms per part doing it again for each.
@functools.lru_cache(maxsize=1024)
def _outline_problem(key: bytes, noun: str) -> str | None:
    """What is wrong with the outline whose float64 (x, y) vertices are ``key``, or None."""
    v = np.frombuffer(key).reshape(-1, 2)
    extent = float(np.max(v.max(axis=0) - v.min(axis=0)))
    if extent < MIN_OUTLINE_M:
        return (f'{noun} is {extent:.3g} m across; outlines must span at least '
                f'{MIN_OUTLINE_M:g} m (coordinates are in metres)')
    ok, reason = geometry.is_simple(v)
    if not ok:
        return f'{noun} is {reason}; {_SIMPLE_HINT}'
    area = geometry.polygon_area(v)
    if area < 0:
        return (f'{noun} vertices must be counter-clockwise; reverse the list (signed area '
                f'{area:.6g} m^2)')
    return None


@functools.lru_cache(maxsize=1024)
def _decomposed(key: bytes) -> tuple[tuple[np.ndarray, ...], tuple[float, ...]]:
    """The convex pieces of the simple outline ``key`` (see ``_outline_problem``), read-only,
    and the width of each."""
    pieces = tuple(geometry.convex_decomposition(np.frombuffer(key).reshape(-1, 2)))
    for piece in pieces:
        piece.flags.writeable = False
    return pieces, tuple(geometry.min_width(piece) for piece in pieces)


def _polygon(value, path: str) -> np.ndarray:
    v = _vertices(value, path)
    _orientation(v, path, 'polygon')
    return v


def _pieces(value, path: str) -> tuple[np.ndarray, ...]:
    if not _is_list(value) or len(value) == 0:
        raise _Invalid(path, 'expected a non-empty list of convex pieces, each a list of [x, y] '
                             f'vertices (m), got {_describe(value)}')
    if len(value) > MAX_PIECES:
        raise _Invalid(path, f'{len(value)} pieces; a body may have at most {MAX_PIECES}: merge '
                             'them into fewer convex pieces')
    pieces = []
    for k, item in enumerate(value):
        sub = f'{path}[{k}]'
        v = _vertices(item, sub)
        _orientation(v, sub, 'piece')
        if not geometry.is_convex(v):
            bad = geometry.reflex_vertices(v)
            raise _Invalid(sub, f'piece is not convex (it turns inward at vertex {bad[0]}); '
                                'split it into convex pieces, or give the whole outline as '
                                '`polygon:` and let feeder_sim decompose it')
        pieces.append(v)
    clean = [geometry.drop_collinear(p) for p in pieces]
    for i in range(len(clean)):
        for j in range(i + 1, len(clean)):
            if geometry.convex_overlap(clean[i], clean[j]):
                raise _Invalid(path, f'pieces {i} and {j} overlap; pieces of one body may touch '
                                     'but must not overlap (the overlap would count twice in '
                                     'the mass)')
    return tuple(pieces)


# --------------------------------------------------------------------------------------------
# Blocks

def _drive_value(name: str, check: Callable[[Any, str], float]) -> Callable[[Any, str], float]:
    def checked(value, path: str) -> float:
        x = check(value, path)
        if (problem := drive_value_problem(name, x)) is not None:
            raise _Invalid(path, problem)
        return x
    return checked


_VIBRATION = {
    'amplitude': _Field(_drive_value('amplitude', _num(
                            0.0, MAX_AMPLITUDE_M, unit='m, 0-peak',
                            hint='feeder amplitudes are typically 1e-5 to 1e-3 m')),
                        'the displacement amplitude in m (0-peak)'),
    'frequency': _Field(_drive_value('frequency', _num(0.0, MAX_FREQUENCY_HZ, unit='Hz')),
                        'the frequency in Hz'),
    'angle': _Field(_num(-MAX_ANGLE_RAD, MAX_ANGLE_RAD, unit='rad'),
                    'the direction in rad from the body x axis'),
    'phase': _Field(_num(-MAX_ANGLE_RAD, MAX_ANGLE_RAD, unit='rad'), 'the phase in rad', 0.0),
}


def _vibration(value, path: str) -> Vibration | None:
    if value is None:
        return None
    return Vibration(**_fields(value, path, _VIBRATION))


_STEP_AUTO = 'auto'
_time_step_number = _num(MIN_TIME_STEP_S, 0.1, unit='s',
                         hint=f'steps below {MIN_TIME_STEP_S:g} s cost over 1e7 per simulated '
                              'second')


def _time_step(value, path: str) -> float | str:
    if isinstance(value, str) and value.strip() == _STEP_AUTO:
        return _STEP_AUTO
    try:
        return _time_step_number(value, path)
    except _Invalid as err:
        if not isinstance(value, str):
            raise
        raise _Invalid(path, f'{err.message}; or auto (time_stepping: the step a pilot run '
                             'picks)') from None


_SOLVER = {
    'method': _Field(lambda v, p: _choice(v, p, METHODS), 'one of ' + ', '.join(METHODS),
                     SolverSpec.method),
    'time_step': _Field(_time_step, 'the time step in s, or auto', SolverSpec.time_step),
    'friction_impulse': _Field(_boolean, 'true or false', SolverSpec.friction_impulse),
    'tolerance': _Field(_num(0.0, 1e-2, lo_open=True), 'a relative tolerance',
                        SolverSpec.tolerance),
    'restitution_law': _Field(lambda v, p: _choice(v, p, RESTITUTION_LAWS),
                              'one of ' + ', '.join(RESTITUTION_LAWS),
                              SolverSpec.restitution_law),
}


def _solver(value, path: str) -> SolverSpec:
    given = {} if value is None else value
    f = _fields(given, path, _SOLVER)
    if f['time_step'] == _STEP_AUTO:
        _auto_method(f['method'], _join(path, 'time_step'))
        # the first candidate follows from the drives: parse_scene sets it
        f.update(time_step=SolverSpec.time_step, time_step_auto=True)
        if 'tolerance' not in given:
            f['tolerance'] = AUTO_TOLERANCE
        elif f['tolerance'] < AUTO_MIN_TOLERANCE:
            raise _Invalid(_join(path, 'tolerance'), _auto_tolerance_problem(f['tolerance']))
    return SolverSpec(**f)


def _auto_tolerance_problem(tolerance: float) -> str:
    return (f"{tolerance:g} with time_step: auto asks for the conveying speed to "
            f"{100 * tolerance:g} %, beyond a first-order step's reach: give "
            f'{AUTO_MIN_TOLERANCE:g} or more (e.g. 0.01 for 1 %)')


def _auto_method(method: str, path: str) -> None:
    if method != 'time_stepping':
        raise _Invalid(path, f'auto picks the fixed step of time_stepping, not of {method}: '
                             'give a step in s (e.g. 1.0e-4) or method: time_stepping')


def _auto_first_step(solver: SolverSpec, bodies) -> SolverSpec:
    """``time_step: auto``: the pilot's first candidate, a fraction of the fastest drive's
    period (the pilot measures a conveying speed: a scene without a drive has none)."""
    frequencies = [b.vibration.frequency for b in bodies
                   if b.vibration is not None and b.vibration.frequency > 0.0]
    if not frequencies:
        raise _Invalid('solver.time_step', 'auto picks the step that keeps the conveying speed '
                                           'within solver.tolerance, and no body vibrates '
                                           '(vibration.frequency > 0): give a step in s')
    step = 1.0 / (AUTO_FIRST_STEPS_PER_PERIOD * max(frequencies))
    return replace(solver, time_step=min(max(step, MIN_TIME_STEP_S), 0.1))


_BODY = {
    'name': _Field(lambda v, p: _body_name(v, p), 'a unique name'),
    'type': _Field(lambda v, p: _choice(v, p, BODY_TYPES), 'one of ' + ', '.join(BODY_TYPES)),
    'polygon': _Field(_polygon, 'a list of [x, y] vertices (m)', None),
    'polygons': _Field(_pieces, 'a list of convex pieces', None),
    'pose': _Field(lambda v, p: _vec(v, p, 3, '[x, y, theta] (m, m, rad)', POSE_BOUNDS),
                   '[x, y, theta] (m, m, rad)'),
    'velocity': _Field(lambda v, p: _vec(v, p, 3, '[vx, vy, omega] (m/s, m/s, rad/s)',
                                         VELOCITY_BOUNDS),
                       '[vx, vy, omega] (m/s, m/s, rad/s)', np.zeros(3)),
    'mass': _Field(_num(MIN_MASS_KG, MAX_MASS_KG, unit='kg',
                        hint='outside it inverse masses and mass ratios lose the physics'),
                   'the mass in kg', None),
    'density': _Field(_num(MIN_DENSITY, MAX_DENSITY, unit='kg/m^2'),
                      'the areal density in kg/m^2', None),
    'mu_static': _Field(_num(0.0, MAX_FRICTION), 'a friction coefficient', 0.0),
    'mu_dynamic': _Field(_num(0.0, MAX_FRICTION), 'a friction coefficient', None),
    'restitution': _Field(_num(0.0, 1.0), 'a coefficient of restitution', 0.0),
    'vibration': _Field(_vibration, 'a mapping with amplitude, frequency, angle', None,
                        nullable=True),
}

_WHY_NO_MASS = {
    'static': 'a static body never moves',
    'kinematic': "a kinematic body's motion is prescribed (by `vibration`)",
}


def _body(value, path: str) -> BodySpec:
    f = _fields(value, path, _BODY)
    kind = f['type']
    outline, pieces = f['polygon'], f['polygons']
    if outline is not None and pieces is not None:
        raise _Invalid(path, 'give either `polygon` (one simple outline) or `polygons` '
                             '(a list of convex pieces), not both')
    if outline is None and pieces is None:
        raise _Invalid(_join(path, 'polygon'),
                       'missing the shape; add `polygon: [[x, y], ...]` (a simple '
                       'counter-clockwise outline, m) or `polygons:` (a list of convex pieces)')
    if outline is not None:
        outlines = (outline,)
        convex, widths = _decomposed(_outline_key(outline))
    else:
        outlines, convex = pieces, tuple(geometry.drop_collinear(p) for p in pieces)
        widths = tuple(geometry.min_width(p) for p in convex)
    for k, width in enumerate(widths):
        if width < MIN_PIECE_WIDTH_M:
            where = (_join(path, 'polygon') if outline is not None
                     else f"{_join(path, 'polygons')}[{k}]")
            raise _Invalid(where, f'a convex piece is {width:.3g} m thin (at least '
                                  f'{MIN_PIECE_WIDTH_M:g} m): contacts cannot resolve it; '
                                  'straighten nearly collinear vertices or thicken the sliver')

    if kind == 'dynamic':
        if f['mass'] is not None and f['density'] is not None:
            raise _Invalid(_join(path, 'density'), 'give either `mass` (kg) or `density` '
                                                   '(kg/m^2), not both')
        if f['mass'] is None and f['density'] is None:
            raise _Invalid(_join(path, 'mass'), 'a dynamic body needs `mass` (kg) or `density` '
                                                '(kg/m^2); its inertia follows from the shape')
    else:
        for key in ('mass', 'density'):
            if f[key] is not None:
                raise _Invalid(_join(path, key),
                               f'{_WHY_NO_MASS[kind]}, so it takes no {key}; remove `{key}` '
                               'or make the body `type: dynamic`')
        if np.any(f['velocity'] != 0):
            raise _Invalid(_join(path, 'velocity'),
                           f'{_WHY_NO_MASS[kind]}, so its velocity must be [0, 0, 0] or left '
                           'out; give it `type: dynamic` to set an initial velocity')

    mu_s = f['mu_static']
    mu_d = mu_s if f['mu_dynamic'] is None else f['mu_dynamic']
    if mu_d > mu_s:
        default = '' if 'mu_static' in value else ', the default'
        raise _Invalid(_join(path, 'mu_dynamic'),
                       f'mu_dynamic ({mu_d:g}) must not exceed mu_static ({mu_s:g}{default}); '
                       'expected 0 <= mu_dynamic <= mu_static')
    if f['vibration'] is not None and kind != 'kinematic':
        raise _Invalid(_join(path, 'vibration'), f'only kinematic bodies vibrate, this one is '
                                                 f'{kind}; use `type: kinematic` or remove '
                                                 '`vibration`')
    return BodySpec(name=f['name'], type=kind, pieces=convex, outlines=outlines, pose=f['pose'],
                    velocity=f['velocity'], mass=f['mass'], density=f['density'],
                    mu_static=mu_s, mu_dynamic=mu_d, restitution=f['restitution'],
                    vibration=f['vibration'])


def _bodies(value, path: str) -> tuple[BodySpec, ...]:
    if not _is_list(value) or len(value) == 0:
        raise _Invalid(path, f'expected a non-empty list of bodies, got {_describe(value)}')
    bodies = []
    first_use: dict[str, int] = {}
    for k, item in enumerate(value):
        body = _body(item, f'{path}[{k}]')
        if body.name in first_use:
            raise _Invalid(f'{path}[{k}].name',
                           f'duplicate body name {body.name!r} (also used by '
                           f'{path}[{first_use[body.name]}]); body names must be unique')
        first_use[body.name] = k
        bodies.append(body)
    _check_start_overlap(bodies, path)
    return tuple(bodies)


def overlap_problem(a: str, piece_a: np.ndarray, b: str, piece_b: np.ndarray,
                    when: str = 'at the start') -> str | None:
    """Why part ``a``'s convex piece cannot be placed where it overlaps body ``b``'s (world
    frame, m), or None: more than MAX_START_OVERLAP of the thinner piece inside."""
    depth = geometry.convex_penetration(piece_a, piece_b)
    allowed = MAX_START_OVERLAP * min(geometry.min_width(piece_a), geometry.min_width(piece_b))
    if depth <= allowed:
        return None
    return (f'{a!r} and {b!r} overlap by {depth:.3g} m {when} (more than {allowed:.3g} m, a '
            'quarter of the thinner piece); move them apart: parts must start outside other '
            'bodies')


def check_placement(name: str, pose, velocity) -> tuple[str, np.ndarray, np.ndarray]:
    """A part's ``name``, ``pose`` and ``velocity`` checked as a scene file's body fields are
    (SceneError naming the field): a part placed in a running world."""
    pose, velocity = (x.tolist() if isinstance(x, np.ndarray) else x for x in (pose, velocity))
    try:
        return (_body_name(name, 'name'),
                _vec(pose, 'pose', 3, '[x, y, theta] (m, m, rad)', POSE_BOUNDS),
                _vec(velocity, 'velocity', 3, '[vx, vy, omega] (m/s, m/s, rad/s)',
                     VELOCITY_BOUNDS))
    except _Invalid as err:
        raise SceneError(err.message, err.path, source='') from None


def _check_start_overlap(bodies: list[BodySpec], path: str) -> None:
    """Refuse a part that starts deep inside another body (MAX_START_OVERLAP of the thinner
    piece): contacts that deep are not found, so the part would pass through or keep
    colliding with what encloses it."""
    world, owner = [], []
    for k, body in enumerate(bodies):
        c, s_ = math.cos(body.pose[2]), math.sin(body.pose[2])
        rot = np.array([[c, -s_], [s_, c]])
        origin = body.pose[:2].copy()
        if body.vibration is not None:      # where the drive puts it at t = 0
            v = body.vibration
            direction = body.pose[2] + v.angle
            origin += v.amplitude * math.sin(v.phase) * np.array([math.cos(direction),
                                                                   math.sin(direction)])
        for piece in body.pieces:
            world.append(piece @ rot.T + origin)
            owner.append(k)
    if len(world) < 2:
        return
    owner = np.array(owner)
    dynamic = np.array([bodies[k].type == 'dynamic' for k in owner])
    lo = np.array([w.min(axis=0) for w in world])
    hi = np.array([w.max(axis=0) for w in world])
    for i in np.flatnonzero(dynamic):
        # the pieces whose boxes overlap piece i's (each pair once if both are dynamic)
        near = np.flatnonzero(np.all(lo <= hi[i], axis=1) & np.all(hi >= lo[i], axis=1)
                              & (owner != owner[i]) & (~dynamic | (np.arange(len(world)) > i)))
        for j in near:
            problem = overlap_problem(bodies[owner[i]].name, world[i], bodies[owner[j]].name,
                                      world[j])
            if problem:
                raise _Invalid(f'{path}[{owner[j] if owner[j] > owner[i] else owner[i]}].pose',
                               problem)


def _track_name(value, path: str) -> str | None:
    return None if value is None else _string(value, path)


def _interval(value, path: str) -> tuple[float, float]:
    lo, hi = _vec(value, path, 2, '[low, high] (m)', (MAX_LENGTH_M,) * 2)
    if lo > hi:
        raise _Invalid(path, f'[{lo:g}, {hi:g}] is empty; give [low, high]')
    return float(lo), float(hi)


def _region(value, path: str):
    f = _fields(value, path, {'x': _Field(_interval, '[low, high] (m)'),
                              'y': _Field(_interval, '[low, high] (m)')})
    return f['x'], f['y']


def _orientations_drawn(value, path: str) -> tuple[tuple[str, float, float], ...]:
    if not isinstance(value, Mapping) or not value:
        raise _Invalid(path, 'expected a mapping of name: {angle: rad, share: fraction}')
    out = []
    for name, spec in value.items():
        f = _fields(spec, _join(path, str(name)),
                    {'angle': _Field(_num(-MAX_ANGLE_RAD, MAX_ANGLE_RAD, unit='rad'),
                                     'the angle in rad'),
                     'share': _Field(_num(0.0, 1.0), 'a fraction of the parts', None)})
        out.append((str(name), f['angle'], f['share']))
    given = [share for _, _, share in out if share is not None]
    rest = [k for k, (_, _, share) in enumerate(out) if share is None]
    left = 1.0 - sum(given)
    if left < -1e-9 or (not rest and abs(left) > 1e-9):
        raise _Invalid(path, f'the shares add up to {sum(given):g}; they must add up to 1 '
                             '(leave some out to share the rest equally)')
    for k in rest:
        out[k] = (out[k][0], out[k][1], max(left, 0.0) / len(rest))
    return tuple(out)


_SOURCE = {
    'template': _Field(_string, 'the name of a dynamic body of the scene'),
    'interval': _Field(_num(1e-3, 1e6, unit='s', hint='one part per interval'),
                       'the time between two parts, s', None),
    'rate': _Field(_num(1e-6, 1e3, unit='parts/s'), 'parts per second (or give interval)',
                   None),
    'region': _Field(_region, '{x: [low, high], y: [low, high]} (m)'),
    'orientations': _Field(_orientations_drawn, 'name: {angle: rad, share: fraction}', None),
    'start': _Field(_num(0.0, unit='s'), 'the first arrival, s', 0.0),
    'count': _Field(lambda v, p: _whole(v, p, 0, 10 ** 6), 'a number of parts (0: no limit)',
                    0),
    'seed': _Field(lambda v, p: _whole(v, p, 0, 2 ** 32), 'a whole number', 0),
}
_SINK = {
    'below': _Field(lambda v, p: None if v is None else _number(v, p, -MAX_LENGTH_M,
                                                                 MAX_LENGTH_M, unit='m'),
                    'a height, m (world)', None, nullable=True),
    'past_exit': _Field(_boolean, 'true or false', False),
}


def _sources(value, path: str) -> tuple[SourceSpec, ...]:
    if value is None:
        return ()
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of sources, got {_describe(value)}')
    out = []
    for k, item in enumerate(value):
        f = _fields(item, f'{path}[{k}]', _SOURCE)
        rate = f.pop('rate')
        if (rate is None) == (f['interval'] is None):
            raise _Invalid(f'{path}[{k}]', 'give either interval (s between parts) or rate '
                                            '(parts per second)')
        if rate is not None:
            f['interval'] = 1.0 / rate
        if f['orientations'] is None:
            f['orientations'] = (('as_template', math.nan, 1.0),)
        out.append(SourceSpec(**f))
    return tuple(out)


def _sensor_line(value, path: str) -> tuple[tuple[float, float], tuple[float, float]]:
    if not _is_list(value) or len(value) != 2:
        raise _Invalid(path, f'expected two points [[x0, y0], [x1, y1]] (m, world), got '
                             f'{_describe(value)}')
    a, b = (_vec(p, f'{path}[{k}]', 2, '[x, y] (m)', (MAX_LENGTH_M,) * 2)
            for k, p in enumerate(value))
    if math.hypot(*(b - a)) < MIN_OUTLINE_M:
        raise _Invalid(path, f'the two points are {math.hypot(*(b - a)):.3g} m apart; a sensor '
                             f'line needs at least {MIN_OUTLINE_M:g} m')
    return (float(a[0]), float(a[1])), (float(b[0]), float(b[1]))


def _whole(value, path: str, lo: int, hi: int) -> int:
    x = _number(value, path, lo, hi)
    if x != int(x):
        raise _Invalid(path, f'expected a whole number in [{lo}, {hi}], got {x!r}')
    return int(x)


# Body names end up in ROS frame ids (tf), key paths (bodies[name].mass) and CSV columns.
_BODY_NAME = re.compile(r'[A-Za-z0-9_][A-Za-z0-9_-]*\Z')


def _name_matching(pattern: re.Pattern, refusal: str):
    """A checker of names that ``pattern`` matches, refusing others with ``refusal``."""
    def check(value, path: str) -> str:
        name = _string(value, path)
        if not pattern.match(name):
            raise _Invalid(path, f'{name!r} {refusal}')
        return name
    return check


_body_name = _name_matching(_BODY_NAME, 'is not a body name: use letters, digits, _ and - (it '
                                        'names a ROS frame and a key path such as '
                                        'bodies[name].mass)')

_IDENTIFIER = re.compile(r'[A-Za-z_][A-Za-z0-9_]*\Z')
_sensor_name = _name_matching(_IDENTIFIER, 'is not a name a ROS topic can carry; use letters, '
                                           'digits and _, not starting with a digit')


def _sensor_kind(value, path: str) -> str:
    kind = _string(value, path)
    if kind not in SENSOR_KINDS:
        raise _Invalid(path, f'unknown sensor type {kind!r}{_suggest(kind, SENSOR_KINDS)}; '
                             f'expected one of: {", ".join(SENSOR_KINDS)}')
    return kind


_SENSOR = {
    'name': _Field(_sensor_name, 'a name (letters, digits, _)'),
    'type': _Field(_sensor_kind, 'beam or inspection'),
    'line': _Field(_sensor_line, '[[x0, y0], [x1, y1]] (m, world)'),
}


def _sensors(value, path: str) -> tuple[SensorSpec, ...]:
    if value is None:
        return ()
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of sensors, got {_describe(value)}')
    out: list[SensorSpec] = []
    for k, item in enumerate(value):
        f = _fields(item, f'{path}[{k}]', _SENSOR)
        if f['name'] in {x.name for x in out}:
            raise _Invalid(f'{path}[{k}].name', f'two sensors are named {f["name"]!r}')
        out.append(SensorSpec(f['name'], f['type'], *f['line']))
    return tuple(out)


def _sinks(value, path: str) -> tuple[SinkSpec, ...]:
    if value is None:
        return ()
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of sinks, got {_describe(value)}')
    out = []
    for k, item in enumerate(value):
        sink = SinkSpec(**_fields(item, f'{path}[{k}]', _SINK))
        if sink.below is None and not sink.past_exit:
            raise _Invalid(f'{path}[{k}]', 'a sink takes parts below a height or past the exit: '
                                           'give below (m) or past_exit: true')
        out.append(sink)
    return tuple(out)


_TOP = {
    'name': _Field(_string, 'a text', _AUTO),
    # read first, by parse_scene (the numbers of the rest may be expressions of them)
    'parameters': _Field(lambda v, p: v, 'a mapping of named parameters', None, nullable=True),
    'gravity': _Field(lambda v, p: _vec(v, p, 2, '[gx, gy] (m/s^2)', (MAX_GRAVITY_MPS2,) * 2),
                      '[gx, gy] (m/s^2)',
                      np.array(DEFAULT_GRAVITY)),
    'track': _Field(_track_name, 'the name of a body', _AUTO, nullable=True),
    'solver': _Field(_solver, 'a mapping of solver settings', SolverSpec(), nullable=True),
    'bodies': _Field(_bodies, 'a non-empty list of bodies'),
    'outcomes': _Field(lambda v, p: _outcomes(v, p), 'a mapping of outcome settings',
                       OutcomeSpec(), nullable=True),
    'sources': _Field(_sources, 'a list of sources (parts added while running)', (),
                      nullable=True),
    'sinks': _Field(_sinks, 'a list of sinks (parts taken away while running)', (),
                    nullable=True),
    'sensors': _Field(_sensors, 'a list of sensors (lines across the parts\' path)', (),
                      nullable=True),
    'description': _Field(_string, 'a line of text saying what the scene is', ''),
}


_OUTCOMES = {
    'exit_position': _Field(lambda v, p: None if v is None else _number(
        v, p, -MAX_LENGTH_M, MAX_LENGTH_M, unit='m'),
                            'the along-track position (m) where parts leave', None,
                            nullable=True),
    'jam_time': _Field(_num(0.0, lo_open=True, unit='s'), 'a time in s', OutcomeSpec.jam_time),
    'jam_distance': _Field(_num(0.0, lo_open=True, unit='m'), 'a distance in m',
                           OutcomeSpec.jam_distance),
    'exit_axis': _Field(lambda v, p: None if v is None else _direction(v, p),
                        'a world direction [x, y]', None, nullable=True),
    'orientations': _Field(lambda v, p: _orientations(v, p),
                           'a mapping of orientation names to angles (rad)', (), nullable=True),
    'orientation_tolerance': _Field(_num(0.0, math.pi, lo_open=True, unit='rad'),
                                    'an angle in rad', OutcomeSpec.orientation_tolerance),
}


def _direction(value, path: str) -> tuple[float, float]:
    v = _vec(value, path, 2, '[x, y]')
    norm = math.hypot(*v)
    if norm == 0.0:
        raise _Invalid(path, 'expected a non-zero direction, for example [0.0, -1.0] for down')
    return (float(v[0] / norm), float(v[1] / norm))


def _orientations(value, path: str) -> tuple[tuple[str, float], ...]:
    if value is None:
        return ()
    if not isinstance(value, Mapping):
        raise _Invalid(path, 'expected a mapping of names to angles in rad, for example '
                             f'{{open_end_up: 1.5708}}; got {_describe(value)}')
    out = []
    for key, angle in value.items():
        sub = _join(path, str(key))
        out.append((_string(key, sub), _number(angle, sub, -MAX_ANGLE_RAD, MAX_ANGLE_RAD,
                                               unit='rad')))
    return tuple(out)


def _outcomes(value, path: str) -> OutcomeSpec:
    return OutcomeSpec(**_fields({} if value is None else value, path, _OUTCOMES))


def _default_track(bodies: tuple[BodySpec, ...]) -> str | None:
    for wanted in (lambda b: b.type == 'kinematic' and b.vibration is not None,
                   lambda b: b.type != 'dynamic'):
        for b in bodies:
            if wanted(b):
                return b.name
    return None


def _default_name(source: str) -> str:
    return 'unnamed' if source.startswith('<') else Path(source).stem


_PARAMETER = {
    'default': _Field(lambda v, p: _number(v, p), 'the default value'),
    'unit': _Field(_string, 'a unit (text)', ''),
    'min': _Field(lambda v, p: _number(v, p), 'the smallest value allowed', None),
    'max': _Field(lambda v, p: _number(v, p), 'the largest value allowed', None),
    'description': _Field(_string, 'a text', ''),
}


def _parameters(value, given: Mapping[str, float]) -> dict[str, float]:
    """The parameters' values: ``given`` where given, else their defaults, within bounds."""
    if value is not None and not isinstance(value, Mapping):
        raise _Invalid('parameters', 'expected a mapping of name: default, or name: {default, '
                                     f'unit, min, max}}; got {_describe(value)}')
    specs = value or {}
    out = {}
    for name, spec in specs.items():
        path = f'parameters.{name}'
        if not isinstance(name, str) or not _IDENTIFIER.match(name):
            raise _Invalid(path, f'{name!r} is not a name; use letters, digits and _')
        if name in EXPRESSION_FUNCTIONS or name in EXPRESSION_CONSTANTS:
            raise _Invalid(path, f'{name!r} is taken by a function or constant of '
                                 'expressions; choose another name')
        f = (_fields(spec, path, _PARAMETER) if isinstance(spec, Mapping)
             else {'default': _number(spec, path), 'min': None, 'max': None})
        x = _number(given[name], path) if name in given else f['default']
        if (f['min'] is not None and x < f['min']) or (f['max'] is not None and x > f['max']):
            raise _Invalid(path, f'{x:g} is outside its bounds [{f["min"]}, {f["max"]}]')
        out[name] = x
    unknown = sorted(set(given) - set(out))
    if unknown:
        raise _Invalid('parameters', f'no parameter named {", ".join(unknown)}; the scene '
                                     f'declares: {", ".join(out) or "none"}')
    return out


def override_solver(solver: SolverSpec, changes: Mapping[str, Any],
                    source: str = '<override>') -> SolverSpec:
    """``solver`` with ``changes`` (solver keys) checked as a scene file's would be; raises
    SceneError naming ``solver.<key>``. What the CLI and the node's parameters go through."""
    out = {}
    try:
        for key, value in changes.items():
            if key not in _SOLVER:
                raise _Invalid(_join('solver', key), f'unknown key {key!r}; allowed keys: '
                                                     + ', '.join(_SOLVER))
            out[key] = _SOLVER[key].check(value, _join('solver', key))
        if out.get('time_step') == _STEP_AUTO:
            raise _Invalid('solver.time_step', 'auto is a scene file\'s setting (its drives '
                                               'give the first candidate): give a step in s')
        if 'time_step' in out:
            out['time_step_auto'] = False          # a step given replaces the pilot's
        elif solver.time_step_auto:
            _auto_method(out.get('method', solver.method), 'solver.time_step')
            if out.get('tolerance', AUTO_MIN_TOLERANCE) < AUTO_MIN_TOLERANCE:
                raise _Invalid('solver.tolerance', _auto_tolerance_problem(out['tolerance']))
    except _Invalid as err:
        raise SceneError(err.message, err.path, source) from None
    return replace(solver, **out)


def parse_scene(data: Mapping, source: str = '<dict>',
                parameters: Mapping[str, float] | None = None) -> Scene:
    """Validate a scene given as plain data (as loaded from YAML); raises SceneError.

    A scene may declare ``parameters`` (name: default, or name: {default, unit, min, max});
    any number in it may then be an expression of them. ``parameters`` here gives values
    other than the defaults (a study's design)."""
    token = None
    try:
        if isinstance(data, Mapping):
            values = _parameters(data.get('parameters'), parameters or {})
            data = {k: v for k, v in data.items() if k != 'parameters'}
            if values:
                token = _PARAMETER_VALUES.set(values)
        else:
            values = {}
        f = _fields(data, '', _TOP)
        bodies = f['bodies']
        track = f['track']
        if track is _AUTO:
            track = _default_track(bodies)
        elif track is not None and track not in {b.name for b in bodies}:
            names = [b.name for b in bodies]
            raise _Invalid('track', f'no body named {track!r}{_suggest(track, names)}; '
                                    f'expected one of: {", ".join(names)}')
        name = _default_name(source) if f['name'] is _AUTO else f['name']
        if f['solver'].time_step_auto:
            f['solver'] = _auto_first_step(f['solver'], bodies)
        exit_at = None if f['outcomes'] is None else f['outcomes'].exit_position
        for k, sink in enumerate(f['sinks'] or ()):
            if sink.past_exit and exit_at is None:
                raise _Invalid(f'sinks[{k}].past_exit', 'the scene has no exit: give '
                                                        'outcomes.exit_position (m along the '
                                                        'track)')
        templates = {b.name for b in bodies if b.type == 'dynamic'}
        for k, src in enumerate(f['sources'] or ()):
            if src.template not in templates:
                raise _Invalid(f'sources[{k}].template',
                               f'no dynamic body named {src.template!r}'
                               f'{_suggest(src.template, sorted(templates))}; expected one of: '
                               f'{", ".join(sorted(templates)) or "none"}')
        return Scene(name=name, gravity=f['gravity'], solver=f['solver'], bodies=bodies,
                     track=track, source=source, description=f['description'],
                     outcomes=f['outcomes'] if f['outcomes'] is not None else OutcomeSpec(),
                     parameters=values, sources=f['sources'] or (), sinks=f['sinks'] or (),
                     sensors=f['sensors'] or ())
    except _Invalid as err:
        raise SceneError(err.message, err.path, source) from None
    finally:
        if token is not None:
            _PARAMETER_VALUES.reset(token)


# --------------------------------------------------------------------------------------------
# Files


class _DuplicateKey(yaml.MarkedYAMLError):
    pass


class _NoDuplicateKeys:
    """A mapping whose key appears twice is an error (PyYAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == 'tag:yaml.org,2002:merge':
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node.start_mark)
            except TypeError:
                continue   # unhashable key: the base class reports it
            if first is not key_node.start_mark:
                err = _DuplicateKey('while reading a mapping', node.start_mark,
                                    f'duplicate key {key!r}', key_node.start_mark)
                err.first_line = first.line + 1
                raise err
        return super().construct_mapping(node, deep)


# PyYAML follows YAML 1.1, where 1e-3 (no dot) and 1.0e3 (unsigned exponent) are text.
_FLOAT_12 = re.compile(r'''^(?:
      [-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+
    | [-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
    )$''', re.VERBOSE)


class _SceneLoader(_NoDuplicateKeys, yaml.SafeLoader):
    """SafeLoader with YAML 1.2 floats and an error on duplicate keys."""


class _FastSceneLoader(_NoDuplicateKeys, getattr(yaml, 'CSafeLoader', yaml.SafeLoader)):
    """_SceneLoader on libyaml's parser where PyYAML has it: five times faster on a scene of
    thousands of parts. A file it refuses is read again by _SceneLoader, whose messages and
    marks are the ones reported."""


for _loader in (_SceneLoader, _FastSceneLoader):
    _loader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_12,
                                  list('-+0123456789.'))


def scene_dirs() -> list[Path]:
    """Existing directories searched for shipped scenes, in order.

    $FEEDER_SIM_CONFIG (a list separated by os.pathsep), <sys.prefix>/share/feeder_sim/config,
    <prefix>/share/feeder_sim/config for each prefix in $AMENT_PREFIX_PATH (a sourced colcon
    install), and the source tree's config/.
    """
    candidates = [Path(p).expanduser()
                  for p in os.environ.get('FEEDER_SIM_CONFIG', '').split(os.pathsep) if p]
    candidates.append(Path(sys.prefix) / 'share' / 'feeder_sim' / 'config')
    candidates += [Path(p) / 'share' / 'feeder_sim' / 'config'
                   for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    candidates.append(Path(__file__).resolve().parents[2] / 'config')
    found: list[Path] = []
    for d in candidates:
        if d.is_dir() and d.resolve() not in {f.resolve() for f in found}:
            found.append(d)
    return found


def _is_ros_params(data) -> bool:
    return isinstance(data, Mapping) and any(
        isinstance(v, Mapping) and 'ros__parameters' in v for v in data.values())


def shipped_scenes() -> list[str]:
    """Names of the scenes in :func:`scene_dirs` (``*.yaml`` files, minus ROS parameter files)."""
    names = set()
    for d in scene_dirs():
        for f in d.glob('*.yaml'):
            try:
                data = read_yaml(f)
            except SceneError:
                data = None   # listed anyway, so that loading it shows the problem
            if not _is_ros_params(data):
                names.add(f.stem)
    return sorted(names)


def _find(path_or_name: str | os.PathLike) -> Path:
    given = os.fspath(path_or_name)
    if not str(given).strip():
        raise SceneError('no scene given: name a scene file or a shipped scene ('
                         f'{", ".join(shipped_scenes()) or "none found"})', source='<scene>')
    path = Path(given)
    if path.is_file():
        return path
    if path.is_dir():
        raise SceneError(f'{path.resolve()} is a directory; expected a .yaml scene file',
                         source=given)
    tried = [str(path.resolve())]
    looks_like_name = os.sep not in given and (os.altsep is None or os.altsep not in given)
    if looks_like_name:
        file_name = given if path.suffix in ('.yaml', '.yml') else f'{given}.yaml'
        for d in scene_dirs():
            candidate = d / file_name
            if candidate.is_file():
                return candidate
            tried.append(str(candidate))
    shipped = shipped_scenes()
    raise SceneError(f'scene not found; looked for {", ".join(tried)}. Give the path of a .yaml '
                     'file or the name of a shipped scene '
                     f'({", ".join(shipped) if shipped else "none found"}); '
                     'set FEEDER_SIM_CONFIG to add a scene directory', source=given)


def _check_nesting(data: Any, source: str) -> None:
    """Refuse data nested deeper than MAX_NESTING, expanding to more than MAX_VALUES values or
    holding itself. YAML aliases share one object among every place that names it, so a
    file of a few hundred bytes can stand for billions of values (ten levels of nine
    aliases): each object is visited once, iteratively, and its expanded size and depth are
    summed from its children's."""
    done: dict[int, tuple[int, int] | None] = {}     # id -> (values, depth); None: open
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        item, closing = stack.pop()
        if not isinstance(item, (dict, list)):
            continue
        kids = [c for c in (item.values() if isinstance(item, dict) else item)
                if isinstance(c, (dict, list))]
        if not closing:
            if id(item) in done:
                continue
            done[id(item)] = None
            stack.append((item, True))
            for kid in kids:
                if id(kid) in done and done[id(kid)] is None:
                    raise SceneError('a YAML alias refers to a mapping or list that contains '
                                     'it; write the repeated part out', source=source)
                stack.append((kid, False))
            continue
        sizes = [done[id(kid)] for kid in kids]
        values = len(item) + sum(v for v, _ in sizes)
        depth = 1 + max((d for _, d in sizes), default=0)
        if depth > MAX_NESTING:
            raise SceneError(f'nested deeper than {MAX_NESTING} levels; a scene file needs '
                             'about 6', source=source)
        if values > MAX_VALUES:
            raise SceneError(f'its YAML aliases expand to more than {MAX_VALUES} values; a '
                             'scene file needs some thousands: write repeated parts out or '
                             'name fewer aliases', source=source)
        done[id(item)] = (values, depth)


def read_yaml(path: Path, source: str | None = None) -> Any:
    """The plain data of a YAML file as scene files are read (module docstring: YAML 1.2
    floats, no duplicate keys), within MAX_FILE_BYTES, MAX_NESTING and MAX_VALUES; any
    problem is one SceneError naming ``source`` (default: the path) and the fix."""
    source = str(path) if source is None else source
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise SceneError(f'the file is {size / 2 ** 20:.1f} MiB; scene files are limited to '
                             f'{MAX_FILE_BYTES / 2 ** 20:.0f} MiB (a scene of thousands of parts '
                             'is well under one)', source=source)
        text = path.read_text(encoding='utf-8')
    except UnicodeDecodeError as err:
        raise SceneError(f'not UTF-8 text ({err.reason} at byte {err.start}); save the file as '
                         'UTF-8', source=source) from None
    except OSError as err:
        raise SceneError(f'cannot read the file: {err.strerror}', source=source) from None
    try:
        try:
            data = yaml.load(text, Loader=_FastSceneLoader)
        except yaml.YAMLError:
            data = yaml.load(text, Loader=_SceneLoader)
        _check_nesting(data, source)
    except RecursionError:
        raise SceneError(f'nested deeper than {MAX_NESTING} levels; a scene file needs about 6',
                         source=source) from None
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        line, column = (mark.line + 1, mark.column + 1) if mark else (None, None)
        where = f' at line {line}, column {column}' if mark else ''
        if isinstance(err, _DuplicateKey):
            raise SceneError(f'{err.problem}{where} (first given at line {err.first_line}); '
                             'each key may appear only once', source=source, line=line,
                             column=column) from None
        problem = err.problem or str(err)
        hint = ('; YAML indentation must use spaces, not tabs' if '\\t' in problem
                else '; check the indentation, colons and brackets there')
        raise SceneError(f'YAML syntax error{where}: {problem}{hint}', source=source,
                         line=line, column=column) from None
    except yaml.YAMLError as err:
        raise SceneError(f'YAML error: {err}', source=source) from None
    return data


def load_scene(path_or_name: str | os.PathLike,
               parameters: Mapping[str, float] | None = None) -> Scene:
    """Load and validate a scene file, given its path or the name of a shipped scene (and the
    values of its named parameters where not the defaults)."""
    data, source = read_scene_data(path_or_name)
    return parse_scene(data, source, parameters)


def read_scene_data(path_or_name: str | os.PathLike) -> tuple[Any, str]:
    """The plain data of a scene file (not yet validated) and its path, for tools that edit a
    scene before :func:`parse_scene` checks it; raises SceneError for what no reader takes."""
    path = _find(path_or_name)
    source = str(path)
    data = read_yaml(path, source)
    if data is None:
        raise SceneError('the file is empty; expected a mapping with at least `bodies`',
                         source=source)
    return data, source


# --------------------------------------------------------------------------------------------
# Back to plain data


def _floats(arr) -> list:
    return np.asarray(arr, dtype=float).tolist()


def scene_to_dict(scene: Scene) -> dict:
    """Plain data (YAML/JSON-ready) that :func:`parse_scene` turns back into an equal scene."""
    bodies = []
    for b in scene.bodies:
        d: dict[str, Any] = {'name': b.name, 'type': b.type}
        if len(b.outlines) == 1:
            d['polygon'] = _floats(b.outlines[0])
        else:
            d['polygons'] = [_floats(p) for p in b.outlines]
        d['pose'] = _floats(b.pose)
        d['velocity'] = _floats(b.velocity)
        for key in ('mass', 'density'):
            if getattr(b, key) is not None:
                d[key] = float(getattr(b, key))
        d.update(mu_static=float(b.mu_static), mu_dynamic=float(b.mu_dynamic),
                 restitution=float(b.restitution))
        if b.vibration is not None:
            d['vibration'] = {f.name: float(getattr(b.vibration, f.name))
                              for f in fields(Vibration)}
        bodies.append(d)
    s = scene.solver
    return {
        'name': scene.name,
        'gravity': _floats(scene.gravity),
        'track': scene.track,
        'solver': {'method': s.method,
                   'time_step': _STEP_AUTO if s.time_step_auto else float(s.time_step),
                   'friction_impulse': bool(s.friction_impulse),
                   'tolerance': float(s.tolerance),
                   'restitution_law': s.restitution_law},
        'bodies': bodies,
        'outcomes': _outcomes_dict(scene.outcomes),
        # the values used (every number above is already resolved)
        **({'parameters': {k: float(v) for k, v in scene.parameters.items()}}
           if scene.parameters else {}),
        **({'sources': [_source_dict(src) for src in scene.sources]} if scene.sources else {}),
        **({'sinks': [{'below': k.below, 'past_exit': k.past_exit} for k in scene.sinks]}
           if scene.sinks else {}),
        **({'sensors': [{'name': x.name, 'type': x.kind, 'line': [list(x.start), list(x.end)]}
                        for x in scene.sensors]} if scene.sensors else {}),
    }


def _source_dict(src: SourceSpec) -> dict:
    out = {'template': src.template, 'interval': src.interval, 'start': src.start,
           'count': src.count, 'seed': src.seed,
           'region': {'x': list(src.region[0]), 'y': list(src.region[1])}}
    if not (len(src.orientations) == 1 and math.isnan(src.orientations[0][1])):
        out['orientations'] = {name: {'angle': angle, 'share': share}
                               for name, angle, share in src.orientations}
    return out


def _outcomes_dict(spec: OutcomeSpec) -> dict:
    out = {f.name: getattr(spec, f.name) for f in fields(OutcomeSpec)}
    out['exit_axis'] = None if spec.exit_axis is None else list(spec.exit_axis)
    out['orientations'] = {name: angle for name, angle in spec.orientations}
    return out
