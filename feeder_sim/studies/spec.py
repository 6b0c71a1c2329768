"""A design study as written in a study file: the scene, what varies, the trials, the metrics.

    scene: track_one_box                 # a shipped scene or a path (relative to this file)
    duration: 2.0                        # simulated s per trial
    repeats: 3                           # trials per design, each with its own seed
    seed: 1                              # the study's; trial seeds derive from it
    parameters:                          # a scene parameter name or a key path
      bodies[track].vibration.amplitude: [2.0e-4, 3.0e-4]          # values
      bodies[track].vibration.frequency: {range: [40.0, 60.0], count: 3}
      hook_height: {sample: lhs, low: 0.002, high: 0.006, count: 8}
    perturb: {position_m: 1.0e-4, angle_rad: 0.01, drive_phase: true}
    metrics: [conveying_speed_mps, parts_fed, fraction:open_end_up]
    objective: {metric: conveying_speed_mps, goal: max}     # ranks designs (default: first)
    record: none                         # per-trial MCAP logs: none | all | jammed
    reference: pointmass                 # optional: the point-mass conveying speed per design
    convergence: true                    # optional: each design's numerical error (see below)

Value lists and ranges form a grid; sampled parameters (``random`` or ``lhs``, Latin
hypercube) are drawn together, ``count`` points seeded by ``seed``, and combined with the
grid. A trial's seed sets what ``perturb`` varies: each part's initial position and angle
(uniform within the given bounds) and each drive's phase, standing for the randomized
arrival of parts.

``convergence: true`` runs each design's first trial once more at the refined setting of
``feeder-sim run --error-estimate`` (half the step; event_driven: the tolerance / 100;
:mod:`feeder_sim.output.numerical_error`) and reports each metric's numerical error beside
its interval: one run per design, not per trial.
"""

from __future__ import annotations

from collections.abc import Mapping
import copy
from dataclasses import dataclass, field, replace
import hashlib
import itertools
import json
import math
from pathlib import Path
import re
from typing import Any

import numpy as np

from feeder_sim.model.scene import (
    METHODS,
    parse_scene,
    read_scene_data,
    read_yaml,
    Scene,
    SceneError,
)
from feeder_sim.model.scene.errors import _Invalid
from feeder_sim.model.scene.parse import _check_start_overlap
from feeder_sim.simulator import MAX_PUBLISH_RATE_HZ, MAX_STEPS_PER_RUN

MAX_TRIALS = 100_000
# perturb stands for how parts arrive (a few mm, a few degrees), not where they are: a larger
# spread is a different scene
MAX_PERTURB_POSITION_M = 0.1
MAX_PERTURB_ANGLE_RAD = math.pi
# value lists up to this long are checked value by value; longer ones, like ranges and
# samples, at their two ends (a scene checks its numbers against intervals)
CHECK_EACH_VALUE = 50
METRICS = {
    'conveying_speed_mps': 'mean speed of the parts along the track over the run, m/s',
    'final_position_m': "mean of the parts' final position along the track, m",
    'parts_fed': 'parts that passed the exit (outcomes.exit_position)',
    'feed_rate_per_min': 'parts fed per minute of simulated time',
    'feed_rate_steady_per_min': 'parts fed per minute between the first exit and the last',
    'jams': 'parts found jammed',
    'recirculated': 'parts a sink took back to the bowl (fell below its height)',
    'jammed': '1 when any part jammed, else 0 (a proportion over trials)',
    'fraction:<orientation>': 'share of the fed parts that left in that named orientation '
                              '(a proportion)',
    'rest:<orientation>': 'share of the parts lying in that named orientation at the end (a '
                          'proportion; a drop test)',
}


class StudyError(ValueError):
    """An invalid study file: the key path and what is expected, in one line."""

    def __init__(self, message: str, path: str = '', source: str = '<study>'):
        self.message, self.path, self.source = message, path, source
        super().__init__(': '.join(p for p in (source, path, message) if p))


