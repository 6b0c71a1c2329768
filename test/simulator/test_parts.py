"""Parts that come and go while a simulation runs: added from a template, removed, put
somewhere else; the drives keep their commands, reset brings the scene back."""

import math

import numpy as np
import pytest

from feeder_sim.model.scene import SceneError
from feeder_sim.simulator import Simulator

G = 9.81


def speed_over(sim: Simulator, t0: float, t1: float) -> np.ndarray:
    sim.advance_to(t0)
    s0 = sim.track_coordinates()[0]
    sim.advance_to(t1)
    return (sim.track_coordinates()[0] - s0) / (t1 - t0)


# each method at the scene's step and ten times coarser
STEPS = pytest.mark.parametrize('method, dt', [
    ('event_driven', 1e-3), ('event_driven', 1e-2),
    ('time_stepping', 5e-5), ('time_stepping', 5e-4)])


@STEPS
def test_an_added_part_conveys_as_the_scene_part_does(method, dt):
    # a second box, 0.1 m ahead of the first, added at rest at 0.2 s: once both are on the
    # drive's periodic orbit (20 periods later) they convey at one speed
    sim = Simulator('track_one_box', method=method, time_step=dt)
    sim.advance_to(0.2)
    sim.add_part('box', 'box_2', [-0.3, 0.005, 0.0])
    assert sim.part_poses()[0] == ('box', 'box_2')
    speed = speed_over(sim, 0.6, 1.0)
    assert speed[0] > 0.03
    assert speed[1] == pytest.approx(speed[0], rel=1e-3)


def test_a_removed_part_leaves_the_others_as_if_it_never_was():
    far = Simulator('track_one_box')
    far.advance_to(0.1)
    far.add_part('box', 'box_2', [0.3, 0.005, 0.0])    # 0.7 m ahead: never touches
    far.advance_to(0.3)
    far.remove_part('box_2')
    far.advance_to(0.6)
    alone = Simulator('track_one_box')
    alone.advance_to(0.6)
    assert far.part_poses()[0] == ('box',)
    np.testing.assert_allclose(far.state.position, alone.state.position, rtol=0, atol=1e-9)


@STEPS
def test_a_part_put_somewhere_falls_from_there(method, dt):
    # in flight both methods are exact for constant gravity (the midpoint rule integrates a
    # constant acceleration exactly), whatever the step
    sim = Simulator('track_one_box', method=method, time_step=dt)
    sim.advance_to(0.1)
    sim.set_part_pose('box', [0.1, 0.05, 0.3], [0.2, 0.0, 1.0])
    _, origin, angle = sim.part_poses()
    assert origin[0] == pytest.approx([0.1, 0.05]) and angle[0] == pytest.approx(0.3)
    com0 = sim.state.position[1].copy()
    sim.advance_to(0.15)                                   # in flight: 12 mm fall, no contact
    t = 0.05
    np.testing.assert_allclose(sim.state.position[1], com0 + [0.2 * t, -0.5 * G * t * t],
                               rtol=0, atol=1e-12)
    assert sim.state.angle[1] == pytest.approx(0.3 + 1.0 * t, abs=1e-12)


def test_drives_keep_their_commands_and_reset_brings_the_scene_back():
    sim = Simulator('track_one_box')
    sim.advance_to(0.05)
    sim.command_vibration(2e-4, 60.0)
    sim.add_part('box', 'box_2', [-0.2, 0.005, 0.0])
    drive = sim.world.drives[sim.world.driven[0]]
    assert (drive.amplitude_m, drive.frequency_hz) == (2e-4, 60.0)
    sim.advance_to(0.1)
    sim.reset()
    assert sim.part_poses()[0] == ('box',) and sim.t == 0.0
    drive = sim.world.drives[sim.world.driven[0]]
    assert (drive.amplitude_m, drive.frequency_hz) == (3.5e-4, 50.0)
    fresh = Simulator('track_one_box')
    for s in (sim, fresh):
        s.advance_to(0.3)
    np.testing.assert_array_equal(sim.state.position, fresh.state.position)


@pytest.mark.parametrize('call, fragment', [
    (lambda s: s.add_part('box', 'box', [0.0, 0.005, 0.0]), "duplicate body name 'box'"),
    (lambda s: s.add_part('box', 'b', [0.0, 0.0, 0.0]), "'b' and 'track' overlap"),
    (lambda s: s.add_part('track', 'b', [0.0, 0.1, 0.0]), 'template must name a dynamic'),
    (lambda s: s.remove_part('track'), "no part named 'track'"),
    (lambda s: s.set_part_pose('crate', [0.0, 0.1, 0.0]), "no part named 'crate'"),
    (lambda s: s.add_part('box', 'b', [math.nan, 0.1, 0.0]), 'finite'),
])
def test_bad_changes_are_refused_in_one_line_and_change_nothing(call, fragment):
    sim = Simulator('track_one_box')
    sim.advance_to(0.05)
    before = sim.state.position.copy()
    with pytest.raises((ValueError, SceneError), match=fragment) as err:
        call(sim)
    assert '\n' not in str(err.value)
    assert sim.part_poses()[0] == ('box',)
    np.testing.assert_array_equal(sim.state.position, before)
