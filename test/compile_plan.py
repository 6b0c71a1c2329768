"""Record what a first run compiles, as the helper's plan (``feeder_sim/compiled/plans``).

Each method's plan comes from a fresh process on an empty kernel cache running
``feeder-sim run track_one_box --duration 0.1 --method M`` (the default scene) with the helper
off; it lists every kernel compiled, with its signature, own compile time and callees (see
``feeder_sim.compiled.ahead``). A method whose first compile a helper would not shorten by a
fifth gets no plan. Record again after changing kernels' signatures;
``test_compile_ahead.py`` says when a plan has gone stale::

    .venv/bin/python test/compile_plan.py [event_driven time_stepping]
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile

ROOT = Path(__file__).resolve().parents[1]
METHODS = ('event_driven', 'time_stepping')
# a plan ships only if the helper takes at least a fifth off the simulated first compile
WORTH = 0.8


def record_in_this_process(method: str, out: Path) -> None:
    from feeder_sim.cli import main
    from feeder_sim.compiled import ahead

    with ahead.record() as records:
        status = main(['run', 'track_one_box', '--duration', '0.1', '--method', method])
    if status:
        sys.exit(f'feeder-sim run --method {method} failed ({status})')
    plan = ahead.encode_plan(records)
    print(f'{method}: {len(plan["items"])} kernels, {plan["alone_s"]} s alone, '
          f'{plan["with_helper_s"]} s with the helper (simulated)', flush=True)
    if plan['with_helper_s'] > WORTH * plan['alone_s']:
        # one kernel's own compile is most of it (time_stepping's whole step, one LLVM module)
        out.unlink(missing_ok=True)
        print(f'  not worth a helper (more than {WORTH:.0%} of the time alone): no plan',
              flush=True)
        return
    out.write_text(json.dumps(plan, indent=1) + '\n')


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == '--record':
        record_in_this_process(sys.argv[2], Path(sys.argv[3]))
        return
    for method in sys.argv[1:] or METHODS:
        with tempfile.TemporaryDirectory() as cache:
            env = {k: v for k, v in os.environ.items() if not k.startswith('NUMBA_')}
            env.update(FEEDER_SIM_CACHE_DIR=cache, FEEDER_SIM_COMPILE_HELPER='0')
            out = ROOT / 'feeder_sim' / 'compiled' / 'plans' / f'{method}.json'
            print(f'recording {method} on a cold cache (a minute or two) ...', flush=True)
            subprocess.run([sys.executable, __file__, '--record', method, str(out)], cwd=ROOT,
                           env=env, check=True)


if __name__ == '__main__':
    main()