@dataclass(frozen=True)
class Parameter:
    """One varied parameter: a scene parameter name or a key path, and its values."""

    name: str
    values: tuple[float, ...] = ()           # a grid axis
    sample: str | None = None                # 'random' | 'lhs': drawn jointly, see StudySpec
    low: float = 0.0
    high: float = 0.0
    count: int = 0
    is_range: bool = False                   # values from {range: ..., count: n}
    label: str | None = None                 # the plots' axis label (default: from the name)
    unit: str | None = None                  # the plots' unit (default: a known key path's)

    def checked_values(self) -> tuple[float, ...]:
        """The values a scene is checked at before the first trial: each listed one (up to
        CHECK_EACH_VALUE), else the ends."""
        if self.sample is not None:
            return (self.low, self.high)
        if self.is_range or len(self.values) > CHECK_EACH_VALUE:
            return tuple(dict.fromkeys((min(self.values), max(self.values))))
        return tuple(dict.fromkeys(self.values))


@dataclass(frozen=True)
class StudySpec:
    scene: str
    duration_s: float
    repeats: int
    seed: int
    parameters: tuple[Parameter, ...]
    metrics: tuple[str, ...]
    perturb: Mapping[str, float] = field(default_factory=dict)
    publish_rate_hz: float = 100.0
    method: str | None = None
    record: str = 'none'                     # per-trial MCAP logs: none | all | jammed
    reference: str | None = None             # 'pointmass': the theory beside the metric
    convergence: bool = False                # each design's numerical error, on one trial
    objective: str = ''                      # the metric that ranks designs (default: first)
    goal: str = 'max'                        # max | min
    source: str = '<study>'
    # the scene file's data, read once where the study is started: workers on other machines
    # need neither the file nor the path
    scene_data: Any = None
    scene_source: str = ''

    def design_count(self) -> int:
        """How many designs :meth:`designs` makes, without making them (exact integers: a
        grid of 100 000 x 100 000 is counted, not built)."""
        grid = math.prod(len(p.values) for p in self.parameters if p.sample is None)
        sampled = [p.count for p in self.parameters if p.sample is not None]
        return grid * (sampled[0] if sampled else 1)

    def first_design(self) -> dict[str, float]:
        """``designs()[0]`` without making the others."""
        if any(p.sample is not None for p in self.parameters):
            return self.designs(limit=1)[0]
        return {p.name: p.values[0] for p in self.parameters}

    def designs(self, limit: int | None = None) -> list[dict[str, float]]:
        """Every design, in a fixed order: the grid of value lists, times the sample."""
        grid = [p for p in self.parameters if p.sample is None]
        sampled = [p for p in self.parameters if p.sample is not None]
        points = [dict(zip([p.name for p in grid], combo, strict=True))
                  for combo in itertools.islice(itertools.product(*[p.values for p in grid]),
                                                limit)]
        if not sampled:
            return points
        rng = np.random.default_rng(self.seed)
        n = sampled[0].count
        if sampled[0].sample == 'lhs':
            # one value per stratum of each axis, strata paired at random
            unit = (np.stack([rng.permutation(n) for _ in sampled], 1)
                    + rng.random((n, len(sampled)))) / n
        else:
            unit = rng.random((n, len(sampled)))
        draws = [{p.name: float(p.low + u * (p.high - p.low)) for p, u in zip(sampled, row,
                                                                             strict=True)}
                 for row in unit]
        return [{**g, **d} for g in points for d in draws][:limit]

    def trial_seed(self, design: Mapping[str, float], repeat: int) -> int:
        """A seed of the design's values and the repeat: the same trial gets the same seed
        whoever runs it and in whatever order."""
        text = json.dumps([self.seed, sorted(design.items()), repeat])
        return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], 'little') >> 1


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and \
        math.isfinite(value)


def _number(value: Any, path: str, source: str, *, positive: bool = False) -> float:
    if not _is_number(value) or (positive and value <= 0):
        raise StudyError(f'expected a {"positive " if positive else ""}finite number, got '
                         f'{value!r}', path, source)
    return float(value)


_LABELS = ('label', 'unit')


