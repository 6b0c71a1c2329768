"""The log draws itself: every body's frame in /tf at every frame and every body's outline once in
/feeder_sim/geometry (in its own frame), read back with mcap_ros2 and with rerun's own MCAP
import."""

from __future__ import annotations

import math
from pathlib import Path
import subprocess
import sys

from mcap_ros2.reader import read_ros2_messages
import numpy as np
from paths import DATA, TESTS
import pytest
from rerun.chunk import RrdReader
from visualization_msgs.msg import Marker

from feeder_sim.model.scene import load_scene
from feeder_sim.run import run
from feeder_sim.simulator import Simulator


@pytest.fixture(scope='module')
def track_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp('viewer') / 'ten.mcap'
    run(Simulator('track_ten_boxes'), 0.3, record=path)
    return path


def _messages(path: Path, topic: str) -> list:
    return [(m.log_time_ns, m.ros_msg) for m in read_ros2_messages(str(path), topics=[topic])]


def _yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def test_every_frame_places_every_body_and_the_parts_where_the_poses_say(track_log):
    scene = load_scene('track_ten_boxes')
    names = [b.name for b in scene.bodies]
    parts = [b.name for b in scene.bodies if b.type == 'dynamic']
    tf = _messages(track_log, '/tf')
    poses = dict(_messages(track_log, '/feeder_sim/part_poses'))
    assert len(tf) == len(poses) == 30
    for t, msg in tf:
        assert [x.child_frame_id for x in msg.transforms] == names
        assert {x.header.frame_id for x in msg.transforms} == {'world'}
        by_name = {x.child_frame_id: x for x in msg.transforms}
        for name, pose in zip(parts, poses[t].poses, strict=True):
            tr = by_name[name].transform
            assert (tr.translation.x, tr.translation.y) == (pose.position.x, pose.position.y)
            assert _yaw(tr.rotation) == pytest.approx(_yaw(pose.orientation), abs=1e-12)
    # the track moves with its drive: its frame is that of the simulator at each frame
    sim = Simulator('track_ten_boxes')
    track = names.index(scene.track)
    for k, (_, msg) in enumerate(tf[:5], start=1):
        sim.advance_to(k * 0.01)
        origin, angle = sim.world.body_frame_pose(sim.state)
        x = msg.transforms[track].transform
        assert (x.translation.x, x.translation.y) == pytest.approx(tuple(origin[track]),
                                                                   abs=1e-15)
        assert _yaw(x.rotation) == pytest.approx(angle[track], abs=1e-15)


def test_each_outline_is_drawn_once_in_its_own_frame(track_log):
    scene = load_scene('track_ten_boxes')
    geometry = _messages(track_log, '/feeder_sim/geometry')
    assert len(geometry) == 1
    markers = geometry[0][1].markers
    assert [m.ns for m in markers] == [b.name for b in scene.bodies for _ in b.outlines]
    for m, (body, k) in zip(markers, [(b, k) for b in scene.bodies
                                      for k in range(len(b.outlines))], strict=True):
        assert m.header.frame_id == body.name and m.frame_locked and m.id == k
        assert m.type == Marker.LINE_STRIP and m.action == Marker.ADD and m.scale.x > 0
        outline = np.asarray(body.outlines[k])
        points = np.array([[p.x, p.y] for p in m.points])
        assert np.array_equal(points, np.vstack([outline, outline[:1]]))   # closed, exact


def test_parts_that_come_are_drawn_and_parts_that_go_are_deleted(tmp_path):
    log = tmp_path / 'fed.mcap'
    run(Simulator(str(DATA / 'fed_track.yaml')), 2.0, record=log)
    drawn: dict[str, bool] = {}
    names = {t: list(m.name) for t, m in _messages(log, '/feeder_sim/track_state')}
    tf = dict(_messages(log, '/tf'))
    for t, msg in _messages(log, '/feeder_sim/geometry'):
        for m in msg.markers:
            drawn[m.ns] = m.action == Marker.ADD
        # after each update, exactly the bodies of that frame are drawn
        assert {n for n, on in drawn.items() if on} == {
            x.child_frame_id for x in tf[t].transforms}
    assert any(not on for on in drawn.values())           # a part left
    assert sum(1 for n in drawn if n.startswith('box_')) >= 3
    assert set(names[max(names)]) <= {n for n, on in drawn.items() if on}


def test_rerun_reads_the_frames_as_transforms(track_log, tmp_path):
    rrd = tmp_path / 'raw.rrd'
    rerun = Path(sys.executable).with_name('rerun')
    subprocess.run([str(rerun), 'mcap', 'convert', str(track_log), '-o', str(rrd),
                    '--timeline-type', 'duration'], check=True, capture_output=True, timeout=120)
    components: dict[str, set] = {}
    children: set = set()
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        components.setdefault(chunk.entity_path, set()).update(batch.schema.names)
        if chunk.entity_path == '/tf' and 'Transform3D:child_frame' in batch.schema.names:
            for row in batch.column('Transform3D:child_frame').to_pylist():
                children.update(row or [])
    assert {'Transform3D:translation', 'Transform3D:quaternion'} <= components['/tf']
    assert children == {b.name for b in load_scene('track_ten_boxes').bodies}
    assert any('MarkerArray' in c for c in components['/feeder_sim/geometry'])


