"""What a part added, taken away or moved costs while a world runs.

Issue target: 1 000 ``add_part``/``remove_part`` calls on a 200-part scene in at most 2 s, the
cost of a call not growing with the phase of the drive or with what was accepted before.

The 200-part pile of ``benchmarks/pile.py``, landed (0.3 s simulated), then ``--calls`` calls
in pairs: a part added above the pile and taken away again, each way ``--repeats``
times, interleaved:

- ``calls``: the calls back to back (what a script or a burst of service requests does);
- ``moves``: ``set_part_pose`` of a part of the pile to where it is, back to back;
- ``pymunk calls`` (when pymunk is installed, the benchmark extra): the peer's
  ``space.add`` / ``space.remove`` of a box body and shape in a space of the same 200 boxes,
  landed the same 0.3 s, in the same run; the ratio is feeder_sim's calls over pymunk's.

Prints a table and writes ``out/bench/world_changes.json`` (``--out`` elsewhere)::

    .venv/bin/python benchmarks/world_changes.py [--calls 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import statistics
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'benchmarks'))

from pile import pile_scene  # noqa: E402

from feeder_sim.model.builders import build  # noqa: E402
from feeder_sim.simulator import Simulator  # noqa: E402


def landed_pile(n_parts: int) -> Simulator:
    sim = Simulator(build(pile_scene(n_parts)))
    sim.advance_to(0.3)
    return sim


def calls(sim: Simulator, n_calls: int) -> float:
    """Seconds per call of n_calls add/remove calls, back to back."""
    template = sim.world.names[sim.part_indices[0]]
    spent = 0.0
    for _ in range(n_calls // 2):
        t0 = time.perf_counter()
        sim.add_part(template, 'visitor', [0.0, 0.4, 0.0])
        sim.remove_part('visitor')
        spent += time.perf_counter() - t0
    return spent / (2 * (n_calls // 2))


def moves(sim: Simulator, n_calls: int) -> float:
    name = sim.world.names[sim.part_indices[-1]]
    _, origin, angle = sim.part_poses()
    pose = [*origin[-1], angle[-1]]
    t0 = time.perf_counter()
    for _ in range(n_calls):
        sim.set_part_pose(name, pose)
    return (time.perf_counter() - t0) / n_calls


def pymunk_space(sim: Simulator):
    """The pile as a pymunk space (boxes of the same size and mass where the parts are now,
    the track and walls as static boxes), landed 0.3 s at the same step; None without
    pymunk."""
    try:
        import pymunk
    except ImportError:
        return None
    space = pymunk.Space()
    space.gravity = tuple(sim.world.gravity)
    names, origin, angle = sim.part_poses()
    for i in range(sim.world.n):
        pieces = sim.scene.bodies[i].pieces
        if sim.world.dynamic[i]:
            body = pymunk.Body(float(sim.world.mass[i]), float(sim.world.inertia[i]))
            body.position = tuple(sim.state.position[i])
            body.angle = float(sim.state.angle[i])
            shapes = [pymunk.Poly(body, [tuple(v - sim.world.com_local[i]) for v in p])
                      for p in pieces]
        else:
            body = space.static_body
            c, s_ = np.cos(sim.state.angle[i]), np.sin(sim.state.angle[i])
            rot = np.array([[c, -s_], [s_, c]])
            shapes = [pymunk.Poly(body, [tuple(rot @ (v - sim.world.com_local[i])
                                               + sim.state.position[i]) for v in p])
                      for p in pieces]
        space.add(*([body] if sim.world.dynamic[i] else []), *shapes)
    for _ in range(300):
        space.step(1e-3)
    return space


def pymunk_calls(space, template: np.ndarray, n_calls: int) -> float:
    import pymunk
    t0 = time.perf_counter()
    for _ in range(n_calls // 2):
        body = pymunk.Body(0.01, 1e-6)
        body.position = (0.0, 0.4)
        shape = pymunk.Poly(body, [tuple(v) for v in template])
        space.add(body, shape)
        space.remove(body, shape)
    return (time.perf_counter() - t0) / (2 * (n_calls // 2))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--parts', type=int, default=200)
    parser.add_argument('--calls', type=int, default=1000)
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'world_changes.json'))
    args = parser.parse_args()
    print(f'landing a {args.parts}-part pile (0.3 s simulated) ...', flush=True)
    sim = landed_pile(args.parts)
    space = pymunk_space(sim)
    part = sim.part_indices[0]
    template = sim.scene.bodies[part].pieces[0] - sim.world.com_local[part]
    runs: dict[str, list[float]] = {'calls': [], 'moves': []}
    if space is not None:
        runs['pymunk calls'] = []
    for r in range(args.repeats):
        runs['calls'].append(calls(sim, args.calls))
        runs['moves'].append(moves(sim, args.calls))
        if space is not None:
            runs['pymunk calls'].append(pymunk_calls(space, template, args.calls))
        print(f'  repeat {r + 1}/{args.repeats}: ' + ', '.join(
            f'{k} {v[-1] * 1e3:.2f} ms' for k, v in runs.items()), flush=True)
    rows = {k: {'ms_per_call': statistics.median(v) * 1e3, 'repeats_ms': [x * 1e3 for x in v]}
            for k, v in runs.items()}
    total = rows['calls']['ms_per_call'] * args.calls / 1e3
    print(f'\n{"what":14s} {"ms per call":>12s}   repeats')
    for k, row in rows.items():
        print(f'{k:14s} {row["ms_per_call"]:12.3f}   '
              + ' '.join(f'{x:.3f}' for x in row['repeats_ms']))
    print(f'\n{args.calls} add/remove calls on {args.parts} parts: {total:.2f} s '
          f'(target <= 2 s: {"met" if total <= 2.0 else "not met"})')
    ratio = None
    if space is not None:
        ratios = [a / b for a, b in zip(runs['calls'], runs['pymunk calls'], strict=True)]
        ratio = statistics.median(ratios)
        print(f'feeder_sim / pymunk per add/remove call: {ratio:.1f} (repeats '
              f'{min(ratios):.1f}-{max(ratios):.1f})')
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'parts': args.parts, 'calls': args.calls, 'rows': rows,
                               'seconds_for_calls': total, 'target_s': 2.0,
                               'ratio_to_pymunk': ratio}, indent=2))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
