"""feeder-sim replay: MCAP logs to rerun recordings, checked with rerun's own readers."""

import json
import math
from pathlib import Path
import subprocess
import sys

from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.reader import read_ros2_messages
from mcap_ros2.writer import Writer as Ros2Writer
import numpy as np
from paths import DATA
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from feeder_sim.cli import main
from feeder_sim.model.scene import load_scene, scene_to_dict
from feeder_sim.output import msgdefs
from feeder_sim.output import replay as replay_module
from feeder_sim.output.recording import (
    CONTACT_POINT_DTYPE,
    McapRecorder,
    read_messages,
    TOPIC_PART_POSES,
)
from feeder_sim.output.replay import replay
from feeder_sim.run import run
from feeder_sim.simulator import Simulator

POSES = '/feeder_sim/part_poses'
CONTACTS = '/feeder_sim/contacts'
TRACK = '/feeder_sim/track_state'


# --------------------------------------------------------------------------------------------
# Fixtures and helpers


@pytest.fixture(autouse=True, scope='module')
def strict_rerun():
    """Make rerun raise on bad data instead of logging a warning."""
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(False)


@pytest.fixture(scope='module')
def ten_log(tmp_path_factory) -> Path:
    """Ten boxes (time stepping), 0.1 s at 200 Hz: 20 frames with contacts."""
    path = tmp_path_factory.mktemp('ten') / 'ten.mcap'
    run(Simulator('track_ten_boxes'), 0.1, publish_rate_hz=200, record=path)
    return path


@pytest.fixture(scope='module')
def ten_rrd(ten_log, tmp_path_factory) -> Path:
    return replay(ten_log, tmp_path_factory.mktemp('ten_rrd') / 'ten.rrd', spawn=False)


@pytest.fixture(scope='module')
def chunked_log(tmp_path_factory) -> Path:
    """One box (event driven), 0.2 s at 200 Hz (40 frames), rewritten in 1 KiB chunks."""
    folder = tmp_path_factory.mktemp('one')
    run(Simulator('track_one_box'), 0.2, publish_rate_hz=200, record=folder / 'one_run.mcap')
    return rechunk(folder / 'one_run.mcap', folder / 'one.mcap', chunk_size=1024)


def rechunk(source: Path, target: Path, chunk_size: int) -> Path:
    """Copy of an MCAP file (schemas, channels, messages, metadata) with small chunks, so
    that cutting it leaves complete chunks."""
    with open(source, 'rb') as stream, open(target, 'wb') as out:
        reader = make_reader(stream)
        writer = Writer(out, chunk_size=chunk_size)
        writer.start(profile='ros2', library='test')
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                            schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id])
            writer.add_message(channels[channel.id], message.log_time, message.data,
                               message.publish_time, message.sequence)
        writer.finish()
    return target


def messages(path: Path, topic: str) -> list:
    return list(read_ros2_messages(str(path), topics=[topic]))


def chunks(rrd: Path) -> list:
    return list(RrdReader(str(rrd)).stream().to_chunks())


def temporal(rrd: Path, entity: str, component: str) -> tuple[np.ndarray, list]:
    """(sim_time ns, values) of every row of ``entity`` holding ``component``, by time."""
    times, values = [], []
    for chunk in chunks(rrd):
        if chunk.entity_path != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        times += [int(v) for v in batch.column('sim_time').cast('int64').to_pylist()]
        values += batch.column(component).to_pylist()
    order = np.argsort(times, kind='stable')
    return np.asarray(times, np.int64)[order], [values[i] for i in order]


def static(rrd: Path, entity: str, component: str):
    for chunk in chunks(rrd):
        batch = chunk.to_record_batch()
        if chunk.entity_path == entity and chunk.is_static and component in batch.schema.names:
            return batch.column(component).to_pylist()[-1]
    raise KeyError(f'{entity} has no static {component}')


def stamp_ns(msg) -> int:
    """The simulated time of a message with a header (log times start at the run's wall
    clock)."""
    stamp = msg.ros_msg.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def transformed(polygon: np.ndarray, x: float, y: float, theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    closed = np.vstack([polygon, polygon[:1]])
    return closed @ np.array([[c, -s], [s, c]]).T + [x, y]


def yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y ** 2 + q.z ** 2))


# --------------------------------------------------------------------------------------------
# Contents


