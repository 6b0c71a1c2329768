"""Every shipped scene on every stepping method steps, collides and solves as recorded.

``test/data/fingerprint.json`` holds the solver counters, the final state's bits and a hash of
every frame (state and contact report) of each case in ``fingerprint.py``. A change that is
meant to alter the physics regenerates it (``python test/fingerprint.py --write
test/data/fingerprint.json``) and says why in its commit.
"""

import json
from pathlib import Path

from fingerprint import cases, fingerprint
import pytest

WANT = json.loads((Path(__file__).parent / 'data' / 'fingerprint.json').read_text())


@pytest.mark.parametrize(('scene', 'method'), cases(), ids=[f'{s}-{m}' for s, m in cases()])
def test_identical_to_the_recorded_fingerprint(scene, method):
    assert fingerprint(scene, method) == WANT[f'{scene}/{method}']
