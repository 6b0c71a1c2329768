"""What a part added, taken away or moved costs while a world runs.

Issue target: 1 000 ``add_part``/``remove_part`` calls on a 200-part scene in at most 2 s, the
cost of a call not growing with the phase of the drive or with what was accepted before.

The 200-part pile of ``benchmarks/pile.py``, landed (0.3 s simulated), then ``--calls`` calls
in pairs: a part added above the pile and taken away again. Three ways, each ``--repeats``
times, interleaved:

- ``calls``: the calls back to back (what a script or a burst of service requests does);
- ``calls+frames``: a 10 ms frame simulated between pairs, the frame's own time subtracted
  (measured in the same loop without the calls): what a change costs the next frame (the
  stepper is made anew once per change);
- ``moves``: ``set_part_pose`` of a part of the pile to where it is, back to back.

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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'benchmarks'))

from pile import pile_scene  # noqa: E402

from feeder_sim.model.builders import build  # noqa: E402
from feeder_sim.simulator import Simulator  # noqa: E402

FRAME_S = 0.01


def landed_pile(n_parts: int) -> Simulator:
    sim = Simulator(build(pile_scene(n_parts)))
    sim.advance_to(0.3)
    return sim


def calls(sim: Simulator, n_calls: int, frames: bool) -> float:
    """Seconds per call of n_calls add/remove calls (a frame between pairs if ``frames``,
    its time not counted)."""
    template = sim.world.names[sim.part_indices[0]]
    spent = 0.0
    for _ in range(n_calls // 2):
        t0 = time.perf_counter()
        sim.add_part(template, 'visitor', [0.0, 0.4, 0.0])
        sim.remove_part('visitor')
        spent += time.perf_counter() - t0
        if frames:
            sim.advance_by(FRAME_S)
    return spent / (2 * (n_calls // 2))


def frame_cost(sim: Simulator, n_frames: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n_frames):
        sim.advance_by(FRAME_S)
    return (time.perf_counter() - t0) / n_frames


def with_frames(sim: Simulator, n_calls: int) -> float:
    """Seconds a pair of calls adds to the frame after it, per call."""
    pairs = n_calls // 2
    t0 = time.perf_counter()
    calls(sim, n_calls, frames=True)
    total = time.perf_counter() - t0
    return (total - pairs * frame_cost(sim, pairs)) / (2 * pairs)


def moves(sim: Simulator, n_calls: int) -> float:
    name = sim.world.names[sim.part_indices[-1]]
    _, origin, angle = sim.part_poses()
    pose = [*origin[-1], angle[-1]]
    t0 = time.perf_counter()
    for _ in range(n_calls):
        sim.set_part_pose(name, pose)
    return (time.perf_counter() - t0) / n_calls


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--parts', type=int, default=200)
    parser.add_argument('--calls', type=int, default=1000)
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'world_changes.json'))
    args = parser.parse_args()
    print(f'landing a {args.parts}-part pile (0.3 s simulated) ...', flush=True)
    sim = landed_pile(args.parts)
    runs: dict[str, list[float]] = {'calls': [], 'calls+frames': [], 'moves': []}
    for r in range(args.repeats):
        runs['calls'].append(calls(sim, args.calls, frames=False))
        runs['calls+frames'].append(with_frames(sim, min(args.calls, 200)))
        runs['moves'].append(moves(sim, args.calls))
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
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'parts': args.parts, 'calls': args.calls, 'rows': rows,
                               'seconds_for_calls': total, 'target_s': 2.0}, indent=2))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
