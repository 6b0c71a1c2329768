"""A part that stops sliding where static friction can hold it stays stopped (every method).

A box launched up a slope with mu_d < tan(theta) < mu_s decelerates at
a = g (sin theta + mu_d cos theta), stops after t* = v0 / a at s* = v0^2 / (2 a), and then
static friction holds it. The step that ends the slip must re-establish sticking: a method that
keeps dynamic friction after it slides back down at g (sin theta - mu_d cos theta).
"""

import math

import numpy as np
import pytest

from feeder_sim.model.builders import box_part, build, G, ground, on_slope, scene_dict
from feeder_sim.simulator import Simulator
from feeder_sim.stepping.event_driven.stepper import EventSettings
from feeder_sim.stepping.impulse_based import ImpulseSettings

THETA, MU_S, MU_D = math.radians(30.0), 0.6, 0.4
DECEL = G * (math.sin(THETA) + MU_D * math.cos(THETA))
# impulse_based rests a part on micro-collisions that hop sqrt(2 g eps); between them nothing
# holds it on the slope, so it creeps at about tan(theta) times that speed (module docstring)
CREEP_IB = 2.0 * math.tan(THETA) * math.sqrt(2 * G * ImpulseSettings().envelope_m)


def launched(method: str, v0: float, dt: float, theta: float = THETA,
             settings=None) -> Simulator:
    """A box launched up a slope of ``theta`` (rad) at ``v0`` (m/s)."""
    mu = {'mu_static': MU_S, 'mu_dynamic': MU_D}
    c, s = math.cos(theta), math.sin(theta)
    bodies = [{**ground(angle=theta), **mu},
              {**box_part('box', 0.01, 0.005, (*on_slope(0.0, 0.005, theta), theta),
                          (v0 * c, v0 * s, 0.0)), **mu}]
    return Simulator(build(scene_dict('restick', bodies, method, dt)), settings=settings)


def along(sim: Simulator, theta: float = THETA) -> float:
    """The box's distance along the slope (m)."""
    return float(sim.state.position[1] @ np.array([math.cos(theta), math.sin(theta)]))


# (method, default step): the step the stability report uses; each also at 10x coarser
STEPS = [('time_stepping', 1e-3), ('event_driven', 1e-2), ('impulse_based', 1e-3)]


@pytest.mark.timeout(300)
@pytest.mark.parametrize('scale', [1, 10], ids=['default', 'coarse'])
@pytest.mark.parametrize('method, dt', STEPS, ids=[m for m, _ in STEPS])
@pytest.mark.parametrize('v0', [0.27, 0.5, 1.3])
def test_a_block_that_stops_on_a_slope_stays(method, dt, scale, v0):
    h = dt * scale
    sim = launched(method, v0, h)
    s0 = along(sim)
    t_stop, s_stop = v0 / DECEL, v0 ** 2 / (2 * DECEL)
    # sample on a grid that never lands on t*: the stop falls inside a step
    sim.advance(t_stop + 0.1 + 0.37 * h)
    s1 = along(sim) - s0
    sim.advance(t_stop + 1.5)
    s2 = along(sim) - s0
    if method == 'event_driven':
        assert s1 == pytest.approx(s_stop, abs=1e-9)
        assert abs(s2 - s1) < 1e-12
        assert np.abs(sim.state.velocity[1]).max() < 1e-12
    elif method == 'time_stepping':
        # the stop falls inside a step: the place is off by less than the last step's travel
        assert s1 == pytest.approx(s_stop, abs=DECEL * h ** 2)
        assert abs(s2 - s1) < 1e-9
    else:
        assert s1 == pytest.approx(s_stop, abs=5e-4)
        assert abs(s2 - s1) <= CREEP_IB * 1.4
    assert sim.stats.fallbacks == 0


@pytest.mark.parametrize('dt', [1e-3, 1e-2], ids=['default', 'coarse'])
@pytest.mark.parametrize('chained', [True, False])
@pytest.mark.parametrize('theta', [0.0, THETA], ids=['flat', 'slope'])
def test_event_driven_stops_a_slip_where_it_ends(chained, theta, dt):
    """The slip stop is located where its event function has passed the event threshold: the
    contact then sticks with the slip reversed by up to that threshold times the speed scale
    (~3e-10 m/s here), which a sticking mode keeps. The mode choice closes it by an impulse
    (counted, recorded), on the chain's path and on the general one alike: the box stops at
    v0^2 / (2 a) and then does not move by a picometre in 5 s."""
    v0 = 0.5
    sim = launched('event_driven', v0, dt, theta, EventSettings(chained=chained))
    decel = G * (math.sin(theta) + MU_D * math.cos(theta))
    s0 = along(sim, theta)
    sim.advance(v0 / decel + 0.1)
    s1 = along(sim, theta) - s0
    assert s1 == pytest.approx(v0 ** 2 / (2 * decel), abs=1e-9)
    assert np.abs(sim.state.velocity[1]).max() < 1e-14
    assert abs(sim.state.omega[1]) < 1e-12
    sim.advance(5.0)
    assert abs(along(sim, theta) - s0 - s1) < 1e-12
    assert sim.stats.slip_closures >= 1


@pytest.mark.timeout(120)
@pytest.mark.parametrize('method', ['time_stepping', 'impulse_based'])
def test_where_static_friction_cannot_hold_the_block_slides_back(method):
    """Control: on a 35 deg slope (tan 35 deg = 0.70 > mu_s) the block stops, then slides back
    down at g (sin - mu_d cos), so the restick rule only holds where Coulomb allows it."""
    theta = math.radians(35.0)
    v0 = 0.5
    sim = launched(method, v0, 1e-3, theta)
    up = G * (math.sin(theta) + MU_D * math.cos(theta))
    down = G * (math.sin(theta) - MU_D * math.cos(theta))
    t_stop, s_stop = v0 / up, v0 ** 2 / (2 * up)
    s0 = along(sim, theta)
    after = 0.5
    sim.advance(t_stop + after)
    s = along(sim, theta) - s0
    if method == 'time_stepping':
        # the step in which the slip reverses is one-sided (no friction against the
        # reversal): a velocity error up to 2 mu_d g cos(theta) h, kept for the rest of the run
        tol = 2 * MU_D * G * math.cos(theta) * 1e-3 * after
    else:
        # a micro-collision holds a slip below 2 mu_s (2 v_b) (see impulse_based's module
        # docstring): the slide back starts late by that much speed
        tol = 2 * (2 * MU_S * 2 * math.sqrt(2 * G * ImpulseSettings().envelope_m)) * after
    assert s == pytest.approx(s_stop - 0.5 * down * after ** 2, abs=tol)
