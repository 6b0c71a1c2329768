"""What a study leaves in its folder: every trial in a table, per-design statistics with 95 %
intervals, and plots.

Intervals: a proportion (``jammed``; ``fraction:<orientation>`` and ``rest:<orientation>``,
pooled over the trials' fed parts or parts) gets Wilson's score interval (scipy's binomtest);
any other metric the mean's Student-t interval over its trials (none from a single trial).
The best design is the one with the best mean of the study's objective (ties: the surest
interval). ``overall`` in study.json takes every trial together.

Numerical error (``convergence: true``): per design and metric, the estimate from the
design's first trial and its companion (:mod:`feeder_sim.output.numerical_error`), in the
column ``<metric>_numerical_error`` of that trial's row and as ``numerical_error`` beside the
interval in study.json. Where it exceeds the interval's half-width the study warns: the step,
not the trials, then limits what the design's numbers can tell apart.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
import re
from typing import Any

import numpy as np
from scipy import stats

from feeder_sim.model.scene import Scene
from feeder_sim.output.numerical_error import Companion, metric_errors
from feeder_sim.reports.pointmass import conveyor_of, mean_speed
from feeder_sim.studies.spec import scene_of_design, StudySpec

log = logging.getLogger('feeder_sim')

ERROR_SUFFIX = '_numerical_error'
ROUND_OFF = 1e-9


def attach_numerical_errors(spec: StudySpec, rows: list[dict],
                            companions: dict[str, dict]) -> dict[str, Any]:
    """Put each metric's numerical error on the row of each design's first trial (from its
    companion, by key); returns what study.json says of the estimate: its method and cost."""
    method, measured, failed = None, 0, 0
    trials_wall = sum(r.get('wall_s', 0.0) for r in rows)
    companions_wall = 0.0
    for row in rows:
        if row.get('repeat') != 0:
            continue
        other = companions.get(row.get('key'))
        if other is None:
            continue
        companions_wall += other.get('wall_s', 0.0)
        if row.get('status') != 'ok' or other.get('status') != 'ok':
            failed += 1
            continue
        comp = Companion.from_rule(other['numerical_error'])
        method = comp.method
        for metric, error in metric_errors(row, other, spec.metrics, comp).items():
            row[metric + ERROR_SUFFIX] = error
        measured += 1
    return {'method': method, 'designs_measured': measured, 'designs_failed': failed,
            'trials_wall_s': trials_wall, 'companions_wall_s': companions_wall,
            # the compute the estimate adds, against the trials' own (cluster start-up aside)
            'cost_ratio': (trials_wall + companions_wall) / trials_wall if trials_wall
            else math.nan}


def wilson(successes: float, n: float) -> tuple[float, float]:
    """Wilson's 95 % score interval of a proportion (scipy's binomtest)."""
    n, k = int(round(n)), int(round(successes))
    if n <= 0:
        return math.nan, math.nan
    ci = stats.binomtest(min(k, n), n).proportion_ci(confidence_level=0.95, method='wilson')
    return float(ci.low), float(ci.high)


def t_interval(values: np.ndarray) -> tuple[float, float]:
    """Student-t 95 % interval of the mean of ``values``."""
    n = len(values)
    if n < 2:
        return math.nan, math.nan
    half = float(stats.t.ppf(0.975, n - 1) * np.std(values, ddof=1) / math.sqrt(n))
    mean = float(np.mean(values))
    return mean - half, mean + half


def _is_proportion(metric: str) -> bool:
    return metric == 'jammed' or metric.startswith(('fraction:', 'rest:'))


def design_statistics(spec: StudySpec, rows: list[dict]) -> list[dict[str, Any]]:
    """Per design: its parameters, trial counts, and for each metric mean, interval, n."""
    out = []
    names = [p.name for p in spec.parameters]
    for index in sorted({r['design'] for r in rows}):
        trials = [r for r in rows if r['design'] == index]
        entry = {'design': index, 'parameters': {n: trials[0][n] for n in names},
                 **metric_statistics(spec, trials)}
        if spec.convergence:
            first = [r for r in trials if r.get('repeat') == 0]
            for metric, stats_ in entry['metrics'].items():
                error = first[0].get(metric + ERROR_SUFFIX) if first else None
                stats_['numerical_error'] = (float(error) if error is not None
                                             and math.isfinite(error) else None)
        if spec.reference == 'pointmass':
            scene = scene_of_design(spec, entry['parameters'])
            entry['reference'] = {'conveying_speed_mps': pointmass_speed(scene)}
        out.append(entry)
    return out


def metric_statistics(spec: StudySpec, trials: list[dict]) -> dict[str, Any]:
    """Trial counts and, for each metric, mean, 95 % interval and n over ``trials``."""
    ok = [r for r in trials if r.get('status') == 'ok']
    entry: dict[str, Any] = {'trials': len(trials), 'failed': len(trials) - len(ok),
                             'metrics': {}}
    for metric in spec.metrics:
        values = np.array([r[metric] for r in ok], float)
        finite = values[np.isfinite(values)]
        if metric.startswith(('fraction:', 'rest:')):
            # shares of a trial's fed parts, or of its parts: pooled over the trials' parts
            count = 'parts_fed_count' if metric.startswith('fraction:') else 'parts_count'
            weight = np.array([r.get(count, 1) for r in ok], float)
            use = np.isfinite(values)
            k, n = float(np.sum(values[use] * weight[use])), float(np.sum(weight[use]))
            mean = k / n if n else math.nan
            lo, hi = wilson(k, n)
            kind = 'wilson'
        elif _is_proportion(metric):
            k, n = float(np.sum(finite)), float(len(finite))
            mean = k / n if n else math.nan
            lo, hi = wilson(k, n)
            kind = 'wilson'
        else:
            mean = float(np.mean(finite)) if len(finite) else math.nan
            lo, hi = t_interval(finite)
            kind = 't'
        entry['metrics'][metric] = {'mean': mean, 'ci95': [lo, hi], 'n': int(len(finite)),
                                    'interval': kind}
    return entry


def pointmass_speed(scene: Scene) -> float:
    """The point-mass theory's mean conveying speed (m/s) on the scene's track
    (reports.pointmass, physics reference section 4.3)."""
    return mean_speed(conveyor_of(scene))


def best_design(spec: StudySpec, designs: list[dict]) -> dict | None:
    """The design with the best mean of the objective; among equal means, the one whose
    interval is surest (the higher lower bound for a maximum, the lower upper bound for a
    minimum): 6 of 6 beats 1 of 1."""
    scored = [d for d in designs if math.isfinite(d['metrics'][spec.objective]['mean'])]
    if not scored:
        return None
    sign = 1.0 if spec.goal == 'max' else -1.0

    def rank(d: dict) -> tuple[float, float]:
        m = d['metrics'][spec.objective]
        bound = m['ci95'][0] if sign > 0 else m['ci95'][1]
        return sign * m['mean'], sign * (bound if math.isfinite(bound) else -sign * math.inf)

    return max(scored, key=rank)


COLUMNS_LAST = ('status', 'error', 'wall_s', 'key', 'log')


def write_table(spec: StudySpec, rows: list[dict], out: Path) -> list[str]:
    """results.csv and results.parquet: a row per trial; returns the columns."""
    errors = [m + ERROR_SUFFIX for m in spec.metrics] if spec.convergence else []
    columns = (['design', *[p.name for p in spec.parameters], 'repeat', 'seed',
                *spec.metrics, *errors]
               + [c for c in COLUMNS_LAST if any(c in r for r in rows)])
    with open(out / 'results.csv', 'w', newline='') as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for r in rows:
            writer.writerow(['' if r.get(c) is None else r.get(c) for c in columns])
    import pyarrow as pa
    import pyarrow.parquet as pq
    table = pa.table({c: [r.get(c) for r in rows] for c in columns})
    pq.write_table(table, out / 'results.parquet')
    return columns


def numerical_error_warnings(spec: StudySpec, designs: list[dict]) -> list[str]:
    """A line per design and metric whose numerical error exceeds the half-width of its 95 %
    interval (logged as a warning too)."""
    lines = []
    for d in designs:
        for metric, m in d['metrics'].items():
            error, (lo, hi) = m.get('numerical_error'), m['ci95']
            if error is None or not (math.isfinite(lo) and math.isfinite(hi)):
                continue
            half = (hi - lo) / 2.0
            # differences at the round-off of the time grid (a feed rate's span) are no signal
            if error > half and error > ROUND_OFF * abs(m['mean']):
                values = ', '.join(f'{k}={v:g}' for k, v in d['parameters'].items())
                lines.append(f"design {d['design']} ({values}): the numerical error of {metric}, "
                             f'{error:.3g}, exceeds the half-width of its 95 % interval, '
                             f'{half:.3g}: refine the step before trusting a ranking by it')
    for line in lines:
        log.warning('study: %s', line)
    return lines


def _first_error(failed: list[dict]) -> str | None:
    if not failed:
        return None
    row = failed[0]
    reason = (str(row.get('error') or '').splitlines() or ['no reason stored'])[0]
    return f"design {row.get('design')} repeat {row.get('repeat')}: {reason}"


def write_summary(spec: StudySpec, rows: list[dict], out: Path, wall_s: float,
                  workers: int, convergence: dict | None = None) -> dict:
    designs = design_statistics(spec, rows)
    best = best_design(spec, designs)
    failed = [r for r in rows if r.get('status') != 'ok']
    extra: dict[str, Any] = {}
    if convergence is not None:
        extra = {'convergence': convergence,
                 'warnings': numerical_error_warnings(spec, designs)}
    summary = {
        'study': spec.source, 'scene': spec.scene, 'duration_s': spec.duration_s,
        'repeats': spec.repeats, 'seed': spec.seed, 'metrics': list(spec.metrics),
        'objective': {'metric': spec.objective, 'goal': spec.goal},
        'parameters': [p.name for p in spec.parameters],
        'trials': len(rows), 'failed': len(failed),
        # the reason of the first failed trial in the study's order (null: none failed)
        'first_error': _first_error(failed),
        'wall_s': wall_s, 'workers': workers,
        'best_design': None if best is None else best['design'],
        # every trial of the study together (a drop test's resting distribution)
        'overall': metric_statistics(spec, rows),
        **extra,
        'designs': designs,
    }
    (out / 'study.json').write_text(json.dumps(summary, indent=2, default=float) + '\n')
    return summary


# the last key of a scene key path -> (what it is, unit)
_KEY_LABELS = {
    'amplitude': ('drive amplitude', 'm'), 'frequency': ('drive frequency', 'Hz'),
    'angle': ('drive angle', 'rad'), 'phase': ('drive phase', 'rad'),
    'offset': ('drive offset', 'm'), 'mu_static': ('static friction coefficient', ''),
    'mu_dynamic': ('dynamic friction coefficient', ''), 'restitution': ('restitution', ''),
    'mass': ('mass', 'kg'), 'density': ('density', 'kg/m²'), 'time_step': ('time step', 's'),
    'tolerance': ('tolerance', ''), 'gravity': ('gravity', 'm/s²'), 'pose': ('pose', 'm'),
    'velocity': ('velocity', 'm/s'), 'interval': ('interval', 's'),
}
# metric name endings -> unit
_METRIC_UNITS = (('_mps', 'm/s'), ('_per_min', '1/min'), ('_m', 'm'), ('_s', 's'))


def parameter_label(spec: StudySpec, parameter) -> str:
    """An axis label for a study parameter: the study's own ``label`` / ``unit`` if it gives
    them, else what a known key path or the scene's declared parameter says, with its unit."""
    name, unit = parameter.name, parameter.unit
    label = parameter.label
    declared = ((spec.scene_data or {}).get('parameters') or {}).get(name) \
        if isinstance(spec.scene_data, dict) else None
    if isinstance(declared, dict) and unit is None:
        unit = declared.get('unit')
    if label is None:
        keys = re.findall(r'[A-Za-z_]\w*', name)
        body = re.search(r'bodies\[([^\]]+)\]', name)
        known = _KEY_LABELS.get(keys[-1]) if '.' in name or '[' in name else None
        if known is not None:
            label = f'{body.group(1)} {known[0]}' if body else known[0]
            unit = known[1] if unit is None else unit
        else:
            label = name.replace('_', ' ')
    return f'{label} ({unit})' if unit else label