def _parameter(name: str, value: Any, path: str, source: str) -> Parameter:
    if isinstance(value, list):
        value = {'values': value}
    if not isinstance(value, Mapping):
        raise StudyError('expected a list of values, {values: [...]}, {range: [lo, hi], count: '
                         'n} or {sample: random|lhs, low: lo, high: hi, count: n}', path,
                         source)
    names = {}
    for key in _LABELS:
        if key in value:
            if not isinstance(value[key], str) or not value[key].strip():
                raise StudyError(f'expected a text for the plots, got {value[key]!r}',
                                 f'{path}.{key}', source)
            names[key] = value[key].strip()
    if 'values' in value:
        values = value['values']
        if set(value) - {'values', *_LABELS} or not isinstance(values, list) or not values:
            raise StudyError('expected a non-empty list of values', path, source)
        return Parameter(name, tuple(_number(v, f'{path}[{k}]', source)
                                     for k, v in enumerate(values)), **names)
    count = value.get('count')
    if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= MAX_TRIALS:
        raise StudyError(f'count must be a whole number from 1 to {MAX_TRIALS}, got {count!r}',
                         f'{path}.count', source)
    if 'range' in value:
        extra = set(value) - {'range', 'count', *_LABELS}
        bounds = value['range']
        if extra or not (isinstance(bounds, list) and len(bounds) == 2):
            raise StudyError('a range is {range: [lo, hi], count: n}', path, source)
        lo, hi = (_number(b, f'{path}.range[{k}]', source) for k, b in enumerate(bounds))
        return Parameter(name, tuple(np.linspace(lo, hi, count).tolist()), is_range=True,
                         **names)
    if 'sample' in value:
        if value['sample'] not in ('random', 'lhs') or set(value) - {'sample', 'low', 'high',
                                                                   'count', *_LABELS}:
            raise StudyError('a sample is {sample: random|lhs, low: lo, high: hi, count: n}',
                             path, source)
        low = _number(value.get('low'), f'{path}.low', source)
        high = _number(value.get('high'), f'{path}.high', source)
        if not low < high:
            raise StudyError(f'low ({low:g}) must be below high ({high:g})', path, source)
        return Parameter(name, sample=value['sample'], count=count, low=low, high=high,
                         **names)
    raise StudyError('expected a list of values, {values: ...}, {range: ...} or {sample: ...}',
                     path, source)


_SEGMENT = re.compile(r'([A-Za-z_]\w*)((?:\[[^\]]+\])*)')


def set_path(data: dict, path: str, value: float) -> None:
    """Set the key path ``path`` (as the validator prints them: ``solver.time_step``,
    ``bodies[2].pose[1]``, bodies also by name: ``bodies[track].vibration.amplitude``) in
    scene data. Raises KeyError saying which part of the path is missing."""
    node: Any = data
    steps: list = []
    for segment in path.split('.'):
        m = _SEGMENT.fullmatch(segment)
        if not m:
            raise KeyError(f'{segment!r} is not a key or key[index]')
        steps.append(m.group(1))
        steps += re.findall(r'\[([^\]]+)\]', m.group(2))
    for k, step in enumerate(steps):
        last = k == len(steps) - 1
        if isinstance(node, list):
            if re.fullmatch(r'\d+', step):
                index = int(step)
            else:
                names = [b.get('name') if isinstance(b, Mapping) else None for b in node]
                if step not in names:
                    listed = ', '.join(map(str, names))
                    raise KeyError(f'no body named {step!r} (bodies: {listed})')
                index = names.index(step)
            if index >= len(node):
                raise KeyError(f'index {index} is past the end of a list of {len(node)}')
            if last:
                node[index] = value
            else:
                node = node[index]
        elif isinstance(node, dict):
            if last:
                node[step] = value
            elif step not in node or node[step] is None:
                raise KeyError(f'the scene has no {step!r} here')
            else:
                node = node[step]
        else:
            raise KeyError(f'{step!r} is below a value, not a mapping or list')


