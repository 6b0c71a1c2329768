"""Work-precision benchmark: mean conveying speed of one box on a vibrating track.

Case: one box (20 x 10 mm, 10 g) on a 50 Hz, 1 mm (0-peak), psi = 20 deg, theta = 0 track,
mu = 0.5. The reference is the point-mass solver (feeder_sim.reports.pointmass) over the same cycle
window; a flat box that does not rotate moves like the point mass.

Sweeps event_driven over the event/integration tolerance and time_stepping over the step
(period / N). For each setting: relative error of the mean speed, wall time per simulated
second (median of the repeats, advance_to() only) and solver counters.

Run from the repository root:  .venv/bin/python benchmarks/conveying.py [--quick]
Writes benchmarks/results/conveying.{json,png} (conveying_quick.* with --quick).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
from pathlib import Path
import platform
import statistics
import sys
import time

import numpy as np

from feeder_sim.model.builders import build, conveyor
from feeder_sim.reports.pointmass import Conveyor, mean_speed
from feeder_sim.simulator import Simulator

FREQUENCY_HZ = 50.0
AMPLITUDE_M = 1e-3
PSI = math.radians(20.0)
THETA = 0.0
MU = 0.5
PART_SIZE = (0.02, 0.01)
MASS = 0.01
G = 9.81
PERIOD = 1.0 / FREQUENCY_HZ
TARGET_REL_ERROR = 1e-4
TARGET_WALL_PER_SIM_S = 0.050

FULL = {'warmup': 20, 'measured': 10, 'repeats': 3,
        'tolerances': (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10),
        'steps_per_cycle': (25, 50, 100, 200, 400, 800)}
QUICK = {'warmup': 6, 'measured': 4, 'repeats': 1,
         'tolerances': (1e-5, 1e-8),
         'steps_per_cycle': (25, 100)}


ROOT = Path(__file__).resolve().parents[1]


def gamma() -> float:
    omega = 2.0 * math.pi * FREQUENCY_HZ
    return AMPLITUDE_M * omega ** 2 * math.sin(PSI) / (G * math.cos(THETA))


def run_once(method: str, setting: float, warmup: int, measured: int) -> dict:
    kw = {'tolerance': setting} if method == 'event_driven' else {'time_step': PERIOD / setting}
    scene = conveyor(psi=PSI, mu=MU, theta=THETA, gamma=gamma(), frequency_hz=FREQUENCY_HZ,
                     method=method, part_size=PART_SIZE, mass=MASS, **kw)
    sim = Simulator(build(scene))
    wall = 0.0
    max_angle = 0.0
    s_start = None
    for k in range(1, warmup + measured + 1):
        t0 = time.perf_counter()
        sim.advance_to(k * PERIOD)
        wall += time.perf_counter() - t0
        _, _, angle = sim.part_poses()
        max_angle = max(max_angle, float(np.max(np.abs(angle))))
        if k == warmup:
            s_start = float(sim.track_coordinates()[0][0])
    s_end = float(sim.track_coordinates()[0][0])
    st = sim.stats
    return {'speed': (s_end - s_start) / (measured * PERIOD),
            'wall_per_sim_s': wall / ((warmup + measured) * PERIOD),
            'max_abs_angle_rad': max_angle,
            'stats': {'lcp_solves': st.lcp_solves, 'events': st.events, 'steps': st.steps,
                      'fallbacks': st.fallbacks, 'impacts': st.impacts,
                      'unconverged': st.unconverged}}


def label(method: str, setting: float) -> str:
    return f'tol={setting:.0e}' if method == 'event_driven' else f'N={setting:g}'


def source_info() -> dict:
    """Which simulator code was measured: git HEAD, dirty flag and a hash of the package."""
    import hashlib
    import subprocess

    import feeder_sim

    root = Path(feeder_sim.__file__).resolve().parent
    digest = hashlib.sha256()
    for f in sorted(root.glob('*.py')):
        digest.update(f.name.encode() + b'\0' + f.read_bytes())

    def git(*cmd: str) -> str | None:
        try:
            return subprocess.run(['git', *cmd], cwd=root, capture_output=True, text=True,
                                  check=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None

    status = git('status', '--porcelain', '--', '.')
    return {'git_head': git('rev-parse', 'HEAD'), 'package_dirty': bool(status),
            'package_sha256': digest.hexdigest()}


def machine_info() -> dict:
    return {'cpu_count': os.cpu_count(), 'python': platform.python_version(),
            'numpy': np.__version__, 'platform': platform.platform(),
            'processor': platform.processor() or platform.machine(),
            'date': datetime.datetime.now().astimezone().isoformat(timespec='seconds')}


def plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    for method, marker in (('event_driven', 'o'), ('time_stepping', 's')):
        sel = [r for r in rows if r['method'] == method]
        if not sel:
            continue
        x = [r['wall_per_sim_s'] for r in sel]
        y = [max(r['rel_error'], 1e-16) for r in sel]
        ax.loglog(x, y, marker=marker, label=method)
        for i, (r, xi, yi) in enumerate(zip(sel, x, y)):
            # staggered so that settings with equal error stay readable
            ax.annotate(r['label'], (xi, yi), textcoords='offset points',
                        xytext=(5, 4 + 10 * (i % 6) if method == 'event_driven' else 4),
                        fontsize=7, arrowprops={'arrowstyle': '-', 'lw': 0.4, 'alpha': 0.5})
    ax.axhline(TARGET_REL_ERROR, color='grey', ls='--', lw=0.8)
    ax.axvline(TARGET_WALL_PER_SIM_S, color='grey', ls='--', lw=0.8)
    ax.annotate('target', (TARGET_WALL_PER_SIM_S, TARGET_REL_ERROR), textcoords='offset points',
                xytext=(4, -12), fontsize=8, color='grey')
    ax.set_xlabel('wall time per simulated second (s)')
    ax.set_ylabel('relative error of the mean conveying speed')
    ax.set_title(title, fontsize=8)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='fewer settings, cycles, repeats')
    parser.add_argument('--out', default=str(ROOT / 'out' / 'bench'),
                        help='output folder (default out/bench; benchmarks/results holds the '
                             'published run)')
    args = parser.parse_args(argv)
    sources = source_info()        # before the runs: the code that gets imported and measured
    cfg = QUICK if args.quick else FULL
    warmup, measured, repeats = cfg['warmup'], cfg['measured'], cfg['repeats']

    point = Conveyor(psi=PSI, theta=THETA, mu_s=MU, mu_k=MU, gamma=gamma(),
                     frequency_hz=FREQUENCY_HZ, g=G)
    reference = mean_speed(point, warmup_cycles=warmup, cycles=measured)
    steady = mean_speed(point, warmup_cycles=200, cycles=200)
    header = (f'Conveying benchmark: box {PART_SIZE[0] * 1e3:g} x {PART_SIZE[1] * 1e3:g} mm, '
              f'{MASS * 1e3:g} g; {FREQUENCY_HZ:g} Hz, a0 = {AMPLITUDE_M * 1e3:g} mm (0-peak), '
              f'psi = {math.degrees(PSI):g} deg, theta = {math.degrees(THETA):g} deg, '
              f'mu_s = mu_k = {MU}, restitution 0 -> Gamma = {gamma():.4f}')
    print(header)
    print(f'window: {warmup} warm-up + {measured} measured cycles '
          f'({(warmup + measured) * PERIOD:g} s simulated per run); wall time = median of '
          f'{repeats} run(s) after an untimed warm-up run, advance_to() only')
    print(f'reference (point mass, same window): v_m = {reference:.9f} m/s '
          f'(V_m = {reference / point.velocity_scale:.6f}); '
          f'steady state (200 + 200 cycles): {steady:.9f} m/s, '
          f'window transient {abs(reference / steady - 1):.1e} relative', flush=True)

    print('untimed warm-up run of each method (first-call costs)...', flush=True)
    run_once('event_driven', cfg['tolerances'][0], 1, 1)
    run_once('time_stepping', cfg['steps_per_cycle'][0], 1, 1)

    settings = [('event_driven', tol) for tol in cfg['tolerances']]
    settings += [('time_stepping', n) for n in cfg['steps_per_cycle']]
    rows = []
    for method, setting in settings:
        runs = []
        for rep in range(repeats):
            r = run_once(method, setting, warmup, measured)
            runs.append(r)
            print(f'  {method:13s} {label(method, setting):10s} run {rep + 1}/{repeats}: '
                  f'v = {r["speed"]:.9f} m/s, {r["wall_per_sim_s"]:.3f} s wall/sim s',
                  flush=True)
        first = runs[0]
        rows.append({
            'method': method, 'label': label(method, setting),
            'tolerance': setting if method == 'event_driven' else None,
            'steps_per_cycle': setting if method == 'time_stepping' else None,
            'time_step_s': PERIOD / setting if method == 'time_stepping' else None,
            'speed_m_s': first['speed'],
            'rel_error': abs(first['speed'] / reference - 1.0),
            'wall_per_sim_s': statistics.median(r['wall_per_sim_s'] for r in runs),
            'wall_per_sim_s_runs': [r['wall_per_sim_s'] for r in runs],
            'speed_spread_between_runs': max(r['speed'] for r in runs)
            - min(r['speed'] for r in runs),
            'max_abs_angle_rad': max(r['max_abs_angle_rad'] for r in runs),
            **first['stats'],
        })

    rotating = {m: [r for r in rows if r['method'] == m and r['max_abs_angle_rad'] > 1e-6]
                for m in ('event_driven', 'time_stepping')}
    rotates = any(rotating.values())
    print()
    print(header)
    print(f'reference v_m = {reference * 1e3:.6f} mm/s (point mass, {warmup} warm-up + '
          f'{measured} measured cycles)')
    cols = (f'{"method":13s} {"setting":>10s} {"v_m (mm/s)":>12s} {"rel.err":>9s} '
            f'{"wall/sim s":>10s} {"lcp":>7s} {"events":>7s} {"steps":>7s} {"fallbk":>6s} '
            f'{"max|angle|":>10s}')
    print(cols)
    print('-' * len(cols))
    for r in rows:
        print(f'{r["method"]:13s} {r["label"]:>10s} {r["speed_m_s"] * 1e3:12.6f} '
              f'{r["rel_error"]:9.2e} {r["wall_per_sim_s"]:10.3f} {r["lcp_solves"]:7d} '
              f'{r["events"]:7d} {r["steps"]:7d} {r["fallbacks"]:6d} '
              f'{r["max_abs_angle_rad"]:10.1e}')
    for method, rot in rotating.items():
        sel = [r for r in rows if r['method'] == method]
        if not sel:
            continue
        peak = max(r['max_abs_angle_rad'] for r in sel)
        if rot:
            print(f'box rotation, {method}: YES at {", ".join(r["label"] for r in rot)} '
                  f'(max |angle| {peak:.1e} rad): the box does not stay flat there, so the '
                  'point mass is not an exact reference for those rows')
        else:
            print(f'box rotation, {method}: none (max |angle| {peak:.1e} rad): the point mass '
                  'is the exact reference')

    ok = [r for r in rows if r['method'] == 'event_driven'
          and r['rel_error'] <= TARGET_REL_ERROR]
    best = min(ok, key=lambda r: r['wall_per_sim_s']) if ok else None
    target = (f'target: event_driven within {TARGET_REL_ERROR:.0e} relative at <= '
              f'{TARGET_WALL_PER_SIM_S * 1e3:.0f} ms wall per simulated second')
    if best is None:
        verdict = 'measured: no event_driven setting reached 1e-4 relative -> NOT MET'
    else:
        over = best['wall_per_sim_s'] / TARGET_WALL_PER_SIM_S
        verdict = (f'measured: cheapest event_driven setting within 1e-4 is {best["label"]} '
                   f'(rel.err {best["rel_error"]:.1e}) at {best["wall_per_sim_s"] * 1e3:.0f} ms '
                   'wall per simulated second -> '
                   + ('MET' if over <= 1.0 else f'NOT MET ({over:.0f}x over the budget)'))
    def span(key: str) -> str:
        lo, hi = min(r[key] for r in ok), max(r[key] for r in ok)
        return f'{lo}' if lo == hi else f'{lo}-{hi}'

    if len(ok) > 1 and max(r['steps'] for r in ok) <= 1.05 * min(r['steps'] for r in ok):
        verdict += ('\n  note: the event_driven settings meeting 1e-4 did (nearly) the same '
                    f'work ({span("steps")} steps, {span("events")} events, '
                    f'{span("lcp_solves")} LCP solves), so their wall-time differences '
                    f'({min(r["wall_per_sim_s"] for r in ok):.2f}-'
                    f'{max(r["wall_per_sim_s"] for r in ok):.2f} s) are mostly timing noise')
    print(target)
    print(verdict)

    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = 'conveying_quick' if args.quick else 'conveying'
    result = {
        'case': {'part_size_m': PART_SIZE, 'mass_kg': MASS, 'frequency_hz': FREQUENCY_HZ,
                 'amplitude_m': AMPLITUDE_M, 'psi_deg': math.degrees(PSI),
                 'theta_deg': math.degrees(THETA), 'mu_s': MU, 'mu_k': MU, 'restitution': 0.0,
                 'gamma': gamma(), 'g': G},
        'mode': 'quick' if args.quick else 'full',
        'warmup_cycles': warmup, 'measured_cycles': measured, 'repeats': repeats,
        'reference': {'solver': 'feeder_sim.reports.pointmass', 'mean_speed_m_s': reference,
                      'steady_state_mean_speed_m_s': steady},
        'box_rotates': rotates,
        'box_rotates_in': {m: [r['label'] for r in rot] for m, rot in rotating.items()},
        'rows': rows,
        'target': {'text': target, 'verdict': verdict,
                   'best': None if best is None else best['label']},
        'machine': machine_info(),
        'simulator_source': sources,
        'command': ' '.join([Path(sys.executable).name, *sys.argv]),
    }
    (out_dir / f'{stem}.json').write_text(json.dumps(result, indent=2) + '\n')
    plot(rows, out_dir / f'{stem}.png',
         header.replace('; ', ';\n', 1) + f'\n{warmup} warm-up + {measured} measured cycles; '
         f'reference: point mass ({reference * 1e3:.3f} mm/s)')
    print(f'wrote {out_dir / (stem + ".json")} and {out_dir / (stem + ".png")}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
