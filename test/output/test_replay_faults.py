"""feeder-sim replay on damaged, foreign and hostile input: refused in one line or replayed with
the loss named, never a traceback, a hang or a silent gap."""

import io
import json
import math
import os
from pathlib import Path
import random
import re
import stat
import time

from hypothesis import event, given, HealthCheck, settings
from hypothesis import strategies as st
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from feeder_sim.cli import main
from feeder_sim.model.scene import load_scene, MAX_FILE_BYTES, scene_to_dict
from feeder_sim.output.recording import McapRecorder, TOPIC_PART_POSES
from feeder_sim.output.replay import DamagedLogError, replay

ORIGIN_NS = 1_700_000_000_000_000_000   # a wall-clock start, as `feeder-sim run` logs
FRAMES = 40
STEP_NS = 5_000_000


@pytest.fixture(autouse=True, scope='module')
def strict_rerun():
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(False)


def write_log(path: Path, *, compression: str = 'zstd', chunk_size: int = 1024,
              frames: int = FRAMES, metadata: dict | None = None,
              records: dict | None = None) -> Path:
    """A feeder_sim log as the recorder writes it (one box on the track), without running
    the simulator: small chunks, so that damage hits one of many."""
    scene = load_scene('track_one_box')
    meta = {'scene': scene.name, 'method': 'event_driven', 'feeder_sim': '0',
            'scene_json': json.dumps(scene_to_dict(scene), separators=(',', ':')),
            'log_time_origin_ns': str(ORIGIN_NS)}
    meta.update(metadata or {})
    with McapRecorder(path, metadata=meta, compression=compression, chunk_size=chunk_size,
                      log_time_origin_ns=ORIGIN_NS) as rec:
        for name, values in (records or {}).items():
            rec.write_metadata(name, values)
        rec.write_vibration_cmd(0, 350e-6, 50.0)
        for k in range(1, frames + 1):
            t = k * STEP_NS
            x = 0.001 * k
            rec.write_part_poses(t, [[x, 0.005]], [0.01 * k])
            rec.write_track_state(t, ['box'], [x], [0.2])
            rec.write_contacts(t, [[x - 0.01, 0.0]], [[0.0, 1.0]], [1e-4], [2e-5], [1], [0])
    return path


def pose_times(rrd: Path) -> list[int]:
    times = []
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path == '/world/parts' and not chunk.is_static:
            batch = chunk.to_record_batch()
            if 'LineStrips2D:strips' in batch.schema.names:
                times += [int(v) for v in batch.column('sim_time').cast('int64').to_pylist()]
    return sorted(times)


def replay_cli(log: Path, rrd: Path, *extra: str, capsys) -> tuple[int, str]:
    code = main(['-q', 'replay', str(log), '--rrd', str(rrd), '--no-viewer', *extra])
    return code, capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# A chunk that fails its CRC


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_flipped_chunk_names_the_lost_frames_and_allow_damaged_replays_the_rest(
        tmp_path, capsys, caplog, compression):
    good = write_log(tmp_path / 'good.mcap', compression=compression)
    with open(good, 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.id: c.topic for c in summary.channels.values()}
        all_poses = [m.log_time - ORIGIN_NS for _, c, m in reader.iter_messages()
                     if c.topic == TOPIC_PART_POSES]
    assert len(summary.chunk_indexes) > 10 and len(all_poses) == FRAMES
    index = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    data = bytearray(good.read_bytes())
    record = bytes(data[index.chunk_start_offset + 9:
                        index.chunk_start_offset + index.chunk_length])
    lost = [m.log_time - ORIGIN_NS
            for m in breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(record))))
            if isinstance(m, Message) and channels[m.channel_id] == TOPIC_PART_POSES]
    assert lost  # the damaged chunk held frames
    middle = index.chunk_start_offset + index.chunk_length // 2
    data[middle:middle + 16] = bytes(b ^ 0xFF for b in data[middle:middle + 16])
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(bytes(data))

    rrd = tmp_path / 'bad.rrd'
    code, err = replay_cli(bad, rrd, capsys=capsys)
    assert code == 1 and not rrd.exists()
    start = (index.message_start_time - ORIGIN_NS) / 1e9
    end = (index.message_end_time - ORIGIN_NS) / 1e9
    expected = (f'frames from t={start:.3f} to t={end:.3f} s lost (chunk at byte '
                f'{index.chunk_start_offset}: ')
    said = [line for line in err.splitlines() if 'lost' in line]
    assert len(said) == 1 and expected in said[0], err
    if compression == 'none':
        assert said[0].endswith('CRC mismatch)')
    assert 'Traceback' not in err and '--allow-damaged' in err
    with pytest.raises(DamagedLogError):
        replay(bad, rrd, spawn=False)

    caplog.clear()
    code, err = replay_cli(bad, rrd, '--allow-damaged', capsys=capsys)
    assert code == 0 and expected in caplog.text  # the loss is still said, as a warning
    kept = pose_times(rrd)
    assert kept == sorted(set(all_poses) - set(lost))
    assert 0 < len(kept) < FRAMES


