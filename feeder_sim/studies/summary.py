"""What a study leaves in its folder: every trial in a table, per-design statistics with 95 %
intervals, and plots.

Intervals: a proportion (``jammed``; ``fraction:<orientation>`` and ``rest:<orientation>``,
pooled over the trials' fed parts or parts) gets Wilson's score interval (scipy's binomtest);
any other metric the mean's Student-t interval over its trials (none from a single trial).
The best design is the one with the best mean of the study's objective (ties: the surest
interval). ``overall`` in study.json takes every trial together.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from feeder_sim.model.scene import Scene
from feeder_sim.reports.pointmass import conveyor_of, mean_speed
from feeder_sim.studies.spec import scene_of_design, StudySpec


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
    columns = (['design', *[p.name for p in spec.parameters], 'repeat', 'seed',
                *spec.metrics] + [c for c in COLUMNS_LAST if any(c in r for r in rows)])
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


def write_summary(spec: StudySpec, rows: list[dict], out: Path, wall_s: float,
                  workers: int) -> dict:
    designs = design_statistics(spec, rows)
    best = best_design(spec, designs)
    summary = {
        'study': spec.source, 'scene': spec.scene, 'duration_s': spec.duration_s,
        'repeats': spec.repeats, 'seed': spec.seed, 'metrics': list(spec.metrics),
        'objective': {'metric': spec.objective, 'goal': spec.goal},
        'parameters': [p.name for p in spec.parameters],
        'trials': len(rows), 'failed': sum(r.get('status') != 'ok' for r in rows),
        'wall_s': wall_s, 'workers': workers,
        'best_design': None if best is None else best['design'],
        # every trial of the study together (a drop test's resting distribution)
        'overall': metric_statistics(spec, rows),
        'designs': designs,
    }
    (out / 'study.json').write_text(json.dumps(summary, indent=2, default=float) + '\n')
    return summary


def plot(spec: StudySpec, summary: dict, rows: list[dict], out: Path) -> list[Path]:
    """A PNG per metric: against the parameter with the interval band (one parameter), or a
    map over two (a grid as cells, a sample as dots); the best design marked."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = [p.name for p in spec.parameters]
    designs = summary['designs']
    best = summary['best_design']
    written = []
    for metric in spec.metrics:
        fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
        mean = np.array([d['metrics'][metric]['mean'] for d in designs])
        lo = np.array([d['metrics'][metric]['ci95'][0] for d in designs])
        hi = np.array([d['metrics'][metric]['ci95'][1] for d in designs])
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
            ax.set_xlabel(names[0])
            ax.set_ylabel(metric)
            ax.legend(fontsize=8)
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
            fig.colorbar(mesh, ax=ax, label=f'{metric} (mean)')
            if best is not None:
                d = designs[[e['design'] for e in designs].index(best)]
                ax.plot(d['parameters'][names[0]], d['parameters'][names[1]], '*', ms=18,
                        color='tab:red', label=f'best {spec.objective}')
                ax.legend(fontsize=8)
            ax.set_xlabel(names[0])
            ax.set_ylabel(names[1])
        ax.set_title(f'{Path(spec.source).stem}: {metric}, {spec.repeats} trial(s) per design')
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        path = out / f'{metric.replace(":", "_")}.png'
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    shares = [m for m in spec.metrics if m.startswith(('fraction:', 'rest:'))]
    if len(shares) > 1:
        written.append(_plot_shares(spec, summary, shares, out, plt))
    return written


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
