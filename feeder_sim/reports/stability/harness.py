"""The stability harness: cases and criteria, running one cell (a case on a method) in chunks
with a wall-clock bound, in a forked child that is killed when it overruns, and judging it."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
import math
import multiprocessing as mp
import time
import traceback
from typing import Any

import numpy as np

from feeder_sim.model.scene import parse_scene
from feeder_sim.simulator import Simulator


@dataclass(frozen=True)
class Criterion:
    """``measured <op> bound`` with op '<=' or '>='; ``bound`` may differ per method."""

    metric: str
    bound: float | Mapping[str, float]
    op: str = '<='
    meaning: str = ''

    def bound_for(self, method: str) -> float:
        if isinstance(self.bound, Mapping):
            return float(self.bound[method])
        return float(self.bound)

    def holds(self, value: float | None, method: str) -> bool:
        if value is None or not math.isfinite(value):
            return False
        bound = self.bound_for(method)
        return value <= bound if self.op == '<=' else value >= bound


@dataclass(frozen=True)
class SceneRun:
    """One scene dict to run for ``duration_s`` simulated seconds, in chunks of ``chunk_s``."""

    scene: dict
    duration_s: float
    chunk_s: float
    label: str = ''


@dataclass(frozen=True)
class StabilityCase:
    """A stiff or extreme scene and what it must satisfy.

    ``build(method, params)`` returns the scene runs (usually one; the scaled cases also run the
    reference size); ``measure(records, params)`` turns the sampled runs into case-specific
    numbers that ``criteria`` bound. ``duration_s`` is the simulated time of the main scene per
    method (documentation and builders use it), ``wall_limit_s`` the wall-clock bound of a cell.
    ``why`` says, per method, why the method fails the case by design; ``notes`` documents a
    method's answer where it differs by model (Newton's cradle).
    """

    key: str
    description: str
    build: Callable[[str, Mapping[str, Any]], list[SceneRun]]
    measure: Callable[[list[_Record], Mapping[str, Any]], dict[str, float]]
    criteria: tuple[Criterion, ...]
    duration_s: Mapping[str, float]
    wall_limit_s: float = 60.0
    penetration_m: float | Mapping[str, float] = 1e-4
    residual: float | Mapping[str, float] = 1e-6
    energy_tol: float | Mapping[str, float] | None = 1e-6
    why: Mapping[str, str] = field(default_factory=dict)
    notes: Mapping[str, str] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)

    def all_criteria(self) -> tuple[Criterion, ...]:
        common = [Criterion('non_finite', 0.0, meaning='NaN/inf values in the sampled state'),
                  Criterion('wall_s', self.wall_limit_s, meaning='wall-clock bound, s'),
                  Criterion('max_penetration_m', self.penetration_m,
                            meaning='deepest contact penetration, m'),
                  Criterion('max_residual', self.residual,
                            meaning='largest lcp.residual of any contact LCP solved'),
                  Criterion('inexact_answers', 0.0,
                            meaning='contact LCPs whose fallback answer changed the physics '
                                    '(friction lost, no force after the Painlevé impulse)')]
        if self.energy_tol is not None:
            common.append(Criterion('energy_gain', self.energy_tol,
                                    meaning='largest rise of mechanical energy, of E_ref: '
                                            'after any step or event, from its lowest level '
                                            'since the start or the last drive work'))
        return tuple(common) + self.criteria


# --------------------------------------------------------------------------------------------
# Running one scene: chunks, samples, the wall-clock bound


@dataclass
class _Record:
    """What one scene run leaves for measuring: samples at every chunk end (index 0 = start)."""

    label: str
    sim: Simulator
    t: list[float] = field(default_factory=list)
    energy: list[float] = field(default_factory=list)
    position: list[np.ndarray] = field(default_factory=list)   # (n, 2) centres of mass, m
    angle: list[np.ndarray] = field(default_factory=list)      # (n,) rad
    velocity: list[np.ndarray] = field(default_factory=list)   # (n, 2) m/s
    omega: list[np.ndarray] = field(default_factory=list)      # (n,) rad/s
    non_finite: int = 0
    finished: bool = False

    def sample(self) -> None:
        s = self.sim.state
        idx = self.sim.part_indices
        self.t.append(s.t)
        self.energy.append(self.sim.mechanical_energy())
        self.position.append(s.position[idx].copy())
        self.angle.append(s.angle[idx].copy())
        self.velocity.append(s.velocity[idx].copy())
        self.omega.append(s.omega[idx].copy())
        self.non_finite += int(sum(np.count_nonzero(~np.isfinite(a)) for a in (
            s.position, s.angle, s.velocity, s.omega)))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.array(getattr(self, k)) for k in ('t', 'energy', 'position', 'angle',
                                                      'velocity', 'omega')}

    def index(self, name: str) -> int:
        """Column of the part called ``name`` in the sampled arrays."""
        names, _, _ = self.sim.part_poses()
        return names.index(name)

    def energy_scale(self) -> float:
        """E_ref, J (:meth:`Simulator.energy_scale_j`)."""
        return self.sim.energy_scale_j()


def _apply_overrides(scene: dict, overrides: Mapping[str, Any] | None) -> dict:
    if not overrides:
        return scene
    return {**scene, 'solver': {**scene.get('solver', {}), **overrides}}


def _run_scene(run: SceneRun, overrides: Mapping[str, Any] | None, deadline: float,
               progress: Callable[[str], None] | None) -> _Record:
    """Advance one scene in chunks, sampling after each; stop at the deadline (perf_counter)."""
    # the energy invariant is checked after every step or event; a rise is measured, not raised
    sim = Simulator(parse_scene(_apply_overrides(run.scene, overrides),
                                source=f'<{run.scene.get("name", "scene")}>'),
                    check_energy=math.inf)
    sim.energy_check.raise_error = False
    rec = _Record(run.label, sim)
    rec.sample()
    n = max(1, int(round(run.duration_s / run.chunk_s)))
    next_note = time.perf_counter() + 10.0
    for k in range(1, n + 1):
        sim.advance_to(run.duration_s * k / n)
        rec.sample()
        if rec.non_finite:
            break
        now = time.perf_counter()
        if now > deadline:
            return rec
        if progress is not None and now > next_note:
            progress(f'    {run.label or run.scene.get("name")}: t = {sim.t:.4g} s of '
                     f'{run.duration_s:.4g} s')
            next_note = now + 10.0
    rec.finished = not rec.non_finite
    return rec


def _merge_stats(records: list[_Record]) -> dict[str, Any]:
    counts = ('fallbacks', 'unconverged', 'cascades', 'energy_fixes', 'lcp_solves', 'impacts',
              'events', 'steps', 'tangential_impacts', 'frictionless_answers',
              'unresolved_force_lcps')
    out = {**dict.fromkeys(counts, 0), 'max_residual': 0.0, 'max_penetration_m': 0.0,
           'messages': []}
    for r in records:
        st = r.sim.stats
        for k in counts:
            out[k] += int(getattr(st, k))
        out['max_residual'] = max(out['max_residual'], float(st.max_residual))
        out['max_penetration_m'] = max(out['max_penetration_m'], float(st.max_penetration_m))
        out['messages'] += [str(m) for m in st.messages[:5]]
    out['messages'] = out['messages'][:10]
    return out


def _energy_gain(records: list[_Record]) -> float:
    """The largest rise of mechanical energy, of E_ref: over the chunk samples from the start,
    and from step to step or event to event (the energy check's, where drive work resets it)."""
    gains = []
    for r in records:
        e = np.array(r.energy)
        gains.append(float((np.max(e) - e[0]) / r.energy_scale()))
        gains.append(r.sim.energy_check.largest_rise)
    return max(gains)


def run_case(case: StabilityCase, method: str, *, params: Mapping[str, Any] | None = None,
             solver_overrides: Mapping[str, Any] | None = None,
             progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run one cell in this process and judge it; returns the cell dict of the report."""
    p = {**case.params, **(params or {})}
    t0 = time.perf_counter()
    deadline = t0 + case.wall_limit_s
    cell: dict[str, Any] = {'case': case.key, 'method': method, 'exception': None}
    records: list[_Record] = []
    measured: dict[str, float | None] = {}
    try:
        for run in case.build(method, p):
            records.append(_run_scene(run, solver_overrides, deadline, progress))
            if not records[-1].finished:
                break
        complete = all(r.finished for r in records)
        measured['non_finite'] = float(sum(r.non_finite for r in records))
        if complete:
            measured.update(case.measure(records, p))
            if case.energy_tol is not None:
                measured['energy_gain'] = _energy_gain(records)
    except Exception as exc:   # a crash is a failed cell, reported with its text
        cell['exception'] = f'{type(exc).__name__}: {exc}'
        cell['traceback'] = traceback.format_exc(limit=8)
    wall = time.perf_counter() - t0
    measured['wall_s'] = wall
    stats = _merge_stats(records) if records else {}
    measured['max_penetration_m'] = stats.get('max_penetration_m')
    measured['max_residual'] = stats.get('max_residual')
    if stats:
        measured['inexact_answers'] = float(stats['frictionless_answers']
                                            + stats['unresolved_force_lcps'])
    cell.update(_judge(case, method, measured, cell['exception']))
    cell['wall_s'] = wall
    cell['stats'] = stats
    for k in ('fallbacks', 'unconverged', 'cascades', 'energy_fixes', 'max_residual',
              'max_penetration_m'):
        cell[k] = stats.get(k)
    cell['energy_ratio'] = _energy_ratio(records)
    cell['simulated_s'] = [r.sim.t for r in records]
    if not cell['exception'] and records and not all(r.finished for r in records):
        cell['failures'].insert(0, 'wall-clock bound exceeded' if not any(
            r.non_finite for r in records) else 'non-finite state')
        cell['passed'] = False
    return cell


def _energy_ratio(records: list[_Record]) -> float | None:
    if not records or not records[0].energy:
        return None
    e = records[0].energy
    return float(e[-1] / e[0]) if e[0] else None


def _judge(case: StabilityCase, method: str, measured: Mapping[str, float | None],
           exception: str | None) -> dict[str, Any]:
    criteria = {}
    failures = []
    for c in case.all_criteria():
        value = measured.get(c.metric)
        ok = c.holds(value, method)
        criteria[c.metric] = {'value': value, 'bound': c.bound_for(method), 'op': c.op,
                              'passed': ok, 'meaning': c.meaning}
        if not ok:
            shown = 'not measured' if value is None else f'{value:.3g}'
            failures.append(f'{c.metric} = {shown} (bound {c.op} {c.bound_for(method):.3g})')
    if exception:
        failures.insert(0, f'exception: {exception}')
    return {'passed': not failures, 'criteria': criteria, 'failures': failures,
            'measured': dict(measured)}


# --------------------------------------------------------------------------------------------
# The report: every cell in a forked child with a hard wall-clock bound


def _child(conn, case: StabilityCase, method: str, params, overrides) -> None:
    def note(text: str) -> None:
        conn.send(('progress', text))
    try:
        conn.send(('cell', run_case(case, method, params=params, solver_overrides=overrides,
                                    progress=note)))
    except BaseException as exc:   # noqa: BLE001 - the parent must always get an answer
        conn.send(('cell', {'case': case.key, 'method': method, 'passed': False,
                            'exception': f'{type(exc).__name__}: {exc}',
                            'failures': [f'exception: {exc}'], 'criteria': {}}))
    finally:
        conn.close()


def _killed_cell(case: StabilityCase, method: str, wall: float) -> dict[str, Any]:
    measured = {'wall_s': wall}
    cell = {'case': case.key, 'method': method, 'exception': None, 'wall_s': wall,
            'stats': {}, 'energy_ratio': None, 'simulated_s': []}
    cell.update(_judge(case, method, measured, None))
    cell['failures'].insert(0, 'wall-clock bound exceeded (hung inside one chunk; killed)')
    cell['passed'] = False
    for k in ('fallbacks', 'unconverged', 'cascades', 'energy_fixes', 'max_residual',
              'max_penetration_m'):
        cell[k] = None
    return cell


def _run_isolated(case: StabilityCase, method: str, params, overrides,
                  progress: Callable[[str], None] | None) -> dict[str, Any]:
    """Run a cell in a forked child; kill it if it overruns its wall bound by the grace time
    (the child stops itself between chunks, so this only catches a hang inside one chunk)."""
    ctx = mp.get_context('fork')
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, case, method, params, overrides),
                       daemon=True)
    t0 = time.perf_counter()
    proc.start()
    child.close()
    grace = max(10.0, 0.25 * case.wall_limit_s)
    cell = None
    try:
        while cell is None:
            left = case.wall_limit_s + grace - (time.perf_counter() - t0)
            if left <= 0 or not parent.poll(min(left, 1.0)):
                if left <= 0 or not proc.is_alive() and not parent.poll():
                    break
                continue
            try:
                kind, payload = parent.recv()
            except EOFError:
                break
            if kind == 'progress':
                if progress is not None:
                    progress(payload)
            else:
                cell = payload
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
    if cell is None:
        cell = _killed_cell(case, method, time.perf_counter() - t0)
        if proc.exitcode not in (None, 0, -9):
            cell['exception'] = f'child process died (exit code {proc.exitcode})'
    return cell


def _status(cell: Mapping[str, Any], case: StabilityCase) -> str:
    if cell['passed']:
        return 'PASS'
    return 'FAILS BY DESIGN' if cell['method'] in case.why else 'FAIL'


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else str(v)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value