def scene_for(spec: StudySpec, base: dict, design: Mapping[str, float]) -> tuple[dict, dict]:
    """The scene data of a design and its scene-parameter values (StudyError for a key path
    the scene does not have)."""
    data = copy.deepcopy(base)
    declared = set(base.get('parameters') or {}) if isinstance(base, Mapping) else set()
    values = {}
    for name, value in design.items():
        if name in declared:
            values[name] = value
            continue
        try:
            if '.' not in name and '[' not in name:
                raise KeyError(f'the scene declares no parameter {name!r}')
            set_path(data, name, value)
        except KeyError as err:
            raise StudyError(f'{err.args[0]}; a parameter is one the scene declares '
                             f'({", ".join(sorted(declared)) or "none"}) or a key path such as '
                             'bodies[track].vibration.amplitude', f'parameters.{name}',
                             spec.source) from None
    return data, values


def _resolve_scene(scene: str, study_path: Path | None) -> str:
    if study_path is not None:
        candidate = (study_path.parent / scene)
        if candidate.is_file():
            return str(candidate)
    return scene


def parse_study(data: Any, source: str = '<study>', study_path: Path | None = None
                ) -> StudySpec:
    """Validate a study given as plain data; every design's scene is checked too."""
    allowed = {'scene', 'duration', 'repeats', 'seed', 'parameters', 'metrics', 'perturb',
               'publish_rate', 'method', 'record', 'objective', 'reference', 'convergence'}
    if not isinstance(data, Mapping):
        raise StudyError(f'expected a mapping with the keys {", ".join(sorted(allowed))}',
                         '', source)
    for key in data:
        if key not in allowed:
            raise StudyError(f'unknown key {key!r}; allowed keys: {", ".join(sorted(allowed))}',
                             str(key), source)
    for key in ('scene', 'duration', 'parameters', 'metrics'):
        if key not in data:
            raise StudyError(f'missing required key {key!r}', key, source)
    if not isinstance(data['scene'], str) or not data['scene'].strip():
        raise StudyError('expected a shipped scene name or a path', 'scene', source)
    scene = _resolve_scene(data['scene'], study_path)
    duration = _number(data['duration'], 'duration', source, positive=True)
    repeats = data.get('repeats', 1)
    if not isinstance(repeats, int) or isinstance(repeats, bool) or not 1 <= repeats <= 10_000:
        raise StudyError(f'expected a whole number from 1 to 10000, got {repeats!r}', 'repeats',
                         source)
    seed = data.get('seed', 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise StudyError(f'expected a whole number >= 0, got {seed!r}', 'seed', source)
    if not isinstance(data['parameters'], Mapping) or not data['parameters']:
        raise StudyError('expected a mapping from parameter (a scene parameter or a key path) '
                         'to its values', 'parameters', source)
    parameters = tuple(_parameter(str(name), value, f'parameters.{name}', source)
                       for name, value in data['parameters'].items())
    sampled = [p for p in parameters if p.sample is not None]
    if len({(p.sample, p.count) for p in sampled}) > 1:
        raise StudyError('sampled parameters are drawn together: give them the same sample '
                         'and count', 'parameters', source)
    metrics = data['metrics']
    if not isinstance(metrics, list) or not metrics:
        raise StudyError('expected a non-empty list of metric names', 'metrics', source)
    for k, m in enumerate(metrics):
        known = isinstance(m, str) and (
            m in METRICS and '<' not in m
            or any(m.startswith(p) and len(m) > len(p) for p in ('fraction:', 'rest:')))
        if not known:
            raise StudyError(f'unknown metric {m!r}; known: {", ".join(METRICS)}',
                             f'metrics[{k}]', source)
    perturb = data.get('perturb') or {}
    if not isinstance(perturb, Mapping) or set(perturb) - {'position_m', 'angle_rad',
                                                          'drive_phase'}:
        raise StudyError('expected {position_m: m, angle_rad: rad, drive_phase: true|false}',
                         'perturb', source)
    for k, v in perturb.items():
        if k == 'drive_phase' and not isinstance(v, bool):
            raise StudyError(f'expected true or false, got {v!r}', 'perturb.drive_phase', source)
        if k != 'drive_phase' and not (_is_number(v) and v >= 0):
            raise StudyError(f'expected a spread >= 0, got {v!r}', f'perturb.{k}', source)
        most = {'position_m': (MAX_PERTURB_POSITION_M, 'm'),
                'angle_rad': (MAX_PERTURB_ANGLE_RAD, 'rad')}.get(k)
        if most is not None and v > most[0]:
            raise StudyError(f'a spread of at most {most[0]:g} {most[1]} (how a part arrives, '
                             f'not where it is), got {v:g}', f'perturb.{k}', source)
    perturb = {k: (float(v) if k == 'drive_phase' else _number(v, f'perturb.{k}', source))
               for k, v in perturb.items()}
    record = data.get('record', 'none')
    if record not in ('none', 'all', 'jammed'):
        raise StudyError(f"expected none, all or jammed, got {record!r}", 'record', source)
    rate = _number(data.get('publish_rate', 100.0), 'publish_rate', source, positive=True)
    if rate > MAX_PUBLISH_RATE_HZ:
        raise StudyError(f'at most {MAX_PUBLISH_RATE_HZ:g} frames per simulated second, got '
                         f'{rate:g}', 'publish_rate', source)
    objective = data.get('objective') or {'metric': metrics[0], 'goal': 'max'}
    if not (isinstance(objective, Mapping) and objective.get('metric') in metrics
            and objective.get('goal', 'max') in ('max', 'min')):
        raise StudyError('expected {metric: one of the metrics, goal: max|min}', 'objective',
                         source)
    reference = data.get('reference')
    if reference not in (None, 'pointmass'):
        raise StudyError(f'expected pointmass (the point-mass conveying theory), got '
                         f'{reference!r}', 'reference', source)
    if reference and 'conveying_speed_mps' not in metrics:
        raise StudyError('the point-mass reference is a conveying speed: add the metric '
                         'conveying_speed_mps', 'reference', source)
    convergence = data.get('convergence', False)
    if not isinstance(convergence, bool):
        raise StudyError(f'expected true or false, got {convergence!r}', 'convergence', source)
    if data.get('method') is not None and data['method'] not in METHODS:
        raise StudyError(f'expected one of {", ".join(METHODS)}', 'method', source)
    spec = StudySpec(scene=scene, duration_s=duration, repeats=repeats, seed=seed,
                     parameters=parameters, metrics=tuple(metrics), perturb=perturb,
                     publish_rate_hz=rate, method=data.get('method'), record=record,
                     reference=reference, convergence=convergence,
                     objective=objective['metric'], goal=objective.get('goal', 'max'),
                     source=source)
    # counted before anything is built: a grid of 100 000 x 100 000 is refused at once
    n = spec.design_count() * repeats
    if n > MAX_TRIALS:
        sizes = ' x '.join(str(p.count if p.sample else len(p.values)) for p in parameters
                           if p.sample is None) or '1'
        if sampled:
            sizes += f' x {sampled[0].count} sampled'
        raise StudyError(f'{sizes} designs x {repeats} repeats = {n} trials; a study may have '
                         f'at most {MAX_TRIALS}: use fewer values or a sample', 'parameters',
                         source)
    try:
        data_, scene_source = read_scene_data(scene)
    except SceneError as err:
        raise StudyError(str(err), 'scene', source) from None
    spec = replace(spec, scene_data=data_, scene_source=scene_source)
    check_designs(spec)
    check_perturb(spec)
    check_metrics(spec)
    return spec


def check_metrics(spec: StudySpec) -> None:
    """An orientation a metric names (``fraction:`` / ``rest:``) must be one the scene's
    outcomes name: otherwise every trial would fail."""
    base, source = base_scene(spec)
    data, values = scene_for(spec, base, spec.first_design())
    scene = parse_scene(data, source, values)
    names = sorted(name for name, _ in scene.outcomes.orientations)
    for k, metric in enumerate(spec.metrics):
        orientation = metric.partition(':')[2]
        if orientation and orientation not in names:
            raise StudyError(f'the scene names no orientation {orientation!r}; its '
                             f'outcomes.orientations: {", ".join(names) or "none"}',
                             f'metrics[{k}]', spec.source)


def base_scene(spec: StudySpec) -> tuple[dict, str]:
    """The study's scene as plain data (read by parse_study), and where it came from."""
    return spec.scene_data, spec.scene_source


def check_designs(spec: StudySpec) -> None:
    """Each value of each parameter must give a valid scene (the others at the first
    design's values) that runs ``duration`` within the step limit; a sampled parameter, a
    range and a long list are checked at their two ends (a scene checks its numbers against
    intervals, so the ends stand for the values between; checking each of 100 000 draws
    would build 100 000 scenes); errors name the study parameter and the value."""
    base, source = base_scene(spec)
    first = spec.first_design()
    checks = [(p.name, v) for p in spec.parameters for v in p.checked_values()]
    for name, value in dict.fromkeys(checks):
        data, values = scene_for(spec, base, {**first, name: value})
        try:
            scene = parse_scene(data, source, values)
        except SceneError as err:
            raise StudyError(f'{value:g} gives an invalid scene: {err.path or ""} '
                             f'{err.message}'.replace('  ', ' '), f'parameters.{name}',
                             spec.source) from None
        # what Simulator.check_duration would refuse in every trial, refused once here
        h = scene.solver.time_step
        if spec.duration_s / h > MAX_STEPS_PER_RUN:
            raise StudyError(f'{spec.duration_s:g} s is more than {MAX_STEPS_PER_RUN:.0e} steps '
                             f'of {h:g} s (with {name} = {value:g}); give at most '
                             f'{MAX_STEPS_PER_RUN * h:g} s', 'duration', spec.source)


def check_perturb(spec: StudySpec) -> None:
    """Each part moved to each corner of its perturbation (the others where the scene puts
    them), and each drive at either end of its swing when the phase is drawn, must start
    outside the other bodies as the scene file's own start must: a part shifted into the
    track would fail or pass through it in the trials that draw that shift. Like parameters,
    each is checked at its extremes with the rest as the scene has it (the joint extreme of
    the hook orienter's shipped study, a cup 0.2 mm low on a track swung 0.14 mm up, starts
    0.5 mm deep, and its trials run)."""
    dx, da = spec.perturb.get('position_m', 0.0), spec.perturb.get('angle_rad', 0.0)
    if not (dx or da or spec.perturb.get('drive_phase')):
        return
    bodies = list(scene_of_design(spec, spec.first_design()).bodies)
    cases = []                                     # (field, what, bodies)
    for k, body in enumerate(bodies):
        if body.type != 'dynamic' or not (dx or da):
            continue
        for shift in dict.fromkeys((sx * dx, sy * dx, sa * da) for sx in (-1, 1)
                                   for sy in (-1, 1) for sa in (-1, 1)):
            # the other parts held as if static: only the moved part's contacts are new
            moved = [b if b.type != 'dynamic' else replace(b, type='static') for b in bodies]
            moved[k] = replace(body, pose=body.pose + np.array(shift))
            cases.append(('position_m' if dx else 'angle_rad',
                          f'x {shift[0]:+g} m, y {shift[1]:+g} m, angle {shift[2]:+g} rad',
                          moved))
    if spec.perturb.get('drive_phase'):
        for phase in (math.pi / 2, 3 * math.pi / 2):
            cases.append(('drive_phase', f'drive phase {phase:.3g} rad',
                          [b if b.vibration is None else
                           replace(b, vibration=replace(b.vibration, phase=phase))
                           for b in bodies]))
    for field_, what, moved in cases:
        try:
            _check_start_overlap(moved, 'bodies')
        except _Invalid as err:
            raise StudyError(f'at its extreme ({what}) {err.message.split("; move")[0]}: make '
                             'the spread smaller or start the part further from the other '
                             'bodies', f'perturb.{field_}', spec.source) from None


def scene_of_design(spec: StudySpec, design: Mapping[str, float]) -> Scene:
    base, source = base_scene(spec)
    data, values = scene_for(spec, base, design)
    return parse_scene(data, source, values)


def load_study(path: str | Path) -> StudySpec:
    path = Path(path)
    try:
        # read as scene files are: YAML 1.2 numbers, no duplicate keys, bounded size and depth
        data = read_yaml(path)
    except SceneError as err:
        raise StudyError(err.message.replace('scene file', 'study file'), '',
                         str(path)) from None
    return parse_study(data, str(path), path)
