"""Sensors read off the poses: a beam (presence, count) and an inspection line (each passing
part and its orientation), checked against the analytic motion of parts sliding at a known
speed and against crossings computed independently from the recorded poses."""

from __future__ import annotations

import math
from pathlib import Path

from mcap_ros2.reader import read_ros2_messages
import numpy as np
from paths import DATA
import pytest
import yaml

from feeder_sim.model.scene import load_scene, parse_scene, scene_to_dict, SceneError
from feeder_sim.output.sensors import segment_cuts_polygon, SensorBank
from feeder_sim.run import run
from feeder_sim.simulator import Simulator

SCENE = DATA / 'sensor_slide.yaml'
SPEED = 0.1            # m/s, both boxes, frictionless floor
BEAM_X, CAMERA_X = 0.05, 0.1
START_X = {'flat_box': 0.0, 'upright_box': -0.05}
HALF_WIDTH = {'flat_box': 0.01, 'upright_box': 0.005}   # along x, as they lie
RATE = 100.0           # frames per simulated second
FRAME = 1.0 / RATE


@pytest.fixture(scope='module')
def slide_log(tmp_path_factory) -> tuple[dict, Path]:
    path = tmp_path_factory.mktemp('sensors') / 'slide.mcap'
    result = run(Simulator(SCENE), 2.0, publish_rate_hz=RATE, record=path, log_time='sim')
    return result.summary, path


def _topics(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    for m in read_ros2_messages(str(path)):
        out.setdefault(m.channel.topic, []).append((m.log_time_ns / 1e9, m.ros_msg))
    return out


def test_the_beam_sees_each_part_while_its_outline_is_in_the_beam(slide_log):
    _, path = slide_log
    blocked = _topics(path)['/feeder_sim/sensors/beam/blocked']
    assert len(blocked) == 200                                   # one per frame
    for t, msg in blocked:
        # analytic: x0 + v t within half a width of the beam, for either box (1e-9 m slack
        # for the frames whose edge is exactly at the beam)
        gaps = [abs(START_X[n] + SPEED * t - BEAM_X) - HALF_WIDTH[n] for n in START_X]
        if min(gaps) < -1e-9:
            assert msg.data, t
        elif min(gaps) > 1e-9:
            assert not msg.data, t


def test_counts_step_when_the_centres_cross_and_agree_with_the_recorded_poses(slide_log):
    summary, path = slide_log
    topics = _topics(path)
    assert summary['sensors'] == {'beam': 2, 'camera': 2}
    poses = topics['/feeder_sim/part_poses']
    names = ['flat_box', 'upright_box']
    for sensor, x in (('beam', BEAM_X), ('camera', CAMERA_X)):
        counts = topics[f'/feeder_sim/sensors/{sensor}/count']
        # reference 1: the frames in which a recorded pose went from before the line to on
        # or past it (the boxes are centred, so the pose is the centre of mass)
        expected, total = [], 0
        for (_, prev), (_, now) in zip(poses, poses[1:]):
            total += sum(prev.poses[k].position.x < x <= now.poses[k].position.x
                         for k in range(len(names)))
            expected.append(total)
        assert [m.data for _, m in counts[1:]] == expected
        # reference 2: the analytic crossing times, to within the frame that contains them
        steps = [t for (t, m), (_, m0) in zip(counts[1:], counts) if m.data > m0.data]
        analytic = sorted((x - START_X[n]) / SPEED for n in names)
        assert len(steps) == 2
        for t, t_cross in zip(steps, analytic, strict=True):
            assert t_cross - 1e-9 <= t <= t_cross + FRAME + 1e-9


def test_the_inspection_line_names_each_part_and_its_orientation(slide_log):
    _, path = slide_log
    passed = _topics(path)['/feeder_sim/sensors/camera/passed']
    assert [(m.key, m.value) for _, m in passed] == [('flat_box', 'flat'),
                                                    ('upright_box', 'upright')]
    for (t, m) in passed:
        t_cross = (CAMERA_X - START_X[m.key]) / SPEED
        assert t_cross - 1e-9 <= t <= t_cross + FRAME + 1e-9


def test_a_part_is_counted_from_the_frame_after_it_came_and_only_forwards():
    scene = load_scene(SCENE)
    bank = SensorBank(scene.sensors, scene.outcomes)
    box = (np.array([[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005], [-0.01, 0.005]]),)
    outlines = {'a': box, 'b': box}

    def frame(names, xs):
        com = np.array([[x, 0.005] for x in xs])
        return bank.update(names, com, com, np.zeros(len(xs)), outlines)

    frame(['a'], [0.04])
    # b appears past the beam: no count; a crosses: one
    beam = frame(['a', 'b'], [0.06, 0.07])[0]
    assert beam.count == 1 and [p for p, _ in beam.passed] == ['a']
    # a goes back and forth: the way back is not counted, the way forth again is
    assert frame(['a', 'b'], [0.04, 0.07])[0].count == 1
    assert frame(['a', 'b'], [0.06, 0.07])[0].count == 2
    # a crossing outside the segment (above its top at 0.03 m) is no pass
    bank.reset()
    bank.update(['a'], np.array([[0.04, 0.05]]), np.array([[0.04, 0.05]]), np.zeros(1), outlines)
    assert bank.update(['a'], np.array([[0.06, 0.05]]), np.array([[0.06, 0.05]]), np.zeros(1),
                       outlines)[0].count == 0


def test_segment_against_polygon():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    cases = [
        (([0.5, -1.0], [0.5, 2.0]), True),     # straight through
        (([0.2, 0.2], [0.8, 0.8]), True),      # inside, touching no edge
        (([1.0, -1.0], [1.0, 2.0]), True),     # along an edge
        (([1.5, -1.0], [1.5, 2.0]), False),    # beside it
        (([-1.0, 2.0], [2.0, 1.0 + 1e-9]), False),   # just above a corner's line
        (([-1.0, 1.0], [0.0, 1.0]), True),     # ends on a corner
        (([2.0, 0.5], [3.0, 0.5]), False),     # on an edge's line, outside
    ]
    for (a, b), expected in cases:
        assert segment_cuts_polygon(np.array(a), np.array(b), square) is expected, (a, b)


@pytest.mark.parametrize('change, path, words', [
    ({'type': 'photo_eye'}, 'sensors[0].type', 'beam, inspection'),
    ({'name': '1st'}, 'sensors[0].name', 'letters'),
    ({'line': [[0.05, 0.0], [0.05, 0.0]]}, 'sensors[0].line', 'apart'),
    ({'line': [[0.05, 0.0]]}, 'sensors[0].line', 'two points'),
    ({'line': [[0.05, 0.0], [0.05, math.inf]]}, 'sensors[0].line[1][1]', ''),
    ({'name': 'camera'}, 'sensors[1].name', 'two sensors'),
])
def test_sensors_are_validated(change, path, words):
    data = yaml.safe_load(SCENE.read_text())
    data['sensors'][0].update(change)
    with pytest.raises(SceneError) as err:
        parse_scene(data, 'sensor_slide.yaml')
    assert path in str(err.value) and words in str(err.value)


def test_sensors_survive_writing_the_scene_back():
    scene = load_scene(SCENE)
    again = parse_scene(scene_to_dict(scene), 'again')
    assert again.sensors == scene.sensors
