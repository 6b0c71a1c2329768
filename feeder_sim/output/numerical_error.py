"""The numerical error of a run's outcomes, from a second run of the same scene at another
solver setting (a *companion*).

The companion's setting: ``time_stepping`` and ``impulse_based`` at half the step (refined) or
twice the step (coarsened); ``event_driven`` at its tolerance / 100 (refined) or x 100
(coarsened). ``feeder-sim run --error-estimate`` and a study with ``convergence: true`` take
the refined one; the coarsened one (half a run instead of one to two) serves where a refined
step would fall below the smallest allowed.

The error reported is that of the *base* run, the number the summary shows:

* order p known (``time_stepping``: first order), step ratio r = 2: Richardson. Refined
  companion: |base - fine| r^p / (r^p - 1) (= 2 |base - fine| for p = 1); coarsened:
  |base - coarse| / (r^p - 1) (= |base - coarse|). The extrapolated value (error ~ h^p removed)
  is reported beside it.
* order unknown (``impulse_based``, whose steps adapt; ``event_driven``, tolerance-driven):
  the plain difference |base - other|.

Counts (parts exited, jams, orientations) are not smooth in the step: their difference says
whether the setting changed an outcome, and is reported by the same rule.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
import math
from typing import Any

from feeder_sim.model.scene import MIN_TIME_STEP_S, Scene, SolverSpec
from feeder_sim.stepping import STEPPERS

STEP_RATIO = 2.0           # a method whose error setting is its step: half or twice it
TOLERANCE_RATIO = 100.0    # one whose error setting is a tolerance: it / or x 100
MAX_TIME_STEP_S = 0.1      # the bounds of solver.time_step and solver.tolerance
MAX_TOLERANCE = 1e-2

# the summary's per-part numbers and outcome numbers the estimate covers
PART_KEYS = ('mean_velocity_along_track_mps', 'final_position_along_track_m')
OUTCOME_KEYS = ('parts_exited', 'feed_rate_parts_per_min', 'feed_rate_steady_parts_per_min',
                'jams', 'recirculated')
COUNTS = ('parts_exited', 'jams', 'recirculated')    # whole numbers: nothing to extrapolate
PART_OUTCOME_KEYS = ('exit_time_s', 'jam_time_s')


@dataclass(frozen=True)
class Companion:
    """The second run of an estimate: its solver and how a difference becomes an error."""

    solver: SolverSpec | None  # None: a rule read back from a stored row
    refined: bool              # finer than the base run (else coarser)
    ratio: float               # step or tolerance ratio between the two settings (> 1)
    order: int | None          # the method's order in the step, None where unknown
    method: str                # how the error was estimated, in words (study.json, summary)

    def rule(self) -> dict[str, Any]:
        """What turns a difference into an error, as plain data (a study stores it with the
        companion's row; :meth:`from_rule` reads it back)."""
        return {'method': self.method, 'order': self.order, 'ratio': self.ratio,
                'refined': self.refined, **self.setting}

    @classmethod
    def from_rule(cls, rule: Mapping[str, Any]) -> Companion:
        return cls(None, bool(rule['refined']), float(rule['ratio']), rule['order'],
                   str(rule['method']))

    @property
    def setting(self) -> dict[str, float]:
        """The companion's setting, as the summary reports it."""
        if self.solver is None:
            return {}
        if STEPPERS[self.solver.method].error_setting == 'tolerance':
            return {'tolerance': float(self.solver.tolerance)}
        return {'time_step_s': float(self.solver.time_step)}

    def error(self, base: float | None, other: float | None) -> float | None:
        """The estimated absolute error of ``base`` given the companion's ``other`` (None when
        either is missing or not finite)."""
        if not (_finite(base) and _finite(other)):
            return None
        diff = abs(float(other) - float(base))
        if self.order is None:
            return diff
        gain = self.ratio ** self.order
        return diff * gain / (gain - 1.0) if self.refined else diff / (gain - 1.0)

    def extrapolated(self, base: float | None, other: float | None) -> float | None:
        """The Richardson-extrapolated value (None where the order is unknown)."""
        if self.order is None or not (_finite(base) and _finite(other)):
            return None
        fine, coarse = (other, base) if self.refined else (base, other)
        return float(fine) + (float(fine) - float(coarse)) / (self.ratio ** self.order - 1.0)


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def companion(solver: SolverSpec, *, refine: bool = True) -> Companion:
    """The companion setting of ``solver``: refined (``refine``) or coarsened. A coarsened one
    that would leave the allowed range (step <= 0.1 s, tolerance <= 1e-2) is refined instead,
    and a refined step below 1e-7 s coarsened."""
    method = solver.method
    order = STEPPERS[method].order
    if STEPPERS[method].error_setting == 'tolerance':
        tol = solver.tolerance
        fine = refine or tol * TOLERANCE_RATIO > MAX_TOLERANCE
        new = tol / TOLERANCE_RATIO if fine else tol * TOLERANCE_RATIO
        text = (f'{method} at its tolerance {"/" if fine else "x"} '
                f'{TOLERANCE_RATIO:g} ({new:g} against {tol:g}); the plain difference (its '
                'error is not a known power of the tolerance)')
        return Companion(replace(solver, tolerance=new), fine, TOLERANCE_RATIO, order, text)
    h = solver.time_step
    if refine:
        fine = h / STEP_RATIO >= MIN_TIME_STEP_S
    else:
        fine = h * STEP_RATIO > MAX_TIME_STEP_S
    new = h / STEP_RATIO if fine else h * STEP_RATIO
    how = (f'{method} at {"half" if fine else "twice"} the step ({new:g} s against {h:g} s)')
    if order is None:
        text = f'{how}; the plain difference (the order of its adaptive steps is not known)'
    elif fine:
        text = (f'{how}, Richardson p={order}: error of the base run = '
                f'{STEP_RATIO ** order / (STEP_RATIO ** order - 1):g} |fine - base|')
    else:
        text = (f'{how}, Richardson p={order}: error of the base run = '
                f'{1 / (STEP_RATIO ** order - 1):g} |base - coarse|')
    return Companion(replace(solver, time_step=new), fine, STEP_RATIO, order, text)


def companion_scene(scene: Scene, comp: Companion) -> Scene:
    return replace(scene, solver=comp.solver)


def _by_name(items: list[dict]) -> dict[str, dict]:
    return {item['name']: item for item in items}


class _Errors:
    """Collects errors (and extrapolations) key by key; notes what one run has and the other
    has not (a part that exited or jammed in one run only)."""

    def __init__(self, comp: Companion) -> None:
        self.comp = comp
        self.unresolved: list[str] = []

    def pair(self, where: str, base: Any, other: Any, out: dict, extra: dict | None,
             key: str) -> None:
        if base is None and other is None:
            return
        if base is None or other is None:
            self.unresolved.append(f'{where}: {base!r} in the base run, {other!r} in the '
                                   'companion')
            out[key] = None
            return
        out[key] = self.comp.error(base, other)
        if extra is not None:
            value = self.comp.extrapolated(base, other)
            if value is not None:
                extra[key] = value


def summary_errors(base: Mapping[str, Any], other: Mapping[str, Any],
                   comp: Companion) -> dict[str, Any]:
    """The ``numerical_error`` object of a run summary: for each outcome the base summary
    holds, under the same key, its estimated absolute error; ``extrapolated`` holds the
    Richardson values where the order is known."""
    e = _Errors(comp)
    known = comp.order is not None
    parts, parts_x = [], []
    others = _by_name(other.get('parts', []))
    for p in base.get('parts', []):
        q = others.get(p['name'])
        row, row_x = {'name': p['name']}, {'name': p['name']}
        for key in PART_KEYS:
            e.pair(f"parts[{p['name']}].{key}", p.get(key),
                   None if q is None else q.get(key), row, row_x, key)
        parts.append(row)
        parts_x.append(row_x)
    out: dict[str, Any] = {'method': comp.method, 'order': comp.order,
                           'companion': {'refined': comp.refined, **comp.setting},
                           'parts': parts}
    extra: dict[str, Any] = {'parts': parts_x}
    if 'outcomes' in base:
        ob, oo = base['outcomes'], other.get('outcomes', {})
        outcomes: dict[str, Any] = {}
        outcomes_x: dict[str, Any] = {}
        for key in OUTCOME_KEYS:
            if key in ob:
                e.pair(f'outcomes.{key}', ob[key], oo.get(key), outcomes,
                       None if key in COUNTS else outcomes_x, key)
        counts_b, counts_o = ob.get('exit_orientations') or {}, oo.get('exit_orientations') or {}
        if counts_b:
            outcomes['exit_orientations'] = {n: comp.error(c, counts_o.get(n, 0))
                                             for n, c in counts_b.items()}
            shares = {}
            for n, c in counts_b.items():
                e.pair(f'outcomes.exit_orientation_shares.{n}', _share(c, ob['parts_exited']),
                       _share(counts_o.get(n, 0), oo.get('parts_exited', 0)), shares, None, n)
            outcomes['exit_orientation_shares'] = shares
        rows = []
        others_o = _by_name(oo.get('parts', []))
        for p in ob.get('parts', []):
            q = others_o.get(p['name'], {})
            row = {'name': p['name']}
            for key in PART_OUTCOME_KEYS:
                e.pair(f"outcomes.parts[{p['name']}].{key}", p.get(key), q.get(key), row, None,
                       key)
            rows.append(row)
        outcomes['parts'] = rows
        out['outcomes'] = outcomes
        extra['outcomes'] = outcomes_x
    if 'sensors' in base:
        sensors: dict[str, Any] = {}
        for name, count in base['sensors'].items():
            e.pair(f'sensors.{name}', count, other.get('sensors', {}).get(name), sensors, None,
                   name)
        out['sensors'] = sensors
    if known:
        out['extrapolated'] = extra
    out['unresolved'] = e.unresolved
    return out


def _share(count: float, total: float) -> float | None:
    return count / total if total else None


def metric_errors(base: Mapping[str, Any], other: Mapping[str, Any],
                  metrics: tuple[str, ...], comp: Companion) -> dict[str, float]:
    """A study's metrics' errors from a trial's row and its companion's (NaN where either
    value is missing: a share of no fed parts)."""
    out = {}
    for m in metrics:
        err = comp.error(base.get(m), other.get(m))
        out[m] = math.nan if err is None else err
    return out
