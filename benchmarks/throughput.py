"""Throughput of ``time_stepping`` against pymunk on the same scenes, in one run.

Scenes (issue targets as ratio = feeder_sim wall / pymunk wall):

* ``pile N``: N boxes of 20 x 10 mm dropped on a walled 1 m track vibrating at 50 Hz
  (``benchmarks/pile.py``'s scene, walls 1 m tall so that 1000 parts stay between them),
  dt = 1 ms, N = 10, 50, 200, 1000. Targets: <= 2 at 10 parts, <= 1 at 200, the 1000-part
  cost <= 5.5 x the 200-part cost, no part escaping.
* ``conveying 1``: one box on a 2 m track at 50 Hz, Gamma 1.5 (hopping), psi 20 deg,
  mu 0.5, dt = 1e-4 s. Target: <= 1.
* ``pile N, 10 sweeps`` (N = 200 and 1000, when both are run): the same piles with feeder_sim's
  projected Gauss-Seidel stopped after ``--equal-sweeps`` (10) sweeps, as pymunk stops after
  its 10 iterations: the two engines at equal solver effort, neither converged. It separates
  the cost of the contact pipeline from that of converging a deep pile to 1e-3 m/s.

* ``conveying 1, 100/s`` and ``conveying 1, 1000/s``: the one part advanced 10 ms and 1 ms at a
  time (the node's default 100 frames per simulated second; a control loop), where the cost of
  each call from Python counts: at 1 ms a call runs 10 steps.

feeder_sim runs ``Simulator.advance`` (what the node and the CLI run: the stepping method and
the per-contact impulse log) in 50 ms chunks unless a case says otherwise; pymunk steps the
same frames, each a Python loop of ``space.step``. pymunk gets the same bodies, poses, masses,
gravity and drive: its kinematic bodies (track, walls) get, before every step, the velocity
that carries them to the drive's displacement at the end of the step; pymunk's defaults
otherwise (10 iterations), a collision slop of 0.1 mm (its default, 0.1 length units, is
meant for pixels) and friction sqrt(mu) on every shape, as pymunk multiplies the two shapes'
coefficients. Runs are round robin (each repeat runs every case on both engines, in
alternating order) and the table shows medians of ``--repeats`` (>= 3) wall times, their
ratio, and the spread of the repeats' own ratios (both engines back to back); the JSON has
every run. ``escaped`` counts parts whose centre left the region between the walls;
``deepest`` is the deepest overlap (feeder_sim: the solver's largest penetration over every
step; pymunk: its contact distances sampled every 50 ms). Run from the repository root::

    .venv/bin/python benchmarks/throughput.py
    .venv/bin/python benchmarks/throughput.py --parts 10 200 --repeats 3 --duration 0.5

Writes ``benchmarks/results/throughput.{json,png}``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import platform
import statistics
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'benchmarks'))

from pile import outside_walls, pile_scene, warm_up  # noqa: E402

from feeder_sim.model.builders import build, conveyor  # noqa: E402
from feeder_sim.simulator import Simulator  # noqa: E402
from feeder_sim.stepping import TimeStepSettings  # noqa: E402

CHUNK_S = 0.05
# the one part's run again in shorter frames (simulated s per Simulator.advance call): the
# node's default publish_rate (100 frames per simulated s), and a control loop's 1 ms
FRAMES_S = (0.01, 0.001)
WALL_HEIGHT_M = 1.0
INSIDE_M = WALL_HEIGHT_M - 0.01     # a part's centre below the walls' top
PYMUNK_SLOP_M = 1e-4
CONVEYING_DT = 1e-4
TARGETS = {'pile 10': 2.0, 'pile 200': 1.0, 'conveying 1': 1.0}   # ratio feeder_sim / pymunk


def tall_walled_pile(n_parts: int) -> dict:
    """``pile_scene`` with walls ``WALL_HEIGHT_M`` tall, standing on the track's ends."""
    scene = pile_scene(n_parts)
    for body in scene['bodies']:
        if body['name'].startswith('wall_'):
            x, _, theta = body['pose']
            half = WALL_HEIGHT_M / 2
            body['polygon'] = [[-0.005, -half], [0.005, -half], [0.005, half], [-0.005, half]]
            body['pose'] = [x, half - 0.01, theta]
    return scene


