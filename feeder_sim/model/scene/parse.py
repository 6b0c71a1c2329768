"""Plain data -> :class:`Scene`: the fields of each block (solver, bodies, sources, sinks,
sensors, outcomes, parameters), the placement and start-overlap checks, and
:func:`scene_to_dict` back to plain data.

Optional blocks (``solver``, ``vibration``) written with no content (``solver:`` followed by only
comments) count as absent. ``track: null`` means "no track body".
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import fields, replace
import math
from pathlib import Path
import re
from typing import Any

import numpy as np

from feeder_sim.model import geometry
from feeder_sim.model.scene.errors import _describe, _Invalid, _is_list, SceneError
from feeder_sim.model.scene.expressions import (
    _PARAMETER_VALUES,
    EXPRESSION_CONSTANTS,
    EXPRESSION_FUNCTIONS,
)
from feeder_sim.model.scene.fields import (
    _AUTO,
    _boolean,
    _choice,
    _Field,
    _fields,
    _join,
    _name_matching,
    _num,
    _number,
    _string,
    _suggest,
    _vec,
    _whole,
)
from feeder_sim.model.scene.outlines import _decomposed, _outline_key, _pieces, _polygon
from feeder_sim.model.scene.specs import (
    AUTO_FIRST_STEP,
    AUTO_MIN_TOLERANCE,
    AUTO_TOLERANCE,
    BODY_TYPES,
    BodySpec,
    DEFAULT_GRAVITY,
    MAX_ANGLE_RAD,
    MAX_DENSITY,
    MAX_FRICTION,
    MAX_GRAVITY_MPS2,
    MAX_LENGTH_M,
    MAX_MASS_KG,
    MAX_START_OVERLAP,
    METHODS,
    MIN_DENSITY,
    MIN_MASS_KG,
    MIN_OUTLINE_M,
    MIN_PIECE_WIDTH_M,
    MIN_TIME_STEP_S,
    OutcomeSpec,
    POSE_BOUNDS,
    RESTITUTION_LAWS,
    Scene,
    SENSOR_KINDS,
    SensorSpec,
    SinkSpec,
    SolverSpec,
    SourceSpec,
    VELOCITY_BOUNDS,
    Vibration,
)
from feeder_sim.model.vibration import (
    drive_value_problem,
    MAX_AMPLITUDE_M,
    MAX_FREQUENCY_HZ,
)

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
    step = AUTO_FIRST_STEP.step(b.vibration.frequency for b in bodies if b.vibration is not None)
    if not math.isfinite(step):
        raise _Invalid('solver.time_step', 'auto picks the step that keeps the conveying speed '
                                           'within solver.tolerance, and no body vibrates '
                                           '(vibration.frequency > 0): give a step in s')
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


def _records(value, path: str, what: str, spec: dict) -> Iterator[tuple[str, dict]]:
    """Each item of the list of ``what`` at ``path`` (none if it is absent): its path and
    its fields as ``spec`` reads them."""
    if value is None:
        return
    if not _is_list(value):
        raise _Invalid(path, f'expected a list of {what}, got {_describe(value)}')
    for k, item in enumerate(value):
        yield f'{path}[{k}]', _fields(item, f'{path}[{k}]', spec)


def _sources(value, path: str) -> tuple[SourceSpec, ...]:
    out = []
    for where, f in _records(value, path, 'sources', _SOURCE):
        rate = f.pop('rate')
        if (rate is None) == (f['interval'] is None):
            raise _Invalid(where, 'give either interval (s between parts) or rate (parts per '
                                  'second)')
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


# Body names end up in ROS frame ids (tf), key paths (bodies[name].mass) and CSV columns.
_BODY_NAME = re.compile(r'[A-Za-z0-9_][A-Za-z0-9_-]*\Z')


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
    out: list[SensorSpec] = []
    for where, f in _records(value, path, 'sensors', _SENSOR):
        if f['name'] in {x.name for x in out}:
            raise _Invalid(f'{where}.name', f'two sensors are named {f["name"]!r}')
        out.append(SensorSpec(f['name'], f['type'], *f['line']))
    return tuple(out)


def _sinks(value, path: str) -> tuple[SinkSpec, ...]:
    out = []
    for where, f in _records(value, path, 'sinks', _SINK):
        sink = SinkSpec(**f)
        if sink.below is None and not sink.past_exit:
            raise _Invalid(where, 'a sink takes parts below a height or past the exit: give '
                                  'below (m) or past_exit: true')
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