def test_recording_has_the_entities_components_and_blueprint(ten_log, ten_rrd):
    reader = RrdReader(str(ten_rrd))
    (recording,) = reader.recordings()
    assert recording.application_id == 'feeder_sim'
    assert len(reader.blueprints()) == 1
    components: dict[str, set] = {}
    timelines = set()
    for chunk in chunks(ten_rrd):
        names = set(chunk.to_record_batch().schema.names)
        components.setdefault(chunk.entity_path, set()).update(names)
        timelines.update(chunk.timeline_names)
    assert timelines == {'sim_time'}  # nothing on the wall-clock log_time / log_tick
    assert {'LineStrips2D:strips', 'LineStrips2D:labels'} <= components['/world/parts']
    assert 'LineStrips2D:strips' in components['/world/track']
    assert 'Points2D:positions' in components['/world/parts/origins']
    assert 'Points2D:positions' in components['/world/contacts/points']
    assert {'Arrows2D:origins', 'Arrows2D:vectors'} <= components['/world/contacts/impulses']
    for i in range(10):
        for kind in ('position', 'speed'):
            assert 'Scalars:scalars' in components[f'/plots/{kind}/box_{i}']
    for name in ('amplitude', 'frequency'):
        assert 'Scalars:scalars' in components[f'/plots/vibration/{name}']
    assert 'TextDocument:text' in components['/notes']
    # one row per pose message, at the message's time
    pose_msgs = messages(ten_log, POSES)
    times, strips = temporal(ten_rrd, '/world/parts', 'LineStrips2D:strips')
    assert len(pose_msgs) == 20 and len(strips) == len(pose_msgs)
    assert times.tolist() == [stamp_ns(m) for m in pose_msgs]
    assert static(ten_rrd, '/world/parts', 'LineStrips2D:labels') == [
        f'box_{i}' for i in range(10)]
    # the layout: the 2D world and the three plots, time panel on sim_time
    blueprint = {}
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        for name in ('TimePanelBlueprint:timeline', 'ViewBlueprint:space_origin',
                     'ViewBlueprint:class_identifier', 'ViewContents:query'):
            if name in batch.schema.names:
                blueprint.setdefault(name, []).extend(
                    v for row in batch.column(name).to_pylist() for v in row)
    assert blueprint['TimePanelBlueprint:timeline'] == ['sim_time']
    assert set(blueprint['ViewBlueprint:space_origin']) == {
        '/', '/plots/position', '/plots/speed', '/plots/vibration', '/notes'}
    assert sorted(blueprint['ViewBlueprint:class_identifier']) == [
        '2D', 'TextDocument', 'TimeSeries', 'TimeSeries', 'TimeSeries']
    assert '/world/**' in blueprint['ViewContents:query']
    # the series names say the units
    assert static(ten_rrd, '/plots/position/box_4', 'SeriesLines:names') == ['box_4 [mm]']
    assert static(ten_rrd, '/plots/speed/box_4', 'SeriesLines:names') == ['box_4 [mm/s]']


