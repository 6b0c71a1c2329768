"""feeder-sim run: the MCAP it writes, read back by mcap-ros2-support, the summary, errors."""

import json
import math
import os
import signal
import subprocess
import sys
import time

from mcap_ros2.reader import read_ros2_messages
import numpy as np
import pytest

from feeder_sim.cli import main
from feeder_sim.simulator import Simulator


def test_run_writes_mcap_summary_and_plot(tmp_path):
    mcap = tmp_path / 'run.mcap'
    summary = tmp_path / 'run.json'
    rc = main(['-q', 'run', 'track_one_box', '--duration', '0.2', '--record', str(mcap),
               '--summary', str(summary), '--publish-rate', '50'])
    assert rc == 0
    assert (tmp_path / 'run.png').stat().st_size > 1000
    msgs = {}
    for m in read_ros2_messages(str(mcap)):
        msgs.setdefault(m.channel.topic, []).append(m)
    assert {t: len(v) for t, v in msgs.items()} == {
        '/clock': 10, '/feeder_sim/part_poses': 10, '/feeder_sim/contacts': 10,
        '/feeder_sim/track_state': 10, '/vibration_cmd': 1, '/tf': 10,
        '/feeder_sim/geometry': 1, '/feeder_sim/part_impulses': 10}
    stamps = [m.ros_msg.header.stamp for m in msgs['/feeder_sim/part_poses']]
    assert [s.sec * 10**9 + s.nanosec for s in stamps] == [20_000_000 * k for k in range(1, 11)]
    assert list(msgs['/vibration_cmd'][0].ros_msg.data) == pytest.approx([3.5e-4, 50.0])
    # the recorded pose equals, bit for bit, what the simulator computes on the same schedule
    sim = Simulator('track_one_box')
    for k in range(1, 11):
        sim.advance(0.02 * k)
    _, origin, angle = sim.part_poses()
    last = msgs['/feeder_sim/part_poses'][-1].ros_msg.poses[0]
    assert last.position.x == origin[0, 0] and last.position.y == origin[0, 1]
    assert 2 * math.atan2(last.orientation.z, last.orientation.w) == pytest.approx(angle[0],
                                                                                abs=1e-15)
    data = json.loads(summary.read_text())
    assert data['scene'] == 'track_one_box' and data['method'] == 'event_driven'
    s_end = sim.track_coordinates()[0][0]
    s0 = Simulator('track_one_box').track_coordinates()[0][0]
    assert data['parts'][0]['mean_velocity_along_track_mps'] == pytest.approx(
        (s_end - s0) / 0.2, rel=1e-12)
    assert sim.stats.events > 0 and data['solver']['events'] == sim.stats.events
    assert data['solver']['fallbacks'] == 0


def test_contacts_carry_the_weight(tmp_path):
    # A box resting on a static floor: over each 10 ms frame the normal impulses sum to m g dt.
    mcap = tmp_path / 'rest.mcap'
    scene = tmp_path / 'rest.yaml'
    scene.write_text("""
name: rest
solver: {method: event_driven}
bodies:
  - {name: floor, type: static, polygon: [[-1, -0.1], [1, -0.1], [1, 0], [-1, 0]],
     pose: [0, 0, 0], mu_static: 0.5}
  - {name: box, type: dynamic, polygon: [[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005],
     [-0.01, 0.005]], mass: 0.01, pose: [0, 0.005, 0], mu_static: 0.5}
""")
    assert main(['-q', 'run', str(scene), '--duration', '0.05', '--record', str(mcap)]) == 0
    frames = [m.ros_msg for m in read_ros2_messages(str(mcap), topics=['/feeder_sim/contacts'])]
    assert len(frames) == 5
    for cloud in frames:
        fields = [f.name for f in cloud.fields]
        assert fields[:7] == ['x', 'y', 'z', 'normal_x', 'normal_y', 'normal_impulse',
                              'tangent_impulse']
        pts = np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(cloud.width, -1)
        assert cloud.width == 2
        assert pts[:, 5].sum() == pytest.approx(0.01 * 9.81 * 0.01, rel=1e-6)
        assert np.allclose(pts[:, 6], 0.0, atol=1e-12)


