"""The first run's compile: ``feeder-sim run`` on a cold kernel cache, per stepping method.

Issue target (2-core machine): the kernels a default run needs (``track_one_box``, its
method event_driven) compile in <= 60 s from a fresh cache directory. Each run is a fresh
process, ``feeder-sim run track_one_box --duration 0.1 --method M``, with an empty
``$FEEDER_SIM_CACHE_DIR``; its wall time is nearly all numba compiling. Every method runs
several ways, round robin, so that their ratios are taken in one run: as shipped (a helper
process compiling ahead from the method's plan, callee-only kernels left without machine code
of their own, reference counts inlined); in one process (``$FEEDER_SIM_COMPILE_HELPER=0``);
and in one process with ``$FEEDER_SIM_INLINE_REFCOUNTS=0`` (numba's out-of-line reference
counting), and with that and ``$FEEDER_SIM_DEFER_CODEGEN=0`` (numba's own way: every kernel
compiled on its own and again in each caller). Prints a table of medians of ``--repeats``
and writes ``out/bench/compile.json`` with every run (peak memory: the run's process, not
its helper's)::

    .venv/bin/python benchmarks/compile.py [--repeats 3] [--methods event_driven time_stepping]
        [--modes shipped 'one process']
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import platform
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from feeder_sim.compiled.ahead import HELPER_ENV_VAR  # noqa: E402
from feeder_sim.compiled.jit import DEFER_ENV_VAR, INLINE_ENV_VAR  # noqa: E402

METHODS = ('event_driven', 'time_stepping', 'impulse_based')
MODES = {'shipped': {HELPER_ENV_VAR: '1', DEFER_ENV_VAR: '1', INLINE_ENV_VAR: '1'},
         'one process': {HELPER_ENV_VAR: '0', DEFER_ENV_VAR: '1', INLINE_ENV_VAR: '1'},
         'out-of-line refcounts': {HELPER_ENV_VAR: '0', DEFER_ENV_VAR: '1', INLINE_ENV_VAR: '0'},
         'numba default': {HELPER_ENV_VAR: '0', DEFER_ENV_VAR: '0', INLINE_ENV_VAR: '0'}}
TARGET_S = {'event_driven': 60.0}


def cold_run(method: str, switches: dict[str, str]) -> dict:
    """One ``feeder-sim run`` in a fresh process on an empty cache: wall s, peak MiB."""
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryFile('w+') as log:
        env = {k: v for k, v in os.environ.items() if not k.startswith('NUMBA_')}
        env.update(FEEDER_SIM_CACHE_DIR=cache, **switches)
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, '-m', 'feeder_sim.cli', 'run', 'track_one_box', '--duration',
             '0.1', '--method', method], cwd=ROOT, env=env, stdout=log, stderr=log)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode:
            log.seek(0)
            sys.exit(f'feeder-sim run --method {method} failed:\n{log.read()}')
    return {'wall_s': wall, 'peak_mib': usage.ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--methods', nargs='+', choices=METHODS,
                        default=['event_driven', 'time_stepping'])
    parser.add_argument('--modes', nargs='+', choices=list(MODES), default=list(MODES))
    parser.add_argument('--out', type=Path, default=ROOT / 'out' / 'bench' / 'compile.json')
    args = parser.parse_args()
    modes = [m for m in MODES if m in args.modes]
    runs: dict[str, dict[str, list]] = {m: {mode: [] for mode in modes} for m in args.methods}
    total = args.repeats * len(args.methods) * len(modes)
    done = 0
    for r in range(args.repeats):
        for method in args.methods:
            # alternate which mode runs first: the machine drifts
            for mode in (modes if r % 2 == 0 else modes[::-1]):
                result = cold_run(method, MODES[mode])
                runs[method][mode].append(result)
                done += 1
                print(f'  run {done}/{total}  {method:14s} {mode:22s} {result["wall_s"]:6.1f} s',
                      flush=True)
    rows = []
    short = {'shipped': 'shipped', 'one process': 'one proc', 'out-of-line refcounts':
             'out-of-line', 'numba default': 'numba'}
    # each mode against the one before it in MODES: what that one step brings
    steps = [(a, b) for a, b in zip(modes, modes[1:], strict=False)]
    print(f'\n{"method":>14s} ' + ' '.join(f'{short[m] + " s":>12s}' for m in modes)
          + ''.join(f' {short[a] + "/" + short[b]:>20s}' for a, b in steps)
          + f' {"target s":>9s}   peak MiB (same order)')
    for method in args.methods:
        med = {mode: statistics.median(x['wall_s'] for x in runs[method][mode])
               for mode in modes}
        peak = {mode: statistics.median(x['peak_mib'] for x in runs[method][mode])
                for mode in modes}
        ratios = {f'{a} / {b}': med[a] / med[b] for a, b in steps}
        target = TARGET_S.get(method)
        print(f'{method:>14s} ' + ' '.join(f'{med[m]:12.1f}' for m in modes)
              + ''.join(f' {r:20.2f}' for r in ratios.values())
              + f' {target if target else "-":>9}   '
              + ' / '.join(f'{peak[m]:.0f}' for m in modes))
        rows.append({'method': method, 'median_wall_s': med, 'median_peak_mib': peak,
                     'ratios': ratios, 'target_s': target, 'runs': runs[method]})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        'python': platform.python_version(), 'machine': platform.processor() or platform.machine(),
        'cpus': os.cpu_count(), 'repeats': args.repeats, 'methods': rows}, indent=1))
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()
