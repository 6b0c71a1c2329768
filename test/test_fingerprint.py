"""Every shipped scene on every stepping method steps, collides and solves as recorded.

``test/data/fingerprint.json`` holds the solver counters, the final state's bits and a hash of
every frame (state and contact report) of each case in ``fingerprint.py``. A change that is
meant to alter the physics regenerates it (``python test/fingerprint.py --write
test/data/fingerprint.json``) and says why in its commit. On a machine whose LAPACK and math
library round differently from the recording one (``platform_signature``), a case must agree
to round-off instead (``beyond_round_off``).
"""

import json
from pathlib import Path

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

WANT = json.loads((Path(__file__).parent / 'data' / 'fingerprint.json').read_text())
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