@pytest.mark.parametrize('args, message', [
    (['run', 'no_such_scene', '--duration', '1'], 'no_such_scene'),
    (['run', 'track_one_box', '--duration', '-1'], 'duration'),
    (['run', 'track_one_box', '--duration', '0.01', '--publish-rate', 'nan'], 'publish rate'),
    (['accuracy', '--cases', 'incline'], 'choose from incline_slide'),
    (['accuracy', '--methods', 'box2d'], 'unknown method(s) box2d; choose from'),
    (['stability', '--cases', 'cradle'], 'choose from stack_mass_ratio_1e2'),
    (['stability', '--methods', 'verlet'], 'unknown method(s) verlet; choose from'),
    # options are checked as the scene keys they override, and bounded so a run ends
    (['run', 'track_one_box', '--duration', '1', '--time-step', '0'],
     'solver.time_step: 0 is out of range'),
    (['run', 'track_one_box', '--duration', '1', '--time-step=-1e-3'], 'solver.time_step'),
    (['run', 'track_one_box', '--duration', '1', '--time-step', '1e-300'],
     'in [1e-07, 0.1]'),
    (['run', 'track_one_box', '--duration', '1', '--tolerance', '0'], 'solver.tolerance'),
    (['run', 'track_one_box', '--duration', '1e300'], 'more than 1e+12 steps'),
    (['run', 'track_one_box', '--duration', 'inf'], 'duration must be a positive number'),
    (['run', 'track_one_box', '--duration', '1', '--publish-rate', '1e9'],
     'publish rate must be a number of Hz in (0, 100000]'),
    # output files are checked before the run, each naming its option
    (['run', 'track_one_box', '--duration', '1', '--summary', '{tmp}'],
     '--summary {tmp}: is a directory; give a file name in it'),
    (['run', 'track_one_box', '--duration', '1', '--plot', '{tmp}/p.notanimage'],
     '--plot {tmp}/p.notanimage: expected a file name ending in one of .'),
    (['run', 'track_one_box', '--duration', '1', '--record', '{tmp}/f/x.mcap'],
     '--record {tmp}/f/x.mcap: {tmp}/f is a file, not a directory'),
    # argparse's own errors, without the usage block it prints before them
    (['run', 'track_one_box', '--duration', 'abc'],
     "feeder-sim run: error: argument --duration: invalid float value: 'abc' "
     '(see feeder-sim run -h)'),
    (['frobnicate'], "argument verb: invalid choice: 'frobnicate'"),
])
def test_bad_input_is_one_clear_line(args, message, tmp_path):
    (tmp_path / 'f').write_text('')
    args = [a.replace('{tmp}', str(tmp_path)) for a in args]
    message = message.replace('{tmp}', str(tmp_path))
    proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert 'Traceback' not in proc.stderr
    assert message in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


@pytest.mark.parametrize('duration', [0.004, 0.0123, 0.01])
def test_the_run_simulates_exactly_the_duration_asked(tmp_path, duration):
    # frames every 10 ms: a duration that is not a whole number of frames ends on a shorter one
    from feeder_sim.run import run
    sim = Simulator('track_one_box')
    result = run(sim, duration, publish_rate_hz=100.0)
    assert sim.t == pytest.approx(duration, abs=1e-12)
    assert result.trajectory.t[-1] == pytest.approx(duration, abs=1e-12)
    assert result.summary['simulated_s'] == pytest.approx(sim.t, abs=1e-12)