def test_damaged_record_header_in_a_cut_log_is_damage_not_the_cut(tmp_path, capsys, caplog):
    # no footer (a killed writer) and a chunk's length field damaged mid-file: the walk finds
    # the next chunk, names the frames between the good neighbours, and replays the rest
    good = write_log(tmp_path / 'good.mcap', compression='none')
    with open(good, 'rb') as f:
        reader = make_reader(f)
        chunks = reader.get_summary().chunk_indexes
        times = {m.log_time: k for k, (_, c, m) in enumerate(reader.iter_messages())
                 if c.topic == TOPIC_PART_POSES}
    k = len(chunks) // 2
    hit, last = chunks[k], chunks[-1]
    data = bytearray(good.read_bytes()[:last.chunk_start_offset + last.chunk_length // 2])
    data[hit.chunk_start_offset + 1:hit.chunk_start_offset + 9] = b'\xff' * 8
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(bytes(data))
    code, err = replay_cli(bad, tmp_path / 'bad.rrd', capsys=capsys)
    assert code == 1
    after = (chunks[k - 1].message_end_time - ORIGIN_NS) / 1e9
    before = (chunks[k + 1].message_start_time - ORIGIN_NS) / 1e9
    assert (f'frames after t={after:.3f} s and before t={before:.3f} s lost (record at byte '
            f'{hit.chunk_start_offset}: a record of') in err, err
    caplog.clear()
    code, err = replay_cli(bad, tmp_path / 'bad.rrd', '--allow-damaged', capsys=capsys)
    assert code == 0 and 'ends without its footer' in caplog.text
    kept = pose_times(tmp_path / 'bad.rrd')
    expected = [t - ORIGIN_NS for t in times
                if chunks[0].message_start_time <= t <= chunks[k - 1].message_end_time
                or chunks[k + 1].message_start_time <= t < last.message_start_time]
    assert set(expected) <= set(kept) and kept[-1] < last.message_end_time - ORIGIN_NS
    assert not [t for t in kept if after * 1e9 < t < before * 1e9]


def test_truncated_log_is_not_damaged(tmp_path, capsys, caplog):
    # a killed writer leaves no footer: what it wrote replays, exit 0, one warning
    good = write_log(tmp_path / 'good.mcap')
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(good.read_bytes()[:good.stat().st_size // 3])
    code, err = replay_cli(cut, tmp_path / 'cut.rrd', capsys=capsys)
    assert code == 0 and 'ends without its footer' in caplog.text
    assert 'lost' not in caplog.text + err
    assert 0 < len(pose_times(tmp_path / 'cut.rrd')) < FRAMES


# --------------------------------------------------------------------------------------------
# Not a feeder_sim log


def test_foreign_mcap_is_refused_naming_what_it_holds(tmp_path, capsys):
    path = tmp_path / 'other.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='another program')
        schema = writer.register_schema('lab_msgs/msg/Reading', 'ros2msg', b'float64 value\n')
        image = writer.register_schema('lab_msgs/msg/Frame', 'ros2msg', b'uint8[] data\n')
        temperature = writer.register_channel('/oven/temperature', 'cdr', schema)
        camera = writer.register_channel('/oven/camera', 'cdr', image)
        for k in range(5):
            writer.add_message(temperature, k * 1000, b'\x00\x01\x00\x00' + bytes(8), k * 1000)
            writer.add_message(camera, k * 1000, b'\x00\x01\x00\x00' + bytes(4), k * 1000)
        writer.add_metadata('calibration', {'gain': '2'})
        writer.finish()
    code, err = replay_cli(path, tmp_path / 'other.rrd', capsys=capsys)
    assert code == 2 and not (tmp_path / 'other.rrd').exists()
    (line,) = err.splitlines()
    assert 'not a feeder_sim log' in line
    assert '/oven/temperature (lab_msgs/msg/Reading)' in line
    assert '/oven/camera (lab_msgs/msg/Frame)' in line
    assert 'show nothing' in line and f'rerun {path}' in line


# --------------------------------------------------------------------------------------------
# Metadata


@pytest.mark.parametrize('metadata, episode, field', [
    ({'log_time_origin_ns': 'abc'}, None, "metadata 'log_time_origin_ns': expected an integer"),
    ({'log_time_origin_ns': '-5'}, None, "metadata 'log_time_origin_ns': expected an integer"),
    ({'log_time_origin_ns': '9' * 30}, None, "metadata 'log_time_origin_ns'"),
    ({}, {'index': '1', 'log_time_ns': '1e9'}, "metadata 'episode_1.log_time_ns'"),
    ({}, {'index': '1'}, "metadata 'episode_1.log_time_ns'"),
    ({'method': 'x' * 5000}, None, "metadata 'method': expected a name"),
])
def test_bad_metadata_is_one_line_naming_the_field(tmp_path, capsys, metadata, episode,
                                                   field):
    path = write_log(tmp_path / 'meta.mcap', frames=3, metadata=metadata,
                     records=None if episode is None else {'episode_1': episode})
    code, err = replay_cli(path, tmp_path / 'meta.rrd', capsys=capsys)
    assert code == 2 and not (tmp_path / 'meta.rrd').exists()
    (line,) = err.splitlines()
    assert field in line and str(path) in line and len(line) < 400


def circle(k: int, n: int) -> list:
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    r = 0.01 + 1e-4 * k
    return np.round(np.stack([r * np.cos(a), r * np.sin(a)], 1), 6).tolist()


def hostile_scene(kind: str) -> str:
    scene = scene_to_dict(load_scene('track_one_box'))
    if kind == 'over_2_MiB':
        return json.dumps(scene) + ' ' * MAX_FILE_BYTES     # whitespace is valid JSON
    if kind == 'deeply_nested':
        return '[' * 1_000_000 + ']' * 1_000_000     # within the size limit
    # within the size limit: many distinct outlines of 1000 vertices, about a minute of the
    # scene parser's outline checks
    for k in range(60):
        scene['bodies'].append(dict(scene['bodies'][1], name=f'ring_{k}',
                                    polygon=circle(k, 1000), pose=[0.05 * k - 0.45, 0.05, 0.0]))
    return json.dumps(scene, separators=(',', ':'))


@pytest.mark.parametrize('kind', ['over_2_MiB', 'many_large_outlines', 'deeply_nested'])
def test_hostile_scene_json_is_refused_fast(tmp_path, caplog, kind):
    text = hostile_scene(kind)
    assert len(text) > 1_000_000
    path = write_log(tmp_path / 'hostile.mcap', frames=5, metadata={'scene_json': text})
    t0 = time.perf_counter()
    rrd = replay(path, tmp_path / 'hostile.rrd', spawn=False)
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0, f'{kind}: {elapsed:.2f} s'
    said = [r.getMessage() for r in caplog.records if 'ignoring the scene' in r.getMessage()]
    assert len(said) == 1 and '\n' not in said[0]
    if kind == 'over_2_MiB':
        assert 'limited to 2 MiB' in said[0]
    # the frames are there, drawn as origins
    components = set()
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path == '/world/parts':
            components.update(chunk.to_record_batch().schema.names)
    assert 'Points2D:positions' in components and 'LineStrips2D:strips' not in components


# --------------------------------------------------------------------------------------------
# The output


@pytest.mark.timeout(60)
@pytest.mark.parametrize('kind', ['fifo', 'directory'])
def test_rrd_that_is_not_a_regular_file_is_refused_untouched(tmp_path, capsys, kind):
    log = write_log(tmp_path / 'log.mcap', frames=3)
    out = tmp_path / 'out.rrd'
    if kind == 'fifo':
        os.mkfifo(out)
    else:
        out.mkdir()
    code, err = replay_cli(log, out, capsys=capsys)
    assert code == 2
    (line,) = err.splitlines()
    assert str(out) in line and ('is a FIFO' if kind == 'fifo' else 'is a directory') in line
    mode = out.stat().st_mode
    assert stat.S_ISFIFO(mode) if kind == 'fifo' else stat.S_ISDIR(mode)
    assert not list(tmp_path.glob('out.rrd.part'))
    if kind == 'fifo':
        with pytest.raises(ValueError, match='is a FIFO'):
            replay(log, out, spawn=False)


# --------------------------------------------------------------------------------------------
# Random damage


@pytest.fixture(scope='module')
def small_log(tmp_path_factory) -> bytes:
    folder = tmp_path_factory.mktemp('small')
    return write_log(folder / 'small.mcap', frames=12, chunk_size=512).read_bytes()


@pytest.fixture(scope='module')
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp('damaged')


# Positions come from a seed, uniform over the file: drawn directly, hypothesis would favour
# the first bytes (the magic) and test little else.
damage = st.tuples(st.integers(0, 16), st.booleans(), st.booleans(), st.integers(0, 2 ** 32 - 1))


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(damage=damage)
def test_random_flips_and_cuts_end_in_a_clear_outcome(small_log, scratch, capsys, caplog,
                                                      damage):
    flips, cut, allow, seed = damage
    rng = random.Random(seed)
    data = bytearray(small_log)
    for _ in range(flips):
        data[rng.randrange(len(data))] ^= rng.randrange(1, 256)
    if cut:
        data = data[:rng.randrange(len(data))]
    path = scratch / 'log.mcap'
    path.write_bytes(bytes(data))
    rrd = scratch / 'log.rrd'
    rrd.unlink(missing_ok=True)
    caplog.clear()
    t0 = time.perf_counter()
    code = main(['-q', 'replay', str(path), '--rrd', str(rrd), '--no-viewer',
                 *(['--allow-damaged'] if allow else [])])
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert code in (0, 1, 2), err
    assert 'Traceback' not in err and elapsed < 5.0
    if code == 0:
        lost = bool(re.search(r'lost \(', caplog.text))
        event('replayed with damage reported' if lost else 'replayed')
        assert rrd.is_file()
    elif code == 1:
        assert not allow
        event('damage reported, nothing written')
        assert re.search(r'lost \(', err) and not rrd.exists()
    else:
        event('refused: ' + err.split(': ', 3)[-1].split(' (')[0][:40])
        assert err.startswith('feeder-sim: error: ') and not rrd.exists()
