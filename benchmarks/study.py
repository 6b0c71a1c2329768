"""A 16-trial design study on 1 and on 2 Dask workers: the speed-up and the per-trial overhead.

Issue targets (2-core machine): speed-up >= 1.8 from 1 to 2 workers, and a per-trial
overhead (wall time times workers, less the trials' own run time, per trial) <= 5 % of a
1-second trial. The study is the default track with one box, sliding: 2 amplitudes x 4
frequencies x 2 repeats, 24 s simulated per trial (about a second of wall time each). Each
configuration runs ``--repeats`` times, alternating; the cluster's start-up (workers up,
kernels loaded) is timed apart. Prints a table, writes ``out/bench/study.json``::

    .venv/bin/python benchmarks/study.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import statistics
import sys
import tempfile
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feeder_sim.studies import parse_study  # noqa: E402
from feeder_sim.studies.runner import run_trials  # noqa: E402

STUDY = {
    'scene': 'track_one_box', 'duration': 24.0, 'repeats': 2, 'seed': 1,
    'parameters': {'bodies[track].vibration.amplitude': [2e-4, 3e-4],
                   'bodies[track].vibration.frequency': [40.0, 45.0, 50.0, 55.0]},
    'perturb': {'drive_phase': True},
    'metrics': ['conveying_speed_mps'],
}


def one_run(workers: int) -> dict:
    spec = parse_study(STUDY, 'benchmark')
    with tempfile.TemporaryDirectory() as tmp:
        done: list[float] = []
        timing: dict = {}
        t0 = time.perf_counter()
        rows = run_trials(spec, Path(tmp), workers=workers, timing=timing,
                          on_row=lambda row: done.append(time.perf_counter()))
        total = time.perf_counter() - t0
    trial_s = [r['wall_s'] for r in rows.values()]
    first = timing['ready_s']                   # cluster up, workers warm
    compute = done[-1] - t0 - first             # first submission to last result
    return {'workers': workers, 'wall_s': total, 'start_up_s': first, 'compute_s': compute,
            'trials': len(rows), 'trial_s_median': statistics.median(trial_s),
            'overhead_per_trial_s': (compute * workers - sum(trial_s)) / len(rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'study.json'),
                    help='JSON output (default out/bench/study.json)')
    args = ap.parse_args(argv)
    runs: dict[int, list[dict]] = {1: [], 2: []}
    for k in range(args.repeats):
        for workers in (1, 2):
            runs[workers].append(one_run(workers))
            r = runs[workers][-1]
            print(f'  repeat {k + 1}/{args.repeats}, {workers} worker(s): {r["wall_s"]:.2f} s',
                  flush=True)
    med = {w: {key: statistics.median(r[key] for r in rs) for key in rs[0]}
           for w, rs in runs.items()}
    speedup = med[1]['compute_s'] / med[2]['compute_s']
    overhead = max(med[w]['overhead_per_trial_s'] / med[w]['trial_s_median'] for w in med)
    print(f'{"workers":>8} {"wall s":>8} {"start-up s":>11} {"compute s":>10} '
          f'{"trial s":>8} {"overhead/trial":>15}')
    for w, m in med.items():
        print(f'{w:>8} {m["wall_s"]:>8.2f} {m["start_up_s"]:>11.2f} {m["compute_s"]:>10.2f} '
              f'{m["trial_s_median"]:>8.3f} {m["overhead_per_trial_s"]:>13.4f} s')
    print(f'speed-up 1 -> 2 workers (compute): {speedup:.2f} (target >= 1.8); '
          f'overhead per trial: {100 * overhead:.1f} % of a trial (target <= 5 %)')
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({'median': med, 'runs': runs, 'speedup': speedup,
                               'overhead_fraction': overhead}, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