def metric_label(metric: str) -> str:
    """An axis label for a metric: its words and the unit its name ends with."""
    kind, _, name = metric.rpartition(':')
    kind = f'{kind}: ' if kind else ''
    for ending, unit in _METRIC_UNITS:
        if name.endswith(ending):
            return f'{kind}{name[:-len(ending)].replace("_", " ")} ({unit})'
    return kind + name.replace('_', ' ')


def _legend_outside(fig) -> None:
    """One legend for the figure's axes, below them, where it covers no data (constrained
    layout keeps room for it)."""
    handles: dict[str, Any] = {}
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, handle)
    if handles:
        fig.legend(list(handles.values()), list(handles), loc='outside lower center', ncol=3,
                   fontsize=8, frameon=False)


def plot(spec: StudySpec, summary: dict, rows: list[dict], out: Path) -> list[Path]:
    """A PNG per metric: against the parameter with the interval band (one parameter), or a
    map over two (a grid as cells, a sample as dots); the best design marked. With
    ``convergence``: the numerical error as error bars beside the interval's (one parameter),
    or a panel below the map with both kinds per design."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = [p.name for p in spec.parameters]
    labels = [parameter_label(spec, p) for p in spec.parameters]
    designs = summary['designs']
    best = summary['best_design']
    written = []
    for metric in spec.metrics:
        mean = np.array([d['metrics'][metric]['mean'] for d in designs])
        lo = np.array([d['metrics'][metric]['ci95'][0] for d in designs])
        hi = np.array([d['metrics'][metric]['ci95'][1] for d in designs])
        numerical = None
        if spec.convergence:
            numerical = np.array([np.nan if d['metrics'][metric].get('numerical_error') is None
                                  else d['metrics'][metric]['numerical_error']
                                  for d in designs])
        if numerical is not None and len(names) > 1:
            fig, (ax, low) = plt.subplots(2, 1, figsize=(7, 7.5), dpi=120,
                                          height_ratios=(3, 2), layout='constrained')
            _error_bars(low, np.arange(len(designs)), mean, lo, hi, numerical)
            low.set_xlabel('design')
            low.set_ylabel(metric_label(metric))
            low.grid(True, alpha=0.3)
        else:
            fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120, layout='constrained')
        if len(names) == 1:
            x = np.array([d['parameters'][names[0]] for d in designs])
            o = np.argsort(x)
            ax.fill_between(x[o], lo[o], hi[o], alpha=0.25, label='95 % interval')
            ax.plot(x[o], mean[o], 'o-', label='mean over trials')
            trial_x = [r[names[0]] for r in rows if r.get('status') == 'ok']
            trial_y = [r[metric] for r in rows if r.get('status') == 'ok']
            ax.plot(trial_x, trial_y, '.', color='0.5', ms=3, label='trials')
            if best is not None:
                d = designs[[e['design'] for e in designs].index(best)]
                ax.plot(d['parameters'][names[0]], d['metrics'][metric]['mean'], '*', ms=16,
                        color='tab:red', label='best design')
            theory = _reference(designs, metric)
            if theory is not None:
                ax.plot(x[o], theory[o], 'k--', lw=1, label='point-mass theory')
            if numerical is not None:
                _error_bars(ax, x, mean, None, None, numerical)
            ax.set_xlabel(labels[0])
            ax.set_ylabel(metric_label(metric))
        else:
            x = np.array([d['parameters'][names[0]] for d in designs])
            y = np.array([d['parameters'][names[1]] for d in designs])
            ux, uy = np.unique(x), np.unique(y)
            if len(designs) == len(ux) * len(uy) and len(ux) > 1 and len(uy) > 1:
                rows_, cols_ = np.searchsorted(uy, y), np.searchsorted(ux, x)
                grid = np.full((len(uy), len(ux)), np.nan)
                grid[rows_, cols_] = mean
                mesh = ax.pcolormesh(ux, uy, grid, shading='nearest', cmap='viridis')
                theory = _reference(designs, metric)
                if theory is not None:
                    levels = np.full_like(grid, np.nan)
                    levels[rows_, cols_] = theory
                    lines = ax.contour(ux, uy, levels, colors='white', linewidths=0.8)
                    ax.clabel(lines, fontsize=7, fmt='%.3g')
                    ax.plot([], [], color='white', lw=0.8, label='point-mass theory')
            else:
                mesh = ax.scatter(x, y, c=mean, cmap='viridis', s=60)
            fig.colorbar(mesh, ax=ax, label=f'{metric_label(metric)}, mean')
            if best is not None:
                d = designs[[e['design'] for e in designs].index(best)]
                ax.plot(d['parameters'][names[0]], d['parameters'][names[1]], '*', ms=18,
                        color='tab:red', label=f'best {spec.objective}')
            ax.set_xlabel(labels[0])
            ax.set_ylabel(labels[1])
        ax.set_title(f'{Path(spec.source).stem}: {metric}, {spec.repeats} trial(s) per design')
        ax.grid(True, alpha=0.3)
        _legend_outside(fig)
        path = out / f'{metric.replace(":", "_")}.png'
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    shares = [m for m in spec.metrics if m.startswith(('fraction:', 'rest:'))]
    if len(shares) > 1:
        written.append(_plot_shares(spec, summary, shares, out, plt))
    return written


def _error_bars(ax, x: np.ndarray, mean: np.ndarray, lo: np.ndarray | None,
                hi: np.ndarray | None, numerical: np.ndarray) -> None:
    """Error bars of two kinds at each design: the 95 % interval over the trials (thin, with
    caps) and the numerical error (thick, none where it was not measured)."""
    if lo is not None:
        ok = np.isfinite(lo) & np.isfinite(hi)
        ax.errorbar(x[ok], mean[ok], yerr=[mean[ok] - lo[ok], hi[ok] - mean[ok]], fmt='o',
                    ms=3, color='tab:blue', capsize=4, lw=1, label='95 % interval (trials)')
    ok = np.isfinite(numerical) & np.isfinite(mean)
    ax.errorbar(x[ok], mean[ok], yerr=numerical[ok], fmt='none', ecolor='tab:orange', lw=4,
                alpha=0.7, label='± numerical error (step)')


def _reference(designs: list[dict], metric: str) -> np.ndarray | None:
    if not all(metric in d.get('reference', {}) for d in designs):
        return None
    return np.array([d['reference'][metric] for d in designs])


def _plot_shares(spec: StudySpec, summary: dict, shares: list[str], out: Path, plt) -> Path:
    """The orientation outcomes over all trials, with their Wilson intervals."""
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    stats_ = summary['overall']['metrics']
    mean = np.array([stats_[m]['mean'] for m in shares])
    lo = np.array([stats_[m]['ci95'][0] for m in shares])
    hi = np.array([stats_[m]['ci95'][1] for m in shares])
    ax.bar(range(len(shares)), mean, yerr=[mean - lo, hi - mean], capsize=6,
           color='tab:blue', alpha=0.8)
    ax.set_xticks(range(len(shares)), [m.split(':', 1)[1] for m in shares])
    ax.set_ylabel('share (95 % Wilson interval)')
    ax.set_ylim(0, 1)
    ax.set_title(f'{Path(spec.source).stem}: outcomes over {summary["trials"]} trials')
    ax.grid(True, axis='y', alpha=0.3)
    fig.tight_layout()
    path = out / 'outcomes.png'
    fig.savefig(path)
    plt.close(fig)
    return path