@pytest.mark.parametrize('method', ['event_driven', 'time_stepping'])
def test_two_runs_give_identical_logs(tmp_path, method):
    # --log-time sim: by default log times start at the run's wall-clock second
    paths = [tmp_path / f'{k}.mcap' for k in range(2)]
    for path in paths:
        assert main(['-q', 'run', 'track_one_box', '--duration', '0.05', '--method', method,
                     '--time-step', '1e-4', '--record', str(path), '--log-time', 'sim']) == 0
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_accuracy_and_stability_verbs(tmp_path, capsys):
    assert main(['-q', 'accuracy', '--list']) == 0
    assert 'conveying_16hz_3deg_hopping' in capsys.readouterr().out
    # one exact case, both ends of the event-driven sweep: within its stated tolerance
    assert main(['-q', 'accuracy', '--cases', 'free_flight', '--methods', 'event_driven',
                 '--quick', '--out', str(tmp_path / 'acc')]) == 0
    rows = json.loads((tmp_path / 'acc' / 'accuracy.json').read_text())['rows']
    assert len(rows) == 2 and all(r['error'] < 1e-12 for r in rows)
    assert main(['-q', 'stability', '--cases', 'restitution_1', '--methods', 'event_driven',
                 '--out', str(tmp_path / 'stab')]) == 0
    cell = json.loads((tmp_path / 'stab' / 'stability.json').read_text())['cells'][0]
    assert cell['status'] == 'PASS'


def test_advance_to_is_a_time_and_advance_by_a_duration():
    sim = Simulator('track_one_box')
    sim.advance_to(0.05)
    assert sim.t == pytest.approx(0.05, abs=1e-12)
    sim.advance_to(0.05)                  # already there: nothing happens
    sim.advance_to(0.01)                  # in the past: nothing happens
    assert sim.t == pytest.approx(0.05, abs=1e-12)
    sim.advance_by(0.02)
    sim.advance_by(0.02)
    assert sim.t == pytest.approx(0.09, abs=1e-12)
    # the state of stops at the same times (to the round-off of 0.05 + 0.02)
    other = Simulator('track_one_box')
    for t in (0.05, 0.07, 0.09):
        other.advance(t)                  # the first name of advance_to still works
    np.testing.assert_allclose(sim.state.position, other.state.position, rtol=0, atol=1e-12)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='duration must be a positive number'):
            sim.advance_by(bad)


def test_switching_to_time_stepping_takes_a_step_fit_for_it():
    # track_one_box is an event_driven scene: its 1 ms is that method's largest step, 20 per
    # period of the 50 Hz drive; time stepping there conveys ~19 % slow
    ed = Simulator('track_one_box')
    ts = Simulator('track_one_box', method='time_stepping')
    assert ts.scene.solver.time_step == pytest.approx(1.0 / (400 * 50.0))
    chosen = Simulator('track_one_box', method='time_stepping', time_step=1e-4)
    assert chosen.scene.solver.time_step == 1e-4                # a given step is kept
    for sim in (ed, ts):
        sim.advance_to(0.5)
    s0 = [sim.track_coordinates()[0][0] for sim in (ed, ts)]
    for sim in (ed, ts):
        sim.advance_to(1.0)
    speed = [(sim.track_coordinates()[0][0] - a) / 0.5 for sim, a in zip((ed, ts), s0)]
    assert speed[1] == pytest.approx(speed[0], rel=0.03)        # first order: ~2 % at 400


@pytest.mark.parametrize('log_time', ['wall', 'sim'])
def test_log_times_start_at_the_run_or_at_zero(tmp_path, log_time):
    # 'wall' (the default): log time = the run's wall-clock start (a whole second, in the
    # metadata) + simulated time, so viewers show dates; 'sim': simulated time alone
    import time

    from mcap.reader import make_reader
    from mcap_ros2.reader import read_ros2_messages
    log = tmp_path / 'run.mcap'
    before = time.time_ns()
    args = ['run', 'track_one_box', '--duration', '0.05', '--record', str(log)]
    assert main(args + ([] if log_time == 'wall' else ['--log-time', 'sim'])) == 0
    with open(log, 'rb') as f:
        origin = int({m.name: m.metadata for m in make_reader(f).iter_metadata()}
                     ['feeder_sim']['log_time_origin_ns'])
    if log_time == 'wall':
        assert before - 10**9 < origin <= time.time_ns() and origin % 10**9 == 0
    else:
        assert origin == 0
    poses = list(read_ros2_messages(str(log), topics=['/feeder_sim/part_poses']))
    stamps = [m.ros_msg.header.stamp.sec * 10**9 + m.ros_msg.header.stamp.nanosec
              for m in poses]
    assert stamps == [k * 10_000_000 for k in range(1, 6)]
    assert [m.log_time_ns for m in poses] == [origin + s for s in stamps]