def test_rrd_verifies_with_the_rerun_cli(ten_rrd):
    exe = Path(sys.executable).with_name('rerun')
    cmd = [str(exe)] if exe.exists() else [sys.executable, '-m', 'rerun']
    proc = subprocess.run([*cmd, 'rrd', 'verify', str(ten_rrd)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_part_outlines_are_the_scene_polygons_at_the_logged_poses(ten_log, ten_rrd):
    scene = load_scene('track_ten_boxes')
    pose_msgs = messages(ten_log, POSES)
    times, strips = temporal(ten_rrd, '/world/parts', 'LineStrips2D:strips')
    for k in (0, len(pose_msgs) // 2, len(pose_msgs) - 1):
        msg = pose_msgs[k]
        assert times[k] == stamp_ns(msg)
        assert len(strips[k]) == 10  # one outline per part
        for j in (0, 3, 9):
            pose = msg.ros_msg.poses[j]
            expected = transformed(scene.body(f'box_{j}').outlines[0], pose.position.x,
                                   pose.position.y, yaw(pose.orientation))
            np.testing.assert_allclose(np.array(strips[k][j]), expected, rtol=0, atol=1e-6)
        origins = temporal(ten_rrd, '/world/parts/origins', 'Points2D:positions')[1][k]
        np.testing.assert_allclose(
            origins, [(p.position.x, p.position.y) for p in msg.ros_msg.poses], atol=1e-6)
    track = static(ten_rrd, '/world/track', 'LineStrips2D:strips')
    np.testing.assert_allclose(track[0], transformed(scene.body('track').outlines[0], 0, 0, 0),
                               atol=1e-7)


def test_rotated_multi_piece_part_is_drawn_piece_by_piece(tmp_path):
    # An L-shaped part given as two convex pieces, at large angles of both signs.
    scene = scene_to_dict(load_scene('track_one_box'))
    pieces = [[[0, 0], [0.02, 0], [0.02, 0.005], [0, 0.005]],
              [[0, 0.005], [0.005, 0.005], [0.005, 0.02], [0, 0.02]]]
    del scene['bodies'][1]['polygon']
    scene['bodies'][1]['polygons'] = pieces
    path = tmp_path / 'l_part.mcap'
    poses = [(0.1, 0.05, 0.0), (0.2, 0.04, 0.7), (-0.3, 0.03, -2.5)]
    with McapRecorder(path, metadata={'scene': 'l_part', 'scene_json': json.dumps(scene)}) as rec:
        for k, (x, y, theta) in enumerate(poses, 1):
            rec.write_part_poses(k * 10_000_000, [[x, y]], [theta])
    rrd = replay(path, spawn=False)
    times, strips = temporal(rrd, '/world/parts', 'LineStrips2D:strips')
    assert times.tolist() == [10_000_000, 20_000_000, 30_000_000]
    for row, (x, y, theta) in zip(strips, poses):
        assert len(row) == 2
        for strip, piece in zip(row, pieces):
            np.testing.assert_allclose(np.array(strip), transformed(np.array(piece), x, y, theta),
                                       rtol=0, atol=1e-6)
    assert static(rrd, '/world/parts', 'LineStrips2D:labels') == ['box', 'box']
    colours = static(rrd, '/world/parts', 'LineStrips2D:colors')
    assert colours[0] == colours[1]
    assert static(rrd, '/__properties/replay', 'part_size_m')[0] == pytest.approx(
        math.hypot(0.02, 0.02))


def test_series_equal_the_track_state(ten_log, ten_rrd):
    states = messages(ten_log, TRACK)
    for j in (0, 7):
        name = states[0].ros_msg.name[j]
        t, position = temporal(ten_rrd, f'/plots/position/{name}', 'Scalars:scalars')
        t_speed, speed = temporal(ten_rrd, f'/plots/speed/{name}', 'Scalars:scalars')
        assert t.tolist() == t_speed.tolist() == [stamp_ns(m) for m in states]
        np.testing.assert_allclose(
            np.ravel(position), [1e3 * m.ros_msg.position[j] for m in states], rtol=1e-12)
        np.testing.assert_allclose(
            np.ravel(speed), [1e3 * m.ros_msg.velocity[j] for m in states], rtol=1e-12)


def test_contacts_and_impulse_arrows(ten_log, ten_rrd):
    clouds = [(stamp_ns(m), np.frombuffer(bytes(m.ros_msg.data), CONTACT_POINT_DTYPE))
              for m in messages(ten_log, CONTACTS)]
    t_points, points = temporal(ten_rrd, '/world/contacts/points', 'Points2D:positions')
    t_arrows, vectors = temporal(ten_rrd, '/world/contacts/impulses', 'Arrows2D:vectors')
    _, origins = temporal(ten_rrd, '/world/contacts/impulses', 'Arrows2D:origins')
    assert t_points.tolist() == t_arrows.tolist() == [t for t, _ in clouds]
    assert [len(p) for p in points] == [len(c) for _, c in clouds]
    assert sum(len(c) for _, c in clouds) > 0
    # scale rule: the 95th percentile impulse is drawn as 30 % of the part size (box diagonal)
    scale = static(ten_rrd, '/__properties/replay', 'impulse_arrow_m_per_Ns')[0]
    every = np.concatenate([c for _, c in clouds])
    magnitude = np.hypot(every['normal_impulse'], every['tangent_impulse'].astype(float))
    size = math.hypot(0.02, 0.01)
    assert scale * np.percentile(magnitude[magnitude > 0], 95) == pytest.approx(0.3 * size)
    assert static(ten_rrd, '/__properties/replay', 'part_size_m')[0] == pytest.approx(size)
    for k, (_, cloud) in enumerate(clouds):
        n = np.stack([cloud['normal_x'], cloud['normal_y']], 1).astype(float)
        t = np.stack([-n[:, 1], n[:, 0]], 1)  # the solvers' tangent, perp(n)
        impulse = (cloud['normal_impulse'][:, None] * n
                   + cloud['tangent_impulse'][:, None] * t)
        np.testing.assert_allclose(np.reshape(vectors[k], (-1, 2)), scale * impulse,
                                   rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(np.reshape(origins[k], (-1, 2)),
                                   np.stack([cloud['x'], cloud['y']], 1), atol=1e-7)
        np.testing.assert_allclose(np.reshape(points[k], (-1, 2)),
                                   np.stack([cloud['x'], cloud['y']], 1), atol=1e-7)


def test_vibration_command_is_a_step_series_to_the_end(ten_log, ten_rrd):
    t, amplitude = temporal(ten_rrd, '/plots/vibration/amplitude', 'Scalars:scalars')
    _, frequency = temporal(ten_rrd, '/plots/vibration/frequency', 'Scalars:scalars')
    end = stamp_ns(messages(ten_log, POSES)[-1])
    assert t.tolist() == [0, end]  # the t = 0 command, repeated at the end of the log
    np.testing.assert_allclose(np.ravel(amplitude), [350.0, 350.0])  # µm
    np.testing.assert_allclose(np.ravel(frequency), [50.0, 50.0])
    assert static(ten_rrd, '/plots/vibration/amplitude',
                  'SeriesLines:interpolation_mode') is not None


def test_fast_decoding_equals_mcap_ros2_decoding(ten_log):
    decoder = replay_module._Decoder()
    seen = set()
    for topic, _, data in read_messages(ten_log, replay_module._Decoder.TOPICS):
        seen.add(topic)
        fast, generic = decoder.fast(topic, data), decoder.generic(topic, data)
        if topic == CONTACTS:
            assert fast.tobytes() == generic.tobytes()
        elif topic == TRACK:
            assert fast[0] == generic[0]
            np.testing.assert_array_equal(fast[1], generic[1])
            np.testing.assert_array_equal(fast[2], generic[2])
        elif topic == POSES:
            np.testing.assert_array_equal(fast[0], generic[0])
            np.testing.assert_array_equal(fast[1], generic[1])
        else:
            np.testing.assert_array_equal(fast, generic)
    assert seen == set(replay_module._Decoder.TOPICS)


# --------------------------------------------------------------------------------------------
# Robustness


def test_same_log_same_recording_id(ten_log, ten_rrd, tmp_path):
    again = replay(ten_log, tmp_path / 'again.rrd', spawn=False)
    ids = [RrdReader(str(p)).recordings()[0].recording_id for p in (ten_rrd, again)]
    assert ids[0] == ids[1]


def test_truncated_log_converts_what_it_holds(chunked_log, tmp_path, caplog):
    data = chunked_log.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:len(data) // 2])
    full = replay(chunked_log, tmp_path / 'full.rrd', spawn=False)
    assert not [r for r in caplog.records if 'without its footer' in r.getMessage()]
    part = replay(cut, spawn=False)
    assert part == tmp_path / 'cut.rrd'
    # the user is told the log is cut short, and how much of it is replayed
    said = [r.getMessage() for r in caplog.records if 'without its footer' in r.getMessage()]
    assert len(said) == 1 and f'{cut}: the log ends without its footer' in said[0]
    n_full = len(temporal(full, '/world/parts', 'LineStrips2D:strips')[0])
    t_part, strips = temporal(part, '/world/parts', 'LineStrips2D:strips')
    # log times count from the run's wall-clock start (in the metadata, early in the file)
    with open(chunked_log, 'rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}['feeder_sim']
    origin = int(meta['log_time_origin_ns'])
    readable = [t - origin for topic, t, _ in read_messages(cut) if topic == TOPIC_PART_POSES]
    assert n_full == 40
    assert 0 < len(strips) < n_full
    assert f'replaying the {len(strips)} frames up to its last whole record' in said[0]
    assert t_part.tolist() == readable
    assert RrdReader(str(part)).recordings()[0].recording_id != \
        RrdReader(str(full)).recordings()[0].recording_id


def test_foreign_log_without_scene_draws_part_origins(tmp_path):
    # As a ROS tool writes it: no feeder_sim metadata, an extra topic of an unknown type.
    path = tmp_path / 'foreign.mcap'
    with open(path, 'wb') as stream:
        writer = Ros2Writer(stream)
        schemas = {name: writer.register_msgdef(name, msgdefs.definition(name)) for name in (
            'geometry_msgs/msg/PoseArray', 'sensor_msgs/msg/JointState')}
        log_schema = writer.register_msgdef('rcl_interfaces/msg/Note', 'string text\n')
        for k in range(1, 6):
            t = k * 10_000_000
            header = {'stamp': {'sec': 0, 'nanosec': t}, 'frame_id': 'world'}
            poses = [{'position': {'x': 0.01 * k + i, 'y': 0.5, 'z': 0.0},
                      'orientation': {'x': 0.0, 'y': 0.0, 'z': 0.0, 'w': 1.0}}
                     for i in range(2)]
            writer.write_message(POSES, schemas['geometry_msgs/msg/PoseArray'],
                                 {'header': header, 'poses': poses}, log_time=t)
            writer.write_message(TRACK, schemas['sensor_msgs/msg/JointState'],
                                 {'header': header, 'name': ['a', 'b'],
                                  'position': [0.01 * k, 1.0], 'velocity': [],
                                  'effort': []}, log_time=t)
            writer.write_message('/rosout', log_schema, {'text': f'frame {k}'}, log_time=t)
        writer.finish()
    rrd = replay(path, spawn=False)
    components = {}
    for chunk in chunks(rrd):
        components.setdefault(chunk.entity_path, set()).update(
            chunk.to_record_batch().schema.names)
    assert '/world/track' not in components
    assert 'LineStrips2D:strips' not in components['/world/parts']
    times, positions = temporal(rrd, '/world/parts', 'Points2D:positions')
    assert times.tolist() == [k * 10_000_000 for k in range(1, 6)]
    np.testing.assert_allclose(positions[2], [(0.03, 0.5), (1.03, 0.5)], atol=1e-6)
    assert static(rrd, '/world/parts', 'Points2D:labels') == ['a', 'b']
    _, position = temporal(rrd, '/plots/position/a', 'Scalars:scalars')
    np.testing.assert_allclose(np.ravel(position), [10.0 * k for k in range(1, 6)])
    _, speed = temporal(rrd, '/plots/speed/b', 'Scalars:scalars')
    assert np.isnan(np.ravel(speed)).all()  # JointState without velocities


def test_log_without_contacts_or_parts_still_converts(tmp_path):
    path = tmp_path / 'empty.mcap'
    McapRecorder(path).close()
    rrd = replay(path, spawn=False)
    assert RrdReader(str(rrd)).recordings()[0].application_id == 'feeder_sim'


@pytest.mark.parametrize('content, message', [
    (b'not an mcap file at all\n', 'is not an MCAP file'),
    (b'', 'is empty'),
])
def test_not_an_mcap_is_a_clear_error(tmp_path, capsys, content, message):
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(content)
    with pytest.raises(ValueError, match=message) as err:
        replay(bad, spawn=False)
    assert str(bad) in str(err.value) and '\n' not in str(err.value)
    assert main(['-q', 'replay', str(bad), '--no-viewer']) == 2
    assert f'feeder-sim: error: {bad}' in capsys.readouterr().err
    assert not (tmp_path / 'bad.rrd').exists()


def test_missing_file_is_an_os_error(tmp_path, capsys):
    missing = tmp_path / 'missing.mcap'
    with pytest.raises(OSError, match='missing.mcap'):
        replay(missing, spawn=False)
    assert main(['replay', str(missing)]) == 2
    assert 'feeder-sim: error:' in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# CLI and viewer


def test_cli_replay_writes_the_recording(chunked_log, tmp_path, capsys):
    out = tmp_path / 'sub' / 'out.rrd'
    assert main(['-q', 'replay', str(chunked_log), '--rrd', str(out), '--no-viewer']) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and f'rerun {out}' in printed
    assert len(temporal(out, '/world/parts', 'LineStrips2D:strips')[0]) == 40


@pytest.mark.parametrize('spawn, env, opened', [
    (None, {}, False),
    (None, {'DISPLAY': ':0'}, True),
    (None, {'WAYLAND_DISPLAY': 'wayland-0'}, True),
    (False, {'DISPLAY': ':0'}, False),
    (True, {}, True),
])
def test_viewer_is_opened_only_when_asked_or_displayable(chunked_log, tmp_path, monkeypatch,
                                                         spawn, env, opened):
    # Record instead of starting a viewer; the .rrd is written in every case.
    calls = []
    monkeypatch.setattr(replay_module, '_open_viewer', calls.append)
    monkeypatch.delenv('DISPLAY', raising=False)
    monkeypatch.delenv('WAYLAND_DISPLAY', raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    rrd = replay(chunked_log, tmp_path / 'v.rrd', spawn=spawn)
    assert rrd.stat().st_size > 0
    assert calls == ([rrd] if opened else [])


def test_rerun_reads_the_raw_log_with_its_own_ros2_decoders(ten_log, tmp_path):
    # `rerun LOG.mcap` without feeder_sim: contacts become points, track state and commands
    # become plotted scalars.
    rrd = tmp_path / 'raw.rrd'
    rerun = Path(sys.executable).with_name('rerun')
    subprocess.run([str(rerun), 'mcap', 'convert', str(ten_log), '-o', str(rrd),
                    '--timeline-type', 'duration'], check=True, capture_output=True, timeout=120)
    components: dict[str, set] = {}
    for chunk in chunks(rrd):
        components.setdefault(chunk.entity_path, set()).update(
            chunk.to_record_batch().schema.names)
    flat = {(e, c) for e, cs in components.items() for c in cs}
    assert any(e.startswith('/feeder_sim/contacts') and 'Points3D:positions' in c
               for e, c in flat)
    assert any(e.startswith('/feeder_sim/track_state') and 'Scalars:scalars' in c
               for e, c in flat)
    assert any(e.startswith('/vibration_cmd') and 'Scalars:scalars' in c for e, c in flat)


def test_parts_that_come_and_go_are_drawn_with_their_own_outlines(tmp_path):
    # a fed track: boxes added every 0.5 s and taken away 0.15 m on; each frame draws the
    # parts of that frame, named as track_state names them, each at its recorded pose
    log = tmp_path / 'fed.mcap'
    run(Simulator(str(DATA / 'fed_track.yaml')), 3.0, record=log)
    rrd = replay(log, tmp_path / 'fed.rrd', spawn=False)
    names = {stamp_ns(m): list(m.ros_msg.name)
             for m in read_ros2_messages(log, topics=['/feeder_sim/track_state'])}
    poses = {stamp_ns(m): m.ros_msg
             for m in read_ros2_messages(log, topics=['/feeder_sim/part_poses'])}
    t, labels = temporal(rrd, '/world/parts', 'LineStrips2D:labels')
    _, strips = temporal(rrd, '/world/parts', 'LineStrips2D:strips')
    assert len(t) == len(poses) and len({len(x) for x in labels}) >= 3     # 2 to 5 parts
    half_w, half_h = 0.01, 0.005
    for ti, label, strip in zip(t, labels, strips):
        assert label == names[int(ti)]
        pose = poses[int(ti)].poses[-1]
        yaw = 2 * math.atan2(pose.orientation.z, pose.orientation.w)
        c, s = math.cos(yaw), math.sin(yaw)
        corner = [pose.position.x + c * -half_w - s * -half_h,
                  pose.position.y + s * -half_w + c * -half_h]
        assert strip[-1][0] == pytest.approx(corner, abs=1e-6)      # f32 in the recording


def test_sensors_are_plotted_and_each_passing_part_is_a_line(tmp_path):
    # the sensor_slide scene: a beam at x = 0.05 m and a camera at 0.1 m; the replay plots
    # each count and the beam's state at the frames' simulated times and writes one line per
    # part that passes the camera
    log = tmp_path / 'slide.mcap'
    run(Simulator(str(DATA / 'sensor_slide.yaml')), 2.0, record=log)
    rrd = replay(log, tmp_path / 'slide.rrd', spawn=False)
    counts = [m.ros_msg.data for m in messages(log, '/feeder_sim/sensors/beam/count')]
    t, values = temporal(rrd, '/plots/sensors/beam/count', 'Scalars:scalars')
    assert [v[0] for v in values] == counts and counts[-1] == 2
    assert t.tolist() == [k * 10_000_000 for k in range(1, 201)]     # simulated time
    _, blocked = temporal(rrd, '/plots/sensors/beam/blocked', 'Scalars:scalars')
    assert sum(v[0] for v in blocked) == 32                          # 21 + 11 frames
    t, lines = temporal(rrd, '/sensors/camera/passed', 'TextLog:text')
    assert [x[0] for x in lines] == ['flat_box: flat', 'upright_box: upright']
    assert t.tolist() == [1_010_000_000, 1_510_000_000]
