"""A continuously fed scene: sources add parts at their interval, seeded, drawn from their
region and orientation shares; sinks take away parts past the exit or fallen back; the run's
outcomes count them."""

import copy
import math

import numpy as np
from paths import DATA
import pytest
import yaml

from feeder_sim.model.scene import parse_scene, SceneError
from feeder_sim.run import run
from feeder_sim.simulator import Simulator

FED = yaml.safe_load((DATA / 'fed_track.yaml').read_text())

# parts released 1 m up in free space, taken away once they fall below 0.9 m: never in
# each other's way, so every arrival is added
RAIN = {
    'gravity': [0.0, -9.81],
    'solver': {'method': 'time_stepping', 'time_step': 1e-3},
    'sources': [{'template': 'drop', 'interval': 0.2, 'start': 0.1, 'seed': 5,
                 'region': {'x': [-0.5, 0.5], 'y': [1.0, 1.0]},
                 'orientations': {'flat': {'angle': 0.0, 'share': 0.7},
                                  'upright': {'angle': math.pi / 2}}}],
    'sinks': [{'below': 0.9}],
    'bodies': [{'name': 'drop', 'type': 'dynamic', 'mass': 0.01, 'pose': [2.0, 1.0, 0.0],
                'polygon': [[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005], [-0.01, 0.005]]},
               {'name': 'far_floor', 'type': 'static', 'pose': [0.0, -10.0, 0.0],
                'polygon': [[-1.0, -0.1], [1.0, -0.1], [1.0, 0.0], [-1.0, 0.0]]}],
}


def test_arrivals_come_at_their_interval_drawn_from_the_region_and_shares():
    sim = Simulator(parse_scene(RAIN))
    angles, xs = [], []
    for k in range(1, 401):
        sim.advance_to(0.1 * k)
        names, origin, angle = sim.part_poses()
        for n, o, a in zip(names, origin, angle):
            if n.startswith('drop_') and n not in {x[0] for x in xs}:
                xs.append((n, o[0]))
                angles.append(a)
    counts = sim.feed.counts()
    # arrivals at 0.1, 0.3, ..., 39.9 s: 200, every one added, every one fallen back (the
    # template too) but those still above 0.9 m
    assert counts['added'] == 200 and counts['blocked'] == 0
    assert counts['fell_back'] >= 199
    flat = np.mean(np.isclose(np.array(angles), 0.0))
    assert flat == pytest.approx(0.7, abs=0.1)                   # seeded: 200 draws
    x = np.array([v for _, v in xs])
    assert x.min() >= -0.5 and x.max() <= 0.5 and np.std(x) == pytest.approx(1 / math.sqrt(12),
                                                                            rel=0.15)
    again = Simulator(parse_scene(RAIN))
    again.advance_to(2.0)
    sim.reset()
    sim.advance_to(2.0)
    assert sim.feed.events == again.feed.events                  # reset: the same arrivals


def test_a_taken_place_blocks_the_arrival_until_it_is_free():
    # arrivals every 0.05 s at the same spot on a still track: one box stays there
    data = copy.deepcopy(FED)
    data['bodies'][0]['vibration']['amplitude'] = 0.0
    data['sources'][0]['interval'] = 0.05
    data['bodies'][1]['pose'] = [0.3, 0.005, 0.0]
    sim = Simulator(parse_scene(data))
    sim.advance_to(0.5)
    counts = sim.feed.counts()
    assert counts['added'] == 1 and counts['blocked'] == 10      # at 0.05, 0.1, ... 0.5 s


@pytest.mark.parametrize('dt', [5e-5, 5e-4], ids=['scene step', '10x coarser'])
def test_a_fed_track_feeds_at_the_source_rate(dt):
    # one box every 0.5 s, taken away 0.15 m on: once they arrive, 120 per minute
    sim = Simulator(parse_scene(FED), time_step=dt)
    out = run(sim, 8.0, publish_rate_hz=100.0).summary
    assert out['feed']['added'] == 17
    # the source's boxes leave one per interval (their start varies by 1 cm: 0.15 s)
    exits = sorted(p['exit_time_s'] for p in out['outcomes']['parts']
                   if p['name'].startswith('box_') and p['exit_time_s'] is not None)
    assert len(exits) >= 10
    assert 60.0 * (len(exits) - 1) / (exits[-1] - exits[0]) == pytest.approx(120.0, rel=0.05)
    assert out['outcomes']['recirculated'] == 0
    speeds = [p['mean_velocity_along_track_mps'] for p in out['parts'][1:10]]
    assert np.std(speeds) < 0.02 * np.mean(speeds)               # each conveys alike


