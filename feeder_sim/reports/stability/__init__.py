"""Stability report: stiff and extreme scenes, each with numeric pass criteria, on every method.

``run_stability(out_dir)`` runs every case of :data:`SCENES` on every stepping method and writes
``out_dir/stability.json`` and ``out_dir/stability.png`` (a table: rows = cases, columns =
methods). A cell passes when every criterion of its case holds; each criterion is a measured
number with a stated bound (SI units; ratios are dimensionless). Criteria every case has:

* ``non_finite``: count of NaN/inf values in the state at the sampled times (bound 0);
* ``wall_s``: wall-clock time of the cell (bound ``wall_limit_s``). Each cell runs in a forked
  child process that advances in small chunks and stops itself once over the bound; the parent
  kills a child that overruns by more than a grace period (a hang inside one chunk), so a hang
  is a failed cell, never a stuck report;
* ``max_penetration_m``: the solver's deepest contact penetration (default bound 1 % of the
  smallest part dimension);
* ``max_residual``: the largest ``lcp.residual`` of any contact LCP the method solved;
* ``energy_gain``: ``(max_t E(t) - E(0)) / E_ref`` with E the mechanical energy and
  ``E_ref = sum(m |g| d + KE_0)`` (d the part's largest dimension), for scenes without a drive;
  the report's ``largest_energy_rise`` gives each method's worst case of it;
* ``inexact_answers``: contact LCPs whose fallback answer changed the physics (the ladder
  ended without friction, or a force LCP had no answer even after the Painlevé impulse),
  bound 0.

Fallbacks, unconverged solves, event cascades and energy fixes are counted and reported in
every cell. A method may *fail by design* on a case (``StabilityCase.why``): the cell is still
run and shown, marked, and the overall ``passed`` ignores it.

Each cell's solver block can be overridden (``solver_overrides``, public scene keys such as
``{'friction_impulse': False}``), which is how a deliberately broken solver is injected.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
import json
import os
from pathlib import Path
import time
from typing import Any

from feeder_sim.reports.stability.cases import METHODS, SCENES
from feeder_sim.reports.stability.harness import (
    _jsonable,
    _run_isolated,
    _status,
    Criterion,
    run_case,
    SceneRun,
    StabilityCase,
)
from feeder_sim.reports.stability.table import write_table_png

__all__ = ['Criterion', 'SceneRun', 'StabilityCase', 'SCENES', 'METHODS', 'run_case',
           'run_stability', 'write_table_png']


def run_stability(out_dir: str | os.PathLike,
                  methods: Sequence[str] = METHODS,
                  cases: Sequence[str] | None = None,
                  solver_overrides: dict | None = None,
                  progress: Callable[[str], None] | None = print,
                  params: Mapping[str, Mapping[str, Any]] | None = None,
                  isolate: bool = True) -> dict:
    """Run the cases (default all of :data:`SCENES`) on ``methods``; write
    ``out_dir/stability.json`` and ``out_dir/stability.png``; return the report dict.

    ``solver_overrides`` is merged into every scene's ``solver:`` block; ``params`` maps a case
    key to parameter overrides (e.g. ``{'pile_500': {'n_parts': 60}}``); ``isolate`` runs each
    cell in a forked child so that a hang inside one chunk is killed at the wall bound.
    The report's ``passed`` is True when every cell passes, ignoring cells of methods that fail
    a case by design (``StabilityCase.why``).
    """
    keys = list(SCENES) if cases is None else list(cases)
    unknown = [k for k in keys if k not in SCENES]
    if unknown:
        raise ValueError(f'unknown stability case(s) {", ".join(unknown)}; choose from '
                         f'{", ".join(SCENES)}')
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ValueError(f'unknown method(s) {", ".join(bad)}; choose from '
                         f'{", ".join(METHODS)}')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda _text: None)
    cells = []
    t_start = time.perf_counter()
    for key in keys:
        case = SCENES[key]
        for method in methods:
            say(f'stability: {key} on {method} (wall bound {case.wall_limit_s:g} s) ...')
            case_params = (params or {}).get(key)
            if isolate:
                cell = _run_isolated(case, method, case_params, solver_overrides, progress)
            else:
                cell = run_case(case, method, params=case_params,
                                solver_overrides=solver_overrides, progress=progress)
            cell['status'] = _status(cell, case)
            cell['expected_to_fail'] = method in case.why
            cell['why'] = case.why.get(method, '')
            cell['note'] = case.notes.get(method, '')
            cells.append(cell)
            detail = '' if cell['passed'] else ': ' + '; '.join(cell['failures'][:3])
            say(f'  {cell["status"]} in {cell["wall_s"]:.1f} s{detail}')
    report = {
        'passed': all(c['passed'] or c['expected_to_fail'] for c in cells),
        'methods': list(methods),
        'cases': {k: {'description': SCENES[k].description,
                      'duration_s': dict(SCENES[k].duration_s),
                      'wall_limit_s': SCENES[k].wall_limit_s,
                      'why': dict(SCENES[k].why), 'notes': dict(SCENES[k].notes),
                      'criteria': [{'metric': c.metric, 'op': c.op, 'meaning': c.meaning,
                                    'bound': {m: c.bound_for(m) for m in methods}}
                                   for c in SCENES[k].all_criteria()]}
                  for k in keys},
        'solver_overrides': dict(solver_overrides or {}),
        'cells': cells,
        'largest_energy_rise': _largest_energy_rise(cells, methods),
        'wall_s': time.perf_counter() - t_start,
    }
    (out / 'stability.json').write_text(json.dumps(_jsonable(report), indent=1))
    write_table_png(report, out / 'stability.png')
    for method, rise in report['largest_energy_rise'].items():
        say(f'stability: largest energy rise on {method}: {rise["energy_gain"]:.3g} of E_ref '
            f'({rise["case"]})')
    say(f'stability: {"PASSED" if report["passed"] else "FAILED"}; wrote {out / "stability.json"}'
        f' and {out / "stability.png"}')
    return report


def _largest_energy_rise(cells: Sequence[Mapping[str, Any]],
                         methods: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per method, the largest ``energy_gain`` of any case without a drive, and its case: the
    mechanical energy never rises between impacts with e <= 1, so this is the method's worst
    violation of that invariant (round-off for an exact method)."""
    out = {}
    for method in methods:
        gains = [(c['measured']['energy_gain'], c['case']) for c in cells
                 if c['method'] == method
                 and c.get('measured', {}).get('energy_gain') is not None]
        if gains:
            gain, case = max(gains)
            out[method] = {'energy_gain': gain, 'case': case}
    return out