def test_part_impulses_in_the_log_carry_the_weight_of_parts_sliding_without_friction(tmp_path):
    # two boxes of 10 g slide on a frictionless floor: every frame of 10 ms the floor gives
    # each m g dt = 9.81e-4 N s straight up and nothing along it, at the centre of mass
    log = tmp_path / 'slide.mcap'
    run(Simulator(str(DATA / 'sensor_slide.yaml')), 0.3, record=log)
    clouds = _messages(log, '/feeder_sim/part_impulses')
    poses = dict(_messages(log, '/feeder_sim/part_poses'))
    assert len(clouds) == 30
    for t, cloud in clouds:
        rows = np.frombuffer(bytes(cloud.data), dtype=np.dtype({
            'names': [f.name for f in cloud.fields],
            'formats': ['<f4' if f.datatype == 7 else '<u4' for f in cloud.fields],
            'offsets': [f.offset for f in cloud.fields], 'itemsize': cloud.point_step}))
        assert rows['part'].tolist() == [0, 1] and (rows['contacts'] >= 1).all()
        assert rows['impulse_y'] == pytest.approx([0.01 * 9.81 * 0.01] * 2, rel=1e-5)
        assert np.abs(rows['impulse_x']).max() <= 1e-9
        for row, pose in zip(rows, poses[t].poses, strict=True):
            assert (row['x'], row['y']) == pytest.approx(
                (pose.position.x, pose.position.y), abs=1e-7)     # float32


JS_PACKAGES = {'@mcap/core': '2.2.2', '@foxglove/rosmsg': '5.0.5',
               '@foxglove/rosmsg2-serialization': '3.1.0', '@foxglove/wasm-zstd': '1.0.1'}


@pytest.fixture(scope='module')
def foxglove_decoders() -> Path:
    """A directory holding the npm packages Foxglove decodes ROS 2 logs with (installed once
    into the user's cache, never into the checkout)."""
    import json
    import os
    import shutil
    if shutil.which('node') is None or shutil.which('npm') is None:
        pytest.skip('Node.js and npm are needed to run the viewer\'s own decoders')
    home = Path(os.environ.get('XDG_CACHE_HOME', Path.home() / '.cache'))
    where = home / 'feeder_sim' / 'viewer-decoders'
    where.mkdir(parents=True, exist_ok=True)
    manifest = {'name': 'viewer-decoders', 'private': True, 'dependencies': JS_PACKAGES}
    package = where / 'package.json'
    if not (where / 'node_modules').is_dir() or not package.is_file() or json.loads(
            package.read_text()) != manifest:
        (where / 'package.json').write_text(json.dumps(manifest))
        subprocess.run(['npm', 'install', '--no-audit', '--no-fund', '--silent'], cwd=where,
                       check=True, capture_output=True, timeout=300)
    shutil.copy(TESTS / 'js' / 'decode_mcap.mjs', where / 'decode_mcap.mjs')
    return where


def test_foxglove_decoders_read_every_message_as_the_python_reader_does(foxglove_decoders,
                                                                       tmp_path):
    import json
    log = tmp_path / 'slide.mcap'
    run(Simulator(str(DATA / 'sensor_slide.yaml')), 1.2, record=log)
    out = subprocess.run(['node', str(foxglove_decoders / 'decode_mcap.mjs'), str(log)],
                         capture_output=True, text=True, check=True, timeout=120).stdout
    theirs = json.loads(out)
    ours: dict[str, list] = {}
    for m in read_ros2_messages(str(log)):
        ours.setdefault(m.channel.topic, []).append(m)
    assert {t for t, v in theirs.items() if v['messages']} == set(ours)
    for topic, messages in ours.items():
        assert len(theirs[topic]['messages']) == len(messages), topic
    geometry = theirs['/feeder_sim/geometry']['messages'][0]['message']['markers']
    ref = ours['/feeder_sim/geometry'][0].ros_msg.markers
    assert [(m['ns'], m['header']['frame_id'], m['frame_locked'], m['type']) for m in geometry] \
        == [(m.ns, m.header.frame_id, m.frame_locked, m.type) for m in ref]
    assert [[(p['x'], p['y']) for p in m['points']] for m in geometry] == \
        [[(p.x, p.y) for p in m.points] for m in ref]
    for a, b in zip(theirs['/tf']['messages'], ours['/tf'], strict=True):
        assert [(x['child_frame_id'], x['transform']['translation']['x'],
                 x['transform']['rotation']['z']) for x in a['message']['transforms']] == \
            [(x.child_frame_id, x.transform.translation.x, x.transform.rotation.z)
             for x in b.ros_msg.transforms]
        assert int(a['log_time']) == b.log_time_ns
    passed = [(m['message']['key'], m['message']['value'])
              for m in theirs['/feeder_sim/sensors/camera/passed']['messages']]
    assert passed == [('flat_box', 'flat')]          # the upright box passes at 1.5 s