@pytest.mark.timeout(300)
@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_a_stop_signal_ends_the_run_with_its_files_whole(tmp_path, sig):
    """SIGTERM or SIGINT in the middle of a run: the run ends after the frame under way, the
    MCAP is finalized (an independent reader reads every frame whole), the summary covers
    the time simulated and says why, one line says so, exit status 128 + the signal."""
    log, summary = tmp_path / 'run.mcap', tmp_path / 'run.json'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'feeder_sim.cli', 'run', 'track_one_box', '--duration', '1e4',
         '--record', str(log), '--summary', str(summary)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # a run started in the background of a script would inherit SIGINT ignored
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        # until frames are being written (kernels loaded, compiled on a cold cache)
        deadline = time.monotonic() + 240
        while (not log.exists() or log.stat().st_size < 200_000) and \
                time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        proc.send_signal(sig)
        sent = time.monotonic()
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    assert proc.returncode == 128 + sig, err
    assert 'Traceback' not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f'feeder-sim: stopped by {sig.name} after '), err
    assert took < 5.0, took        # a frame, the summary and the plot: well under a second
    data = json.loads(summary.read_text())
    assert data['stopped'] == {'reason': sig.name, 'planned_s': 1e4}
    frames = {}
    from mcap.reader import make_reader
    with open(log, 'rb') as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None           # finalized: summary section
        for _, channel, _ in reader.iter_messages():
            frames[channel.topic] = frames.get(channel.topic, 0) + 1
    n = round(data['simulated_s'] * 100)                  # 100 frames per simulated second
    assert n > 10
    for topic in ('/clock', '/feeder_sim/part_poses', '/feeder_sim/contacts'):
        assert frames[topic] == n, (topic, frames)


@pytest.mark.timeout(300)
def test_a_stop_signal_while_compiling_ends_the_run_at_once(tmp_path):
    """Before the first frame (here: compiling on a cold cache, native code that holds
    Python's signal handlers off for up to a minute) nothing is written: the process ends at
    once with one line and leaves no log behind."""
    err_path = tmp_path / 'err.txt'
    env = {**os.environ, 'FEEDER_SIM_CACHE_DIR': str(tmp_path / 'cache')}
    with open(err_path, 'w') as err:
        proc = subprocess.Popen(
            [sys.executable, '-m', 'feeder_sim.cli', 'run', 'track_one_box', '--duration', '1',
             '--record', str(tmp_path / 'run.mcap')], stdout=subprocess.DEVNULL, stderr=err,
            env=env)
    try:
        deadline = time.monotonic() + 60
        while 'compiling numba kernels' not in err_path.read_text() and \
                time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        proc.wait(timeout=60)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    lines = err_path.read_text().strip().splitlines()
    assert proc.returncode == 128 + signal.SIGTERM, lines
    assert lines[-1] == 'feeder-sim: stopped by SIGTERM before the first frame; nothing written'
    assert took < 10.0, took
    assert not (tmp_path / 'run.mcap').exists()


def test_a_run_that_writes_nothing_says_so(tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'run', 'track_one_box',
                           '--duration', '0.02'], capture_output=True, text=True, cwd=tmp_path,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith('nothing written (add --record OUT.mcap')
    assert list(tmp_path.iterdir()) == []


def test_scenes_lists_each_shipped_scene_with_its_method_and_a_line_about_it():
    from feeder_sim.model.scene import load_scene, shipped_scenes

    proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'scenes'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    lines = proc.stdout.splitlines()
    assert [line.split()[0] for line in lines] == shipped_scenes()
    for line in lines:
        name, method, about = line.split(maxsplit=2)
        scene = load_scene(name)
        assert method == scene.solver.method and about == scene.description != ''


def test_a_description_must_be_text():
    from feeder_sim.model.scene import parse_scene, SceneError

    data = {'bodies': [{'name': 'floor', 'type': 'static',
                        'polygon': [[0, 0], [1, 0], [1, 1], [0, 1]], 'pose': [0, 0, 0]}],
            'description': 5}
    with pytest.raises(SceneError, match='description'):
        parse_scene(data)
