"""event_driven collision events in degenerate and fast configurations.

* Blocks meeting face-on with exactly aligned corners: every corner lies on the line of a side
  face of the other block while the faces overlap, so no corner is ever strictly inside the
  other block; the collision must still be seen (Newton's cradle of the stability report).
"""

import numpy as np
import pytest

from feeder_sim.builders import box, build
from feeder_sim.simulator import Simulator

HALF_M = 0.005        # half side of the 10 mm blocks
MASS_KG = 0.01


def block(name, x_m, y_m, vx_mps, vy_mps=0.0):
    return {'name': name, 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M), 'mass': MASS_KG,
            'pose': [x_m, y_m, 0.0], 'velocity': [vx_mps, vy_mps, 0.0], 'mu_static': 0.0,
            'mu_dynamic': 0.0, 'restitution': 1.0}


def run(bodies, duration_s, time_step_s=1e-2):
    sim = Simulator(build({'name': 'blocks', 'gravity': [0.0, 0.0],
                           'solver': {'method': 'event_driven', 'time_step': time_step_s},
                           'bodies': bodies}))
    sim.advance(duration_s)
    return sim


@pytest.mark.parametrize('time_step_s', [1e-2, 1e-4])
def test_aligned_blocks_exchange_velocities(time_step_s):
    # e = 1, equal masses, face-on: the moving block stops and the other leaves at 1 m/s.
    sim = run([block('a', -0.012, 0.0, 1.0), block('b', 0.0, 0.0, 0.0)], 0.01, time_step_s)
    assert sim.stats.impacts == 1
    assert np.allclose(sim.state.velocity[:, 0], (0.0, 1.0), rtol=0.0, atol=1e-9)
    # They met after 2 mm of travel, 2 ms in: a at -0.010 m since, b 8 mm on from 0.
    assert np.allclose(sim.state.position[:, 0], (-0.010, 0.008), rtol=0.0, atol=1e-9)


def test_newton_cradle_gives_the_simultaneous_answer():
    # Kawachi's simultaneous impulse LCP over both contacts (the touching pair enters with
    # v_N = 0): (-1/3, 2/3, 2/3) v, momentum and kinetic energy kept (e = 1).
    sim = run([block('a', -0.012, 0.0, 1.0), block('b', 0.0, 0.0, 0.0),
               block('c', 2 * HALF_M, 0.0, 0.0)], 0.01)
    v = sim.state.velocity[:, 0]
    assert np.allclose(v, (-1 / 3, 2 / 3, 2 / 3), rtol=0.0, atol=1e-9)
    assert abs(np.sum(v) - 1.0) <= 1e-12
    assert abs(0.5 * MASS_KG * np.sum(v ** 2) / (0.5 * MASS_KG) - 1.0) <= 1e-9


@pytest.mark.parametrize('start, velocity', [
    ((-2 * HALF_M, 0.0), (0.0, 1.0)),    # side by side, sliding past along the shared face
    ((0.0, 2 * HALF_M), (1.0, 0.0)),     # on top, sliding off along the shared face
])
def test_flush_blocks_sliding_past_each_other_do_not_collide(start, velocity):
    # Corners pass corners along the shared face line: nothing enters anything, so no impact
    # and the velocities stay exactly as they were.
    sim = run([block('a', *start, *velocity), block('b', 0.0, 0.0, 0.0)], 0.02)
    assert sim.stats.impacts == 0
    assert np.array_equal(sim.state.velocity[0], velocity)
    assert np.array_equal(sim.state.velocity[1], (0.0, 0.0))
