"""Every shipped scene on every stepping method steps, collides and solves as recorded.

``test/data/fingerprint.json`` holds the solver counters, the final state's bits and a hash of
every frame (state and contact report) of each case in ``fingerprint.py``. A change that is
meant to alter the physics regenerates it (``python test/fingerprint.py --write
test/data/fingerprint.json``) and says why in its commit. On a machine whose LAPACK and math
library round differently from the recording one (``platform_signature``), a case must agree
to round-off instead (``beyond_round_off``).
"""

import json
import os
from pathlib import Path
import subprocess
import sys

from fingerprint import (
    beyond_round_off,
    cases,
    fingerprint,
    PLATFORM_KEY,
    platform_signature,
    POSITION_TOL_M,
)
import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
WANT = json.loads((HERE / 'data' / 'fingerprint.json').read_text())
SAME_PLATFORM = WANT.get(PLATFORM_KEY) == platform_signature()


@pytest.mark.parametrize(('scene', 'method'), cases(), ids=[f'{s}-{m}' for s, m in cases()])
def test_identical_to_the_recorded_fingerprint(scene, method):
    got, want = fingerprint(scene, method), WANT[f'{scene}/{method}']
    if SAME_PLATFORM:
        assert got == want
    else:
        assert beyond_round_off(got, want) == []


def test_round_off_comparison_refuses_a_change_of_physics():
    """What the comparison on another machine lets through: round-off of the positions and
    the pivot count; not a moved part, a changed counter or another final time."""
    want = WANT['track_one_box/event_driven']
    x = float.fromhex(want['final_position'][1])

    def changed(**edits) -> dict:
        got = json.loads(json.dumps(want))
        for key, value in edits.items():
            if key == 'position':
                got['final_position'][1] = float(x + value).hex()
            elif key == 'final_t':
                got['final_t'] = value
            else:
                got['stats'][key] = value
        return got

    assert beyond_round_off(changed(position=np.spacing(x) * 4, pivots=-1), want) == []
    assert beyond_round_off(changed(position=10 * POSITION_TOL_M), want) != []
    assert beyond_round_off(changed(events=want['stats']['events'] + 1), want) != []
    assert beyond_round_off(changed(final_t=(1.0).hex()), want) != []


# the cases of one method in a fresh process: their fingerprints, and whether the patches of
# numba internals were on there
UNPATCHED = '''
import json, sys
from fingerprint import cases, run_all
from feeder_sim.compiled import cache
got = run_all(cases([sys.argv[1]]), verbose=False)
print(json.dumps({'cases': got, 'patches': [cache.state['deferred_codegen'],
                                            cache.state['inline_refcounts']]}))
'''


def test_the_numba_patches_leave_the_physics_alone(tmp_path):
    """``feeder_sim.compiled.jit`` patches numba (callee-only kernels without machine code of
    their own, reference counts behind inlined null tests): other machine code, the same
    physics. impulse_based's cases, compiled cold with both patches off, give the recorded
    fingerprints (which the patched build gave). Cheap to compile cold (some 20 s in all), they
    go through the same ``jit`` / ``inner`` machinery as the other methods, and through the
    collision kernels all methods share."""
    method = 'impulse_based'
    env = {k: v for k, v in os.environ.items() if not k.startswith(('NUMBA_', 'FEEDER_SIM'))}
    env.update(FEEDER_SIM_DEFER_CODEGEN='0', FEEDER_SIM_INLINE_REFCOUNTS='0',
               FEEDER_SIM_CACHE_DIR=str(tmp_path / 'cache'), FEEDER_SIM_COMPILE_PROGRESS='0',
               # this checkout's package and fingerprint.py, whatever else is on the path
               PYTHONPATH=os.pathsep.join(p for p in (str(HERE.parent), str(HERE),
                                                      env.get('PYTHONPATH')) if p))
    done = subprocess.run([sys.executable, '-c', UNPATCHED, method], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.splitlines()[-1])
    assert out['patches'] == [False, False]
    assert sorted(out['cases']) == sorted(f'{s}/{m}' for s, m in cases([method]))
    for name, got in out['cases'].items():
        if SAME_PLATFORM:
            assert got == WANT[name], name
        else:
            assert beyond_round_off(got, WANT[name]) == [], name
