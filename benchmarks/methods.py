"""Methods benchmark: wall time and conveying speed of each stepping method on the paper's
Fig. 7/8 scenes (one 20 x 10 mm part on the 16 Hz bowl-feeder track, 0 and 3 degree ramp,
with and without the friction impulse).

For every scene and method: wall time per simulated second (median over ``--repeats`` runs of
``Simulator.advance`` over ``--duration`` s, after a warm-up run that loads the numba kernels),
the position after 1 s (Fig. 7's number), the mean conveying speed over 2 s after a 1 s
warm-up (on the 3 degree ramp without the friction impulse the part slides back faster and
faster: no steady state, so only the positions at 1 s compare) and, as the reference, the
exact point-mass speed of ``feeder_sim.reports.pointmass`` with the same friction-impulse setting.
``event_driven`` and ``impulse_based`` run with the scene's solver settings (largest step
1/256 s, tolerance 1e-9); ``time_stepping`` at 400 steps per vibration period.

Run from the repository root:  .venv/bin/python benchmarks/methods.py [--repeats N]
Prints a table and writes benchmarks/results/methods.{json,png}.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import statistics
import sys
import time

from conveying import machine_info, source_info

from feeder_sim.model.scene import load_scene
from feeder_sim.reports.paper import _conveyor, steady_speed, TRACK_SCENES
from feeder_sim.reports.pointmass import mean_speed
from feeder_sim.simulator import Simulator

METHODS = ('event_driven', 'impulse_based', 'time_stepping')
STEPS_PER_PERIOD = 400


def _options(scene, method: str) -> dict:
    if method != 'time_stepping':
        return {'method': method}
    period = 1.0 / scene.bodies[0].vibration.frequency
    return {'method': method, 'time_step': period / STEPS_PER_PERIOD}


def measure(name: str, method: str, duration_s: float, repeats: int) -> dict:
    scene = load_scene(name)
    opts = _options(scene, method)
    walls, position = [], None
    for _ in range(repeats):
        sim = Simulator(scene, **opts)
        s0 = float(sim.track_coordinates()[0][0])
        t0 = time.perf_counter()
        sim.advance_to(duration_s)
        walls.append((time.perf_counter() - t0) / duration_s)
        position = float(sim.track_coordinates()[0][0]) - s0
    speed = steady_speed(Simulator(scene, **opts).scene)
    return {'scene': name, 'method': method, 'time_step_s': sim.scene.solver.time_step,
            'wall_per_simulated_s': statistics.median(walls), 'walls': walls,
            'position_1s_m': position, 'steady_speed_mps': speed}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5))
    markers = {'event_driven': 'o', 'impulse_based': 's', 'time_stepping': '^'}
    for name in dict.fromkeys(r['scene'] for r in rows):
        sub = [r for r in rows if r['scene'] == name]
        ref = sub[0]['point_mass_speed_mps']
        for r in sub:
            ax.scatter(r['wall_per_simulated_s'], 1e3 * r['steady_speed_mps'],
                       marker=markers[r['method']], label=f"{name} / {r['method']}")
        ax.axhline(1e3 * ref, color='0.6', lw=0.6, ls=':')
    ax.set_xscale('log')
    ax.set_xlabel('wall time per simulated second [s]')
    ax.set_ylabel('steady conveying speed [mm/s] (dotted: point mass)')
    ax.set_title('Stepping methods on the Fig. 7/8 scenes (16 Hz track)')
    ax.grid(True, alpha=0.3, which='both')
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--duration', type=float, default=1.0, help='simulated s per timed run')
    ap.add_argument('--out', default=str(Path(__file__).resolve().parents[1] / 'out' / 'bench'),
                    help='output folder (default out/bench; benchmarks/results holds the '
                         'published run)')
    args = ap.parse_args(argv)

    warm = time.perf_counter()
    for method in METHODS:              # loads (or compiles) the kernels before any timing
        Simulator(TRACK_SCENES[0, True], method=method).advance_to(0.05)
    warm = time.perf_counter() - warm
    rows = []
    for name in TRACK_SCENES.values():
        scene = load_scene(name)
        conveyor = _conveyor(scene, friction_impulse=scene.solver.friction_impulse)
        reference = mean_speed(conveyor)
        for method in METHODS:
            row = measure(name, method, args.duration, args.repeats)
            row['point_mass_speed_mps'] = reference
            row['speed_vs_point_mass'] = row['steady_speed_mps'] / reference - 1.0 \
                if reference != 0 else None
            rows.append(row)
            print(f'  {name:38s} {method:14s} {row["wall_per_simulated_s"]:7.3f} s/sim s',
                  file=sys.stderr, flush=True)

    head = (f'{"scene":38s} {"method":14s} {"wall s/sim s":>12s} {"x(1 s) mm":>10s} '
            f'{"speed mm/s":>10s} {"point mass":>10s} {"vs pm":>7s}')
    print(head)
    print('-' * len(head))
    for r in rows:
        vs = r['speed_vs_point_mass']
        print(f'{r["scene"]:38s} {r["method"]:14s} {r["wall_per_simulated_s"]:12.3f} '
              f'{1e3 * r["position_1s_m"]:10.1f} {1e3 * r["steady_speed_mps"]:10.1f} '
              f'{1e3 * r["point_mass_speed_mps"]:10.1f} '
              f'{"" if vs is None else f"{100 * vs:+.1f}%":>7s}')
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'methods.json').write_text(json.dumps(
        {'rows': rows, 'warmup_s': warm, 'repeats': args.repeats,
         'steps_per_period_time_stepping': STEPS_PER_PERIOD, 'machine': machine_info(),
         'source': source_info()}, indent=1) + '\n')
    plot(rows, out / 'methods.png')
    print(f'wrote {out / "methods.json"} and {out / "methods.png"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
