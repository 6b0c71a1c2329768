"""A block on an incline (reference section 3.1): sticking must not creep, sliding is exact."""

import math

import pytest

from feeder_sim.model.builders import box, build, on_slope, scene_dict
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


def overhanging_slide(method: str, centre_inside_m: float, dt: float = 1e-3) -> Simulator:
    """``incline_slide``'s block and slope, the block ``centre_inside_m`` from the slope's
    lower end: a positive value less than the block's half length leaves it resting on its
    own upper corner and on the slope's corner, a vertex of the slope on the block's face."""
    theta = math.radians(20.0)
    material = {'mu_static': 0.3, 'mu_dynamic': 0.25, 'restitution': 0.0}
    slope = {'name': 'incline', 'type': 'static',
             'polygon': [[-0.1, -0.02], [0.1, -0.02], [0.1, 0.0], [-0.1, 0.0]],
             'pose': [0.0, 0.0, theta], **material}
    block = {'name': 'block', 'type': 'dynamic', 'polygon': box(0.01, 0.005), 'mass': 0.01,
             'pose': [*on_slope(-0.1 + centre_inside_m, 0.005, theta), theta], **material}
    scene = scene_dict('overhanging_slide', [slope, block], method, dt)
    scene['track'] = 'incline'
    return Simulator(build(scene))


# A constant acceleration is exact for event_driven and for time_stepping's semi-implicit
# Euler at any step (round-off only); impulse_based's micro-collisions leave about 1 %.
EXACT = [('event_driven', 1e-9), ('time_stepping', 1e-9)]


@pytest.mark.parametrize('method, rel, turn_rad', [(*m, 1e-9) for m in EXACT]
                         + [('impulse_based', 1e-2, 1e-5)])
@pytest.mark.parametrize('centre_inside_m', [0.004, 0.05])
@pytest.mark.parametrize('dt', [1e-3, 5e-3])
def test_block_overhanging_the_slopes_end_slides_like_one_on_the_slope(method, rel, turn_rad,
                                                                       centre_inside_m, dt):
    # Rigid-body mechanics does not care where under the block the support is while the
    # centre of mass stays over it: a g (sin 20 - 0.25 cos 20) slide either way (the friction
    # of the block's corner and of the slope's corner, a group of one line, reaches its cone
    # together; counted with opposite signs it held the block stuck at the corner).
    theta = math.radians(20.0)
    a = G * (math.sin(theta) - 0.25 * math.cos(theta))
    sim = overhanging_slide(method, centre_inside_m, dt)
    s0 = along(sim)
    sim.advance(0.06)         # 1.9 mm: the centre stays 2 mm inside the end
    assert s0 - along(sim) == pytest.approx(0.5 * a * 0.06 ** 2, rel=rel)
    assert abs(sim.state.angle[1] - theta) < turn_rad


@pytest.mark.parametrize('centre_inside_m', [0.004, 0.05])
@pytest.mark.parametrize('dt', [1e-3, 5e-3])
def test_time_stepping_on_the_row_states_of_the_step_before_slides_exactly(centre_inside_m, dt):
    # The same slides with time_stepping solving each step's island in the row states of the
    # step before (reuse_row_states, the default), and that path doing the work: g (sin 20 -
    # 0.25 cos 20) to 1e-9 with no pivot after the first steps (measured: 8 pivots in 12
    # and in 60 steps, against 52 and 244 solving from scratch).
    theta = math.radians(20.0)
    a = G * (math.sin(theta) - 0.25 * math.cos(theta))
    sim = overhanging_slide('time_stepping', centre_inside_m, dt)
    assert sim._stepper.settings.reuse_row_states
    s0 = along(sim)
    sim.advance(0.03)
    pivots = sim.stats.pivots
    sim.advance(0.06)
    assert s0 - along(sim) == pytest.approx(0.5 * a * 0.06 ** 2, rel=1e-9)
    assert sim.stats.pivots == pivots and sim.stats.steps * dt == pytest.approx(0.06)
    assert sim.stats.fallbacks == 0


def offset_stack(method: str, offset_m: float, dt: float = 1e-3) -> Simulator:
    """Two ``incline_slide`` blocks stacked on a 20 degree slope that holds the lower one
    (mu 0.8), the upper one ``offset_m`` along the slope: offset, it rests on its own corner
    on the lower block's face and on the lower block's corner on its face."""
    theta = math.radians(20.0)
    blocks = {'mu_static': 0.3, 'mu_dynamic': 0.25, 'restitution': 0.0}
    slope = {'name': 'incline', 'type': 'static',
             'polygon': [[-0.2, -0.02], [0.2, -0.02], [0.2, 0.0], [-0.2, 0.0]],
             'pose': [0.0, 0.0, theta], 'mu_static': 0.8, 'mu_dynamic': 0.8, 'restitution': 0.0}
    lower = {'name': 'lower', 'type': 'dynamic', 'polygon': box(0.01, 0.005), 'mass': 0.01,
             'pose': [*on_slope(0.0, 0.005, theta), theta], **blocks}
    upper = {'name': 'upper', 'type': 'dynamic', 'polygon': box(0.01, 0.005), 'mass': 0.01,
             'pose': [*on_slope(offset_m, 0.015, theta), theta], **blocks}
    scene = scene_dict('offset_stack', [slope, lower, upper], method, dt)
    scene['track'] = 'incline'
    return Simulator(build(scene))


@pytest.mark.parametrize('method, rel, still_m', [(*m, 1e-12) for m in EXACT]
                         + [('impulse_based', 2e-2, 2e-5)])
@pytest.mark.parametrize('offset_m', [-0.006, 0.0, 0.006])
@pytest.mark.parametrize('dt', [1e-3, 5e-3])
def test_upper_block_of_an_offset_stack_slides_on_the_lower_one(method, rel, still_m,
                                                                 offset_m, dt):
    # The lower block sticks to the slope (mu 0.8 > tan 20); the upper one slides down its
    # face at g (sin 20 - 0.25 cos 20) however far it overhangs (while its centre stays over
    # the lower block): part on part, the overhanging case pairs a corner of each block on
    # the other's face, one friction group. With no offset the blocks meet corner on corner:
    # impulse_based must take the lower block's corner against the upper block's bottom face,
    # not its end face (it held the upper block, and at dt 5 ms its capped sweeps stalled the
    # clock).
    theta = math.radians(20.0)
    a = G * (math.sin(theta) - 0.25 * math.cos(theta))
    sim = offset_stack(method, offset_m, dt)
    s0, _ = sim.track_coordinates()
    sim.advance(0.05)
    s1, _ = sim.track_coordinates()
    assert abs(s1[0] - s0[0]) < still_m
    assert s0[1] - s1[1] == pytest.approx(0.5 * a * 0.05 ** 2, rel=rel)
