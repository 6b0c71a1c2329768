"""Outcome measures: exits, feed rate, exit orientation and jams, in the summary and the log."""

from dataclasses import replace
import json

from mcap.reader import make_reader
import numpy as np
import pytest

from feeder_sim.model.scene import load_scene, OutcomeSpec
from feeder_sim.output.outcomes import OutcomeTracker
from feeder_sim.run import run
from feeder_sim.simulator import Simulator


def test_tracker_on_prescribed_motion():
    tracker = OutcomeTracker(('a', 'b'), OutcomeSpec(exit_position=1.0, jam_time=0.5,
                                                     jam_distance=1e-3))
    for k in range(201):
        t = k * 0.01
        tracker.update(t, np.array([t, 0.2]), np.array([[t, 0.0], [0.2, 0.0]]),
                       np.array([0.1, 3.0]))
    out = tracker.summary()
    a, b = out['parts']
    assert a['exit_time_s'] == pytest.approx(1.0) and a['exit_angle_rad'] == pytest.approx(0.1)
    assert a['exit_point_m'] == pytest.approx([1.0, 0.0])   # where it crossed the exit line
    assert a['jam_time_s'] is None
    assert b['exit_point_m'] is None
    assert b['exit_time_s'] is None and b['jam_time_s'] == pytest.approx(0.5)
    assert out['parts_exited'] == 1 and out['jams'] == 1
    assert out['feed_rate_parts_per_min'] == pytest.approx(60.0 / 2.0)


def test_exit_orientation_is_named_after_the_nearest_one_within_the_tolerance():
    spec = OutcomeSpec(exit_position=0.0, exit_axis=(0.0, -1.0), orientation_tolerance=0.3,
                       orientations=(('open_end_up', np.pi / 2), ('open_end_down', -np.pi / 2)))
    tracker = OutcomeTracker(('a', 'b', 'c', 'd'), spec)
    # progress along [0, -1] is minus the height: every part is at or below the exit
    tracker.update(0.0, np.zeros(4), np.zeros((4, 2)),
                   np.array([np.pi / 2 + 0.29, -np.pi / 2 - 0.1, 3 * np.pi / 2, 0.0]))
    out = tracker.summary()
    assert [p['exit_orientation'] for p in out['parts']] == \
        ['open_end_up', 'open_end_down', 'open_end_down', 'other']
    assert out['exit_orientations'] == {'open_end_up': 1, 'open_end_down': 2, 'other': 1}


def test_outcome_settings_are_checked_and_written_back():
    from feeder_sim.model.scene import parse_scene, scene_to_dict, SceneError
    base = scene_to_dict(load_scene('track_one_box'))
    base['outcomes'] = {'exit_position': 0.05, 'exit_axis': [0.0, -2.0],
                        'orientations': {'flat': 0.0, 'on_edge': 1.5708}}
    scene = parse_scene(base)
    assert scene.outcomes.exit_axis == (0.0, -1.0)
    assert scene.outcomes.orientations == (('flat', 0.0), ('on_edge', 1.5708))
    assert parse_scene(scene_to_dict(scene)).outcomes == scene.outcomes
    for bad, where in (({'exit_axis': [0.0, 0.0]}, 'outcomes.exit_axis'),
                       ({'orientations': [0.0]}, 'outcomes.orientations'),
                       ({'orientations': {'up': 'north'}}, 'outcomes.orientations.up'),
                       ({'orientation_tolerance': 4.0}, 'outcomes.orientation_tolerance')):
        with pytest.raises(SceneError, match=where.replace('.', r'\.')):
            parse_scene({**base, 'outcomes': bad})


def test_feeding_part_exits_and_a_resting_one_jams(tmp_path):
    base = load_scene('track_one_box')
    # The box starts 0.4 m before the track's middle and feeds at about 40 mm/s.
    feeding = replace(base, outcomes=OutcomeSpec(exit_position=-0.38, jam_time=0.5))
    result = run(Simulator(feeding), 1.5, record=tmp_path / 'feed.mcap')
    part = result.summary['outcomes']['parts'][0]
    assert 0.4 < part['exit_time_s'] < 0.7
    assert abs(part['exit_angle_rad']) < 1e-6            # flat, as it rode
    assert part['jam_time_s'] is None
    with open(tmp_path / 'feed.mcap', 'rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert json.loads(meta['outcomes']['json']) == result.summary['outcomes']

    track = base.bodies[0]
    still = replace(base, bodies=(replace(track, vibration=replace(track.vibration,
                                                                   amplitude=0.0)),
                                  *base.bodies[1:]),
                    outcomes=OutcomeSpec(exit_position=-0.38, jam_time=0.5))
    out = run(Simulator(still), 1.0).summary['outcomes']
    assert out['jams'] == 1 and out['parts'][0]['jam_time_s'] == pytest.approx(0.5, abs=0.011)
    assert out['parts_exited'] == 0 and out['feed_rate_parts_per_min'] == 0.0


def test_the_steady_feed_rate_leaves_out_the_first_arrival():
    # three parts leaving at 2, 3 and 4 s of a 5 s run: 36 per minute over the run, one per
    # second (60 per minute) once they arrive
    tracker = OutcomeTracker(('a', 'b', 'c'), OutcomeSpec(exit_position=1.0, jam_time=10.0))
    for k in range(501):
        t = k * 0.01
        tracker.update(t, np.array([t - 1.0, t - 2.0, t - 3.0]), np.zeros((3, 2)), np.zeros(3))
    out = tracker.summary()
    assert [p['exit_time_s'] for p in out['parts']] == pytest.approx([2.0, 3.0, 4.0])
    assert out['feed_rate_parts_per_min'] == pytest.approx(36.0)
    assert out['feed_rate_steady_parts_per_min'] == pytest.approx(60.0)
    one = OutcomeTracker(('a',), OutcomeSpec(exit_position=0.0))
    one.update(0.0, np.ones(1), np.zeros((1, 2)), np.zeros(1))
    assert one.summary()['feed_rate_steady_parts_per_min'] is None