def conveying_scene() -> dict:
    return conveyor(psi=math.radians(20.0), mu=0.5, theta=0.0, gamma=1.5, frequency_hz=50.0,
                    method='time_stepping', time_step=CONVEYING_DT, name='conveying_1')


# ------------------------------------------------------------------------------ feeder_sim
def run_feeder(scene: dict, duration: float, walled: bool, sweeps: int | None = None,
               frame_s: float = CHUNK_S) -> dict:
    settings = TimeStepSettings() if sweeps is None else TimeStepSettings(pgs_max_sweeps=sweeps)
    sim = Simulator(build(scene), settings=settings)
    wall = 0.0
    worst = 0
    for k in range(1, int(round(duration / frame_s)) + 1):
        t0 = time.perf_counter()
        sim.advance_to(k * frame_s)
        wall += time.perf_counter() - t0
        if walled:
            worst = max(worst, outside_walls(sim, sim.state.position[sim.part_indices], INSIDE_M))
    st = sim.stats
    return {'wall_per_sim_s': wall / sim.t, 'steps': st.steps, 'escaped': worst,
            'deepest_m': st.max_penetration_m, 'fallbacks': st.fallbacks,
            'unconverged': st.unconverged,
            'finite': bool(np.isfinite(sim.state.position).all())}


# ------------------------------------------------------------------------------ pymunk
def pymunk_world(scene: dict):
    """The scene's bodies in a pymunk space: (space, kinematic (body, drive) list, dynamic
    bodies, feeder_sim's simulator of the scene), with the drives and initial poses (drive
    displacement at t = 0 included) of feeder_sim's own world."""
    import pymunk

    sim = Simulator(build(scene))
    world = sim.world
    space = pymunk.Space()
    space.gravity = tuple(scene['gravity'])
    space.collision_slop = PYMUNK_SLOP_M
    kinematic, dynamic = [], []
    for i, spec in enumerate(scene['bodies']):
        verts = [tuple(v) for v in spec['polygon']]
        if spec['type'] == 'dynamic':
            centroid = np.mean(np.asarray(verts), axis=0)
            assert np.allclose(centroid, 0.0), 'parts here are centred boxes'
            body = pymunk.Body(spec['mass'], pymunk.moment_for_poly(spec['mass'], verts))
            dynamic.append(body)
        else:
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            kinematic.append((body, world.drives[i]))
        body.position = tuple(sim.state.position[i])
        body.angle = float(sim.state.angle[i])
        shape = pymunk.Poly(body, verts, radius=0.0)
        shape.friction = math.sqrt(spec['mu_dynamic'])
        shape.elasticity = 0.0
        space.add(body, shape)
    return space, kinematic, dynamic, sim


def pymunk_deepest(dynamic) -> float:
    deepest = [0.0]

    def visit(arbiter):
        for p in arbiter.contact_point_set.points:
            deepest[0] = max(deepest[0], -p.distance)

    for body in dynamic:
        body.each_arbiter(visit)
    return deepest[0]


def run_pymunk(scene: dict, duration: float, dt: float, walled: bool,
               frame_s: float = CHUNK_S) -> dict:
    space, kinematic, dynamic, sim = pymunk_world(scene)
    # the drives' sinusoids, evaluated inline as a pymunk user would (no command changes here)
    driven = [(body, d.amplitude_m / dt, 2 * math.pi * d.frequency_hz, d.phase_rad,
               float(d.direction[0]), float(d.direction[1]))
              for body, d in kinematic if d is not None]
    n_chunk = int(round(frame_s / dt))
    t, wall, worst, deepest = 0.0, 0.0, 0, 0.0
    for _ in range(int(round(duration / frame_s))):
        t0 = time.perf_counter()
        for _ in range(n_chunk):
            for body, a_over_dt, omega, phase, ux, uy in driven:
                speed = a_over_dt * (math.sin(omega * (t + dt) + phase)
                                     - math.sin(omega * t + phase))
                body.velocity = (speed * ux, speed * uy)
            space.step(dt)
            t += dt
        wall += time.perf_counter() - t0
        deepest = max(deepest, pymunk_deepest(dynamic))
        if walled:
            worst = max(worst, outside_walls(sim, np.array([b.position for b in dynamic]),
                                                INSIDE_M))
    finite = all(math.isfinite(b.position.x) and math.isfinite(b.position.y) for b in dynamic)
    return {'wall_per_sim_s': wall / t, 'steps': int(round(t / dt)), 'escaped': worst,
            'deepest_m': deepest, 'finite': finite}


