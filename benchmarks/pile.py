"""Pile benchmark: N parts dropped on a walled 1 m track vibrating at 50 Hz (time stepping).

Issue target: 200 parts, ``time_stepping`` at dt = 1 ms, <= 2 s wall time per simulated second,
nothing tunnels out, cost per step about linear in the number of parts (10, 50, 200).

The scene is ``feeder_sim.model.builders.conveyor(..., walls=True, track_length=1.0)``
with the parts
moved into staggered rows above the track (small deterministic random tilts and offsets), so
they fall from up to ~0.15 m and pile up between the walls (200 parts of 20 mm need four
layers on a 1 m track). Run from the repository root::

    .venv/bin/python benchmarks/pile.py                 # 10, 50, 200 parts, 1 s each
    .venv/bin/python benchmarks/pile.py --parts 200 --duration 0.5 --repeats 1

Each part count runs ``--repeats`` times (default 3; the runs are identical but for the wall
time on a shared machine) and the table shows the run with the median wall time, the JSON
also every run's wall time. Prints progress lines, then a table, and writes
``benchmarks/results/pile.json``. Columns:
``wall s/sim s`` and ``ms/step`` time ``Simulator.advance`` (the stepping method plus the
simulator's per-contact impulse log); ``stepper`` is ``TimeStepper.advance`` alone; ``contacts``
and ``islands`` are means per step; ``LCP rows`` is the mean size of the non-trivial LCPs and
``max`` the largest; ``PGS`` counts islands answered by projected Gauss-Seidel (more than
``TimeStepSettings.direct_max_rows`` rows), ``unconv`` those that ended above
``pgs_tol_mps``, ``pgs vres`` the worst PGS velocity residual (m/s); ``fallbk`` counts
islands the numba Dantzig handed to ``lcp.solve``; ``max res`` is the largest
``lcp.residual``; ``tunnelled`` counts parts whose centre left the box between the walls and
above the track; ``KE end`` is the parts' kinetic energy at the end (mJ; the JSON also has the
mechanical energy at the start and end and whether the state stayed finite). The numba
kernels are loaded (compiled on a cold cache) by a warm-up run before any timing; its duration
is printed and stored.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import platform
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feeder_sim.model.builders import build, conveyor  # noqa: E402
from feeder_sim.simulator import Simulator  # noqa: E402

TRACK_LENGTH = 1.0
PART = (0.02, 0.01)          # builders.conveyor default part size, m
PSI, MU, GAMMA, FREQ = math.radians(30.0), 0.5, 1.2, 50.0
DT = 1e-3


def pile_scene(n_parts: int, seed: int = 1) -> dict:
    """Conveyor scene with ``n_parts`` boxes stacked in rows above the track, to be dropped."""
    scene = conveyor(psi=PSI, mu=MU, theta=0.0, gamma=GAMMA, frequency_hz=FREQ,
                     method='time_stepping', time_step=DT, n_parts=n_parts, walls=True,
                     track_length=TRACK_LENGTH, spacing=1.5 * PART[0],
                     name=f'pile_{n_parts}')
    rng = np.random.default_rng(seed)
    per_row = int((TRACK_LENGTH - 0.04) // (1.5 * PART[0]))      # 32 parts per row
    parts = [b for b in scene['bodies'] if b['type'] == 'dynamic']
    for i, body in enumerate(parts):
        row, col = divmod(i, per_row)
        in_row = min(per_row, len(parts) - row * per_row)
        pitch = (TRACK_LENGTH - 0.04) / per_row
        x = (col - 0.5 * (in_row - 1)) * pitch + (0.25 * pitch if row % 2 else 0.0)
        x += rng.uniform(-0.003, 0.003)
        y = 0.02 + 0.02 * row + rng.uniform(0.0, 0.004)
        body['pose'] = [float(x), float(y), float(rng.uniform(-0.3, 0.3))]
    return scene


def outside_walls(sim: Simulator, position: np.ndarray, height_m: float = 0.19) -> int:
    """Parts (centres ``position``, m) that left the region between the walls, above the
    track surface and below ``height_m``."""
    origin, axis = sim.world.track_frame()
    rel = position - origin
    along = rel @ axis
    up = rel @ np.array([-axis[1], axis[0]])
    inside = (np.abs(along) < 0.5 * TRACK_LENGTH) & (up > -1e-3) & (up < height_m)
    return int(np.count_nonzero(~inside))


def escaped(sim: Simulator) -> int:
    """Parts whose centre left the region between the walls above the track surface."""
    return outside_walls(sim, sim.state.position[sim.part_indices])


def run(n_parts: int, duration: float, chunk: float = 0.05) -> dict:
    """Drop ``n_parts`` and run ``duration`` simulated seconds through ``Simulator.advance``."""
    t_build = time.perf_counter()
    sim = Simulator(build(pile_scene(n_parts)))
    t_build = time.perf_counter() - t_build
    energy0 = sim.mechanical_energy()
    # the stepping method's own time and contact rows per chunk (the compiled step reports
    # many steps' contacts at once, so per-step counts are not seen here)
    stepper = sim._stepper
    inner = stepper.advance
    step_s: list[float] = []
    rows: list[int] = []

    def advance(state, t_end):
        t0 = time.perf_counter()
        reports = inner(state, t_end)
        step_s.append(time.perf_counter() - t0)
        rows.append(sum(sc.cs.contacts.n for sc in reports))
        return reports

    stepper.advance = advance
    st = sim.stats
    wall = cpu = 0.0
    max_escaped = 0
    n_chunks = int(round(duration / chunk))
    marks = []
    for k in range(1, n_chunks + 1):
        islands0, steps0 = getattr(st, 'islands', 0), st.steps
        w0, c0 = time.perf_counter(), time.process_time()
        sim.advance_to(k * chunk)
        dw, dc = time.perf_counter() - w0, time.process_time() - c0
        wall += dw
        cpu += dc
        max_escaped = max(max_escaped, escaped(sim))
        steps = st.steps - steps0
        marks.append({'t': sim.t, 'ms_per_step': 1e3 * dw / steps,
                      'stepper_ms_per_step': 1e3 * step_s[-1] / steps,
                      'max_penetration_m': st.max_penetration_m,
                      'cpu_ms_per_step': 1e3 * dc / steps,
                      'contacts': rows[-1] / steps,
                      'islands': (getattr(st, 'islands', 0) - islands0) / steps})
        m = marks[-1]
        print(f'  {n_parts:4d} parts  t = {sim.t:5.2f} s  {m["ms_per_step"]:7.3f} ms/step '
              f'(stepper {m["stepper_ms_per_step"]:6.3f})  contacts {m["contacts"]:6.1f}  '
              f'islands {m["islands"]:5.1f}  largest LCP {getattr(st, "max_lcp_rows", 0):5d} '
              f'rows  fallbacks {st.fallbacks}  unconverged {st.unconverged}  '
              f'max pen {st.max_penetration_m * 1e3:.2f} mm  escaped {max_escaped}', flush=True)
    n_steps = st.steps
    nontrivial = max(1, st.lcp_solves - st.trivial_solves)
    settled = marks[len(marks) // 2:]
    return {
        'parts': n_parts,
        'simulated_s': sim.t,
        'steps': n_steps,
        'build_s': t_build,
        'wall_s': wall,
        'cpu_s': cpu,
        'wall_per_sim_s': wall / sim.t,
        'cpu_per_sim_s': cpu / sim.t,
        'ms_per_step': 1e3 * wall / n_steps,
        'cpu_ms_per_step': 1e3 * cpu / n_steps,
        'stepper_ms_per_step': 1e3 * float(np.sum(step_s)) / n_steps,
        'ms_per_step_second_half': float(np.mean([m['ms_per_step'] for m in settled])),
        'cpu_ms_per_step_second_half': float(np.mean([m['cpu_ms_per_step'] for m in settled])),
        'contacts_mean': float(np.sum(rows)) / n_steps,
        'islands_mean': getattr(st, 'islands', 0) / n_steps,
        'lcp_rows_mean': getattr(st, 'lcp_rows', 0) / nontrivial,
        'largest_lcp_rows': getattr(st, 'max_lcp_rows', 0),
        'lcp_solves': st.lcp_solves,
        'trivial_solves': st.trivial_solves,
        'pgs_solves': getattr(st, 'pgs_solves', 0),
        'max_pgs_velocity_residual_mps': getattr(st, 'max_pgs_velocity_residual_mps', 0.0),
        'fallbacks': st.fallbacks,
        'unconverged': st.unconverged,
        'max_residual': st.max_residual,
        'max_penetration_m': st.max_penetration_m,
        'escaped': max_escaped,
        'finite': bool(all(np.isfinite(a).all() for a in (sim.state.position, sim.state.angle,
                                                          sim.state.velocity, sim.state.omega))),
        'mechanical_energy_initial_j': energy0,
        'mechanical_energy_final_j': sim.mechanical_energy(),
        'kinetic_energy_final_j': sim.world.kinetic_energy(sim.state),
        'trace': marks,
        'messages': st.messages[:5],
    }


def warm_up() -> float:
    """Load (or, on a cold cache, compile) the numba kernels before timing: a few steps of a
    small pile through both island solvers. Returns the seconds it took."""
    t0 = time.perf_counter()
    for direct_max_rows in (48, 0):         # 0: every island through the PGS kernel
        sim = Simulator(build(pile_scene(12)))
        sim._stepper.settings.direct_max_rows = direct_max_rows
        sim.advance_to(0.15)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--parts', type=int, nargs='*', default=[10, 50, 200])
    ap.add_argument('--duration', type=float, default=1.0, help='simulated seconds per run')
    ap.add_argument('--repeats', type=int, default=3,
                    help='runs per part count; the table shows the run with the median wall time')
    ap.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'pile.json'),
                    help='JSON output (default out/bench/pile.json)')
    args = ap.parse_args()
    t_warm = warm_up()
    print(f'numba kernels loaded/compiled and warm-up run in {t_warm:.1f} s', flush=True)
    results = []
    for n in args.parts:
        runs = []
        for k in range(args.repeats):
            print(f'{n} parts, {args.duration} s simulated at dt = {DT * 1e3:g} ms '
                  f'(run {k + 1} of {args.repeats})', flush=True)
            runs.append(run(n, args.duration))
        # the same deterministic run each time: only the wall time varies (a shared machine)
        runs.sort(key=lambda r: r['wall_per_sim_s'])
        median = runs[len(runs) // 2]
        median['wall_per_sim_s_runs'] = [r['wall_per_sim_s'] for r in runs]
        results.append(median)
    head = (f'{"parts":>5} {"wall s/sim s":>12} {"cpu s/sim s":>11} {"ms/step":>8} '
            f'{"(stepper)":>9} {"contacts":>8} {"islands":>7} {"LCP rows":>8} {"max":>5} '
            f'{"PGS":>6} {"unconv":>6} {"pgs vres":>8} {"fallbk":>6} {"max res":>8} '
            f'{"max pen m":>9} {"tunnelled":>9} {"KE end mJ":>9}')
    print()
    print(head)
    for r in results:
        print(f'{r["parts"]:5d} {r["wall_per_sim_s"]:12.3f} {r["cpu_per_sim_s"]:11.3f} '
              f'{r["ms_per_step"]:8.3f} {r["stepper_ms_per_step"]:9.3f} '
              f'{r["contacts_mean"]:8.1f} {r["islands_mean"]:7.1f} {r["lcp_rows_mean"]:8.1f} '
              f'{r["largest_lcp_rows"]:5d} {r["pgs_solves"]:6d} {r["unconverged"]:6d} '
              f'{r["max_pgs_velocity_residual_mps"]:8.1e} {r["fallbacks"]:6d} '
              f'{r["max_residual"]:8.1e} {r["max_penetration_m"]:9.1e} {r["escaped"]:9d} '
              f'{1e3 * r["kinetic_energy_final_j"]:9.3f}')
    print('\nwall s/sim s of every run: ' + '; '.join(
        f'{r["parts"]}: ' + ', '.join(f'{w:.3f}' for w in r['wall_per_sim_s_runs'])
        for r in results))
    print('cost per part and step (ms): ' + ', '.join(
        f'{r["parts"]}: {r["ms_per_step"] / r["parts"]:.3f} (stepper '
        f'{r["stepper_ms_per_step"] / r["parts"]:.3f})' for r in results))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'python': platform.python_version(), 'dt': DT,
                               'warm_up_s': t_warm, 'results': results}, indent=2) + '\n')
    print(f'\nwrote {out}')


if __name__ == '__main__':
    main()
