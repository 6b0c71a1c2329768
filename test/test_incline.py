"""A block on an incline (reference section 3.1): sticking must not creep, sliding is exact."""

import math

import pytest

from feeder_sim.simulator import Simulator

G = 9.81


def along(sim):
    s, _ = sim.track_coordinates()
    return float(s[0])


@pytest.mark.parametrize('method', ['event_driven', 'time_stepping'])
def test_block_that_must_stick_does_not_creep(method):
    # tan 30 deg = 0.577 < mu_s = 0.6
    sim = Simulator('incline_stick', method=method, time_step=1e-3)
    s0 = along(sim)
    sim.advance(2.0)
    assert abs(along(sim) - s0) < 1e-9
    assert sim.stats.fallbacks == 0


@pytest.mark.parametrize('method, dt, rel', [('event_driven', 1e-3, 1e-6),
                                             ('time_stepping', 1e-3, 1e-3)])
def test_block_that_slides_follows_the_analytic_acceleration(method, dt, rel):
    theta = math.radians(20.0)
    a = G * (math.sin(theta) - 0.25 * math.cos(theta))   # 1.0508 m/s^2 down the slope
    sim = Simulator('incline_slide', method=method, time_step=dt)
    s0 = along(sim)
    sim.advance(1.0)
    slid = s0 - along(sim)
    assert slid == pytest.approx(0.5 * a * 1.0 ** 2, rel=rel)