@pytest.mark.parametrize('change, path, fragment', [
    ({'template': 'track'}, 'sources[0].template', "no dynamic body named 'track'"),
    ({'interval': 0.0}, 'sources[0].interval', 'out of range'),
    ({'orientations': {'a': {'angle': 0.0, 'share': 0.8}, 'b': {'angle': 1.0, 'share': 0.8}}},
     'sources[0].orientations', 'add up to 1.6'),
    ({'region': {'x': [1.0, 0.0], 'y': [0.0, 0.1]}}, 'sources[0].region.x', 'is empty'),
    ({'rate': 2.0}, 'sources[0]', 'either interval (s between parts) or rate'),
    ({'count': 2.5}, 'sources[0].count', 'expected a whole number in [0, 1000000], got 2.5'),
    ({'seed': 1.7}, 'sources[0].seed', 'expected a whole number in [0, 4294967296], got 1.7'),
], ids=['template', 'interval', 'shares', 'region', 'both', 'count', 'seed'])
def test_bad_sources_are_one_line_naming_the_key(change, path, fragment):
    data = copy.deepcopy(FED)
    data['sources'][0].update(change)
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.path == path and fragment in err.value.message, str(err.value)


@pytest.mark.parametrize('sink, path, fragment', [
    ({}, 'sinks[0]', 'give below (m) or past_exit: true'),
    ({'below': None, 'past_exit': False}, 'sinks[0]', 'give below (m) or past_exit: true'),
    ({'past_exit': True}, 'sinks[0].past_exit',
     'the scene has no exit: give outcomes.exit_position'),
], ids=['empty', 'neither', 'no exit'])
def test_a_sink_that_could_never_take_a_part_is_refused(sink, path, fragment):
    data = copy.deepcopy(FED)
    data.pop('outcomes', None)
    data['sinks'] = [sink]
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert err.value.path == path and fragment in err.value.message, str(err.value)


def test_a_rate_is_one_over_the_interval():
    data = copy.deepcopy(FED)
    del data['sources'][0]['interval']
    data['sources'][0]['rate'] = 2.0
    assert parse_scene(data).sources == parse_scene(FED).sources


def test_a_source_goes_on_after_its_template_part_was_taken_away():
    # the template's own part removed (a robot took it): later arrivals still copy its shape
    # and, with no orientations drawn, its starting angle
    data = copy.deepcopy(RAIN)
    data['sources'][0].pop('orientations')
    data['bodies'][0]['pose'] = [2.0, 1.0, 0.3]
    sim = Simulator(parse_scene(data))
    sim.remove_part('drop')
    sim.advance_to(0.35)
    names, _, angle = sim.part_poses()
    assert names == ('drop_1', 'drop_2')                        # at 0.1 and 0.3 s
    assert angle[-1] == pytest.approx(0.3, abs=1e-12)            # just arrived, not turned
    assert sim.feed.counts()['added'] == 2


def test_a_part_that_left_the_world_is_taken_away_not_the_run(caplog):
    # A part that fell off a track with nothing below passes the scene bounds (10 km, after
    # 45 s of free fall): at the next change of the world (an arrival) it is taken away and
    # counted as lost, one warning, and the run goes on. A part that turned over a thousand
    # radians is the simulation's own doing: it turns on, never refused as a caller's number.
    data = copy.deepcopy(RAIN)
    data['sinks'] = []
    sim = Simulator(parse_scene(data))
    sim.advance_to(0.15)                                 # drop and drop_1
    names = [sim.world.names[i] for i in sim.part_indices]
    assert names == ['drop', 'drop_1']
    fallen, spun = sim.part_indices
    # at the scene bound's edge, falling fast enough to pass it before the next arrival:
    # what the simulation moves past the bound is its own doing, not a caller's number
    sim.state.position[fallen] = [0.0, -9.95e3]
    sim.state.velocity[fallen] = [0.0, -630.0]
    sim.state.angle[spun] = 999.0                        # and spinning past 1000 rad
    sim.state.omega[spun] = 50.0
    with caplog.at_level('WARNING', logger='feeder_sim'):
        sim.advance_to(0.3 - 1e-9)
        angle_before = float(sim.state.angle[spun])
        assert angle_before > 1000.0
        sim.advance_to(0.35)                             # arrivals at 0.3 s rebuild the world
    assert [sim.world.names[i] for i in sim.part_indices] == ['drop_1', 'drop_2']
    assert sim.lost_parts == [(pytest.approx(0.3), 'drop')]
    assert sim.feed.counts()['lost'] == 1
    assert sum("part 'drop' left the world" in r.getMessage() for r in caplog.records) == 1
    # free flight since: the angle the arrival found, 1e-9 s after angle_before
    turned = (sim.state.angle[sim.part_indices[0]]
              - float(sim.state.omega[sim.part_indices[0]]) * 0.05)
    assert turned == pytest.approx(angle_before, abs=1e-6)
    sim.advance_to(0.4)
    # numbers a caller gives are checked as a scene's, not taken for a lost part
    with pytest.raises(SceneError, match='pose'):
        sim.set_part_pose('drop_1', [0.0, -2.0e4, 0.0])
    assert [sim.world.names[i] for i in sim.part_indices] == ['drop_1', 'drop_2']