# ------------------------------------------------------------------------------ main
def cases(parts: list[int], duration: float, conveying_s: float,
          equal_sweeps: int) -> list[dict]:
    out = [{'name': f'pile {n}', 'parts': n, 'dt': 1e-3, 'duration': duration, 'walled': True,
            'scene': tall_walled_pile(n), 'sweeps': None, 'frame_s': CHUNK_S} for n in parts]
    out.append({'name': 'conveying 1', 'parts': 1, 'dt': CONVEYING_DT,
                'duration': conveying_s, 'walled': False, 'scene': conveying_scene(),
                'sweeps': None, 'frame_s': CHUNK_S})
    out += [{'name': f'conveying 1, {round(1 / frame)}/s', 'parts': 1, 'dt': CONVEYING_DT,
             'duration': conveying_s, 'walled': False, 'scene': conveying_scene(),
             'sweeps': None, 'frame_s': frame} for frame in FRAMES_S]
    if {200, 1000} <= set(parts) and equal_sweeps:
        out += [{'name': f'pile {n}, {equal_sweeps} sweeps', 'parts': n, 'dt': 1e-3,
                 'duration': duration, 'walled': True, 'scene': tall_walled_pile(n),
                 'sweeps': equal_sweeps, 'frame_s': CHUNK_S} for n in (200, 1000)]
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    piles = [r for r in rows if r['name'].startswith('pile') and r['pgs_max_sweeps'] is None]
    equal = [r for r in rows if r['pgs_max_sweeps'] is not None]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    n = [r['parts'] for r in piles]
    ax.loglog(n, [r['feeder_sim']['median'] for r in piles], 'o-',
              label='feeder_sim time_stepping')
    if equal:
        ax.loglog([r['parts'] for r in equal], [r['feeder_sim']['median'] for r in equal], 'o:',
                  label=f'feeder_sim, {equal[0]["pgs_max_sweeps"]} PGS sweeps')
    ax.loglog(n, [r['pymunk']['median'] for r in piles], 's--', label='pymunk (10 iterations)')
    ax.set_xlabel('parts on the walled track (dt = 1 ms)')
    ax.set_ylabel('wall s per simulated s (median)')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    names = [r['name'] for r in rows]
    bx.bar(names, [r['ratio'] for r in rows], color='tab:blue')
    for r, target in zip(rows, [r['target'] for r in rows]):
        if target is not None:
            bx.plot([names.index(r['name']) - 0.4, names.index(r['name']) + 0.4], [target] * 2,
                    'r-')
    bx.axhline(1.0, color='k', lw=0.5)
    bx.set_ylabel('feeder_sim wall / pymunk wall\n(red: target)')
    bx.tick_params(axis='x', rotation=30)
    for label in bx.get_xticklabels():
        label.set_horizontalalignment('right')
    fig.suptitle('time_stepping vs pymunk, same scenes, same run')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--parts', type=int, nargs='*', default=[10, 50, 200, 1000])
    ap.add_argument('--duration', type=float, default=1.0, help='simulated s of each pile run')
    ap.add_argument('--conveying-duration', type=float, default=3.0,
                    help='simulated s of the one-part run (150 periods; a run of a few '
                         'milliseconds of wall time would measure the machine\'s jitter)')
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--equal-sweeps', type=int, default=10,
                    help='PGS sweeps of the equal-effort pile runs (0: none)')
    ap.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'throughput.json'),
                    help='JSON output, and a PNG beside it (default out/bench/throughput.json)')
    args = ap.parse_args()
    if args.repeats < 3:
        ap.error('--repeats: at least 3 (the table shows medians)')
    print('loading the numba kernels (compiling them on a cold cache) ...', flush=True)
    print(f'  ready in {warm_up():.1f} s', flush=True)
    todo = cases(args.parts, args.duration, args.conveying_duration, args.equal_sweeps)
    runs = {c['name']: {'feeder_sim': [], 'pymunk': []} for c in todo}
    for rep in range(args.repeats):
        for j, case in enumerate(todo):
            order = ('feeder_sim', 'pymunk') if (rep + j) % 2 == 0 else ('pymunk', 'feeder_sim')
            for engine in order:
                if engine == 'feeder_sim':
                    r = run_feeder(case['scene'], case['duration'], case['walled'],
                                   case['sweeps'], case['frame_s'])
                else:
                    r = run_pymunk(case['scene'], case['duration'], case['dt'], case['walled'],
                                   case['frame_s'])
                runs[case['name']][engine].append(r)
                print(f'  repeat {rep + 1}/{args.repeats}  {case["name"]:>22}  {engine:>10}  '
                      f'{r["wall_per_sim_s"]:8.4f} s/sim s  escaped {r["escaped"]}  '
                      f'deepest {1e3 * r["deepest_m"]:.2f} mm', flush=True)
    rows = []
    for case in todo:
        row = {'name': case['name'], 'parts': case['parts'], 'dt': case['dt'],
               'duration': case['duration'], 'pgs_max_sweeps': case['sweeps'],
               'frame_s': case['frame_s'], 'target': TARGETS.get(case['name'])}
        for engine in ('feeder_sim', 'pymunk'):
            rs = runs[case['name']][engine]
            row[engine] = {'median': statistics.median(r['wall_per_sim_s'] for r in rs),
                           'runs': rs}
        row['ratio'] = row['feeder_sim']['median'] / row['pymunk']['median']
        # each repeat's own ratio: both engines ran back to back, so the machine's drift
        # between repeats cancels; their spread is the measurement's
        row['repeat_ratios'] = [f['wall_per_sim_s'] / p['wall_per_sim_s'] for f, p in
                                zip(runs[case['name']]['feeder_sim'],
                                    runs[case['name']]['pymunk'], strict=True)]
        rows.append(row)
    by = {r['name']: r for r in rows}

    def growth_of(engine: str, suffix: str = '') -> float | None:
        big, small = by.get(f'pile 1000{suffix}'), by.get(f'pile 200{suffix}')
        if big is None or small is None:
            return None
        return big[engine]['median'] / small[engine]['median']

    growth = growth_of('feeder_sim')
    equal = f', {args.equal_sweeps} sweeps'
    growths = {'feeder_sim': growth, 'pymunk': growth_of('pymunk'),
               f'feeder_sim{equal}': growth_of('feeder_sim', equal)}
    print()
    print(f'{"case":>22} {"dt s":>7} {"feeder_sim":>10} {"pymunk":>8} {"ratio":>6} '
          f'{"repeats":>11} {"target":>6} {"escaped":>9} {"deepest mm":>11} {"unconv":>7}')
    print(f'{"":>22} {"":>7} {"s/sim s":>10} {"s/sim s":>8} {"":>6} {"min-max":>11} {"":>6} '
          f'{"fs / pm":>9} {"fs / pm":>11} {"steps":>7}')
    for r in rows:
        f, p = r['feeder_sim'], r['pymunk']
        esc = f'{max(x["escaped"] for x in f["runs"])} / {max(x["escaped"] for x in p["runs"])}'
        deep = (f'{1e3 * max(x["deepest_m"] for x in f["runs"]):.2f} / '
                f'{1e3 * max(x["deepest_m"] for x in p["runs"]):.2f}')
        target = f'{r["target"]:.1f}' if r['target'] is not None else '-'
        spread = f'{min(r["repeat_ratios"]):.2f}-{max(r["repeat_ratios"]):.2f}'
        unconverged = statistics.median(x['unconverged'] for x in f['runs'])
        print(f'{r["name"]:>22} {r["dt"]:7.0e} {f["median"]:10.4f} {p["median"]:8.4f} '
              f'{r["ratio"]:6.2f} {spread:>11} {target:>6} {esc:>9} {deep:>11} '
              f'{unconverged:>7.0f}')
    for engine, g in growths.items():
        if g is not None:
            print(f'1000-part cost / 200-part cost, {engine}: {g:.2f}'
                  + (' (target <= 5.5)' if engine == 'feeder_sim' else ''))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'python': platform.python_version(), 'repeats': args.repeats,
                               'cost_1000_over_200': growth,
                               'cost_1000_over_200_by_engine': growths, 'cases': rows},
                              indent=2) + '\n')
    plot(rows, out.with_suffix('.png'))
    print(f'wrote {out} and {out.with_suffix(".png")}')


if __name__ == '__main__':
    main()
