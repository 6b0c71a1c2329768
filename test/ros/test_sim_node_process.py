"""The installed node as ROS users run it: colcon workspace, `ros2 run` lookup, signals, logs.

The package is built with colcon (from PyPI) into a temporary workspace; the executable is
found the way `ros2 run feeder_sim sim_node` finds it (ament index -> <prefix>/lib/<package>);
the environment is the one `install/setup.bash` gives. Logs are read back with mcap and
mcap-ros2-support only, not with feeder_sim's own reader.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.reader import read_ros2_messages
import numpy as np
from paths import REPO
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.timeout(300)

VENV_BIN = Path(sys.executable).parent


@pytest.fixture(scope='module')
def workspace(tmp_path_factory) -> dict:
    """colcon-built install of this package; returns the sourced environment and prefix."""
    ws = tmp_path_factory.mktemp('ws')
    env = dict(os.environ, PATH=f'{VENV_BIN}{os.pathsep}{os.environ["PATH"]}')
    build = subprocess.run(
        [str(VENV_BIN / 'colcon'), '--log-base', str(ws / 'log'), 'build',
         '--base-paths', str(REPO), '--build-base', str(ws / 'build'),
         '--install-base', str(ws / 'install')],
        cwd=ws, env=env, capture_output=True, text=True, timeout=240)
    assert build.returncode == 0, build.stdout + build.stderr
    sourced = subprocess.run(
        ['bash', '-c', f'. {ws}/install/setup.bash && env -0'], env=env,
        capture_output=True, check=True, timeout=60).stdout.decode()
    env = dict(line.split('=', 1) for line in sourced.split('\0') if '=' in line)
    # The installed copy compiles its numba kernels into its own cache on first use (a minute
    # or more on a cold machine); do that once here so that the tests time the node itself.
    warm = subprocess.run(
        [str(ws / 'install' / 'feeder_sim' / 'lib' / 'feeder_sim' / 'sim_node'), '--ros-args',
         '-p', 'duration:=0.5', '-p', 'real_time_factor:=0.0'],
        env=env, capture_output=True, text=True, timeout=900)
    assert warm.returncode == 0, warm.stderr
    return {'env': env, 'install': ws / 'install'}


@pytest.fixture
def processes():
    """Started nodes; any still running when the test ends (it failed) is killed."""
    started: list[subprocess.Popen] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)


def ros2_run_path(env: dict, package: str, executable: str) -> Path:
    """What `ros2 run` resolves: the package prefix from the ament index, then lib/<package>."""
    prefix = subprocess.run(
        [sys.executable, '-c', 'import sys; from ament_index_python.packages import '
         'get_package_prefix as p; print(p(sys.argv[1]))', package],
        env=env, capture_output=True, text=True, check=True).stdout.strip()
    matches = []
    for root, dirs, files in os.walk(Path(prefix) / 'lib' / package):
        dirs[:] = [d for d in dirs if not d.startswith('.')]
        matches += [Path(root) / f for f in files
                    if f == executable and os.access(Path(root) / f, os.X_OK)]
    assert len(matches) == 1, matches
    return matches[0]


def start_node(workspace, processes: list, *ros_args: str) -> subprocess.Popen:
    exe = ros2_run_path(workspace['env'], 'feeder_sim', 'sim_node')
    proc = subprocess.Popen([str(exe), '--ros-args', *ros_args], env=workspace['env'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    processes.append(proc)
    return proc


def wait_for_messages(path: Path, proc: subprocess.Popen, min_bytes: int = 20_000) -> None:
    end = time.monotonic() + 60
    while not (path.exists() and path.stat().st_size > min_bytes):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < end, 'the node wrote no chunk within 60 s'
        time.sleep(0.1)


def test_colcon_installs_where_ros2_run_and_the_ament_index_look(workspace):
    install = workspace['install']
    exe = ros2_run_path(workspace['env'], 'feeder_sim', 'sim_node')
    assert exe == install / 'feeder_sim' / 'lib' / 'feeder_sim' / 'sim_node'
    share = install / 'feeder_sim' / 'share'
    assert (share / 'ament_index' / 'resource_index' / 'packages' / 'feeder_sim').is_file()
    assert (share / 'feeder_sim' / 'package.xml').is_file()
    assert (share / 'feeder_sim' / 'config' / 'track_one_box.yaml').is_file()
    assert (share / 'feeder_sim' / 'config' / 'sim_node.params.yaml').is_file()
    # the first compile's plans travel with the package
    plans = install.glob('feeder_sim/lib/python*/site-packages/feeder_sim/compiled/plans/*')
    assert sorted(p.name for p in plans) == ['event_driven.json']


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_exits_0_with_a_finalized_log(workspace, tmp_path, sig, processes):
    log = tmp_path / 'run.mcap'
    proc = start_node(workspace, processes, '-p', f'record_path:={log}',
                      '-p', 'real_time_factor:=0.0', '-p', 'record_flush_period:=0.1')
    wait_for_messages(log, proc)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert 'Traceback' not in err
    with open(log, 'rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    by_topic: dict[str, list] = {}
    for m in read_ros2_messages(log):
        by_topic.setdefault(m.channel.topic, []).append(m)
    frames = len(by_topic['/clock'])
    assert frames > 5
    for topic in ('/feeder_sim/part_poses', '/feeder_sim/contacts', '/feeder_sim/track_state'):
        assert len(by_topic[topic]) == frames, topic
    stamps = [m.log_time_ns for m in by_topic['/feeder_sim/part_poses']]
    assert np.all(np.diff(stamps) == 10_000_000)
    assert summary.statistics.message_count == sum(map(len, by_topic.values()))


def test_kill_9_leaves_every_flushed_chunk_readable(workspace, tmp_path, processes):
    log = tmp_path / 'killed.mcap'
    proc = start_node(workspace, processes, '-p', f'record_path:={log}',
                      '-p', 'real_time_factor:=0.0', '-p', 'record_flush_period:=0.1')
    wait_for_messages(log, proc, min_bytes=100_000)
    size_before = log.stat().st_size
    proc.kill()
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    with open(log, 'rb') as f:
        with pytest.raises(McapError):
            make_reader(f).get_summary()            # no footer: the writer never finished
    # An independent streaming reader recovers the messages up to the damage.
    decode = DecoderFactory()
    schemas, channels, stamps = {}, {}, []
    with open(log, 'rb') as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                kind = type(record).__name__
                if kind == 'Schema':
                    schemas[record.id] = record
                elif kind == 'Channel':
                    channels[record.id] = record
                elif kind == 'Message':
                    channel = channels[record.channel_id]
                    if channel.topic == '/feeder_sim/part_poses':
                        schema = schemas[channel.schema_id]
                        msg = decode.decoder_for('cdr', schema)(record.data)
                        stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
        except (McapError, EOFError, ValueError):
            pass
    assert len(stamps) > 50
    assert stamps[0] == 0 and np.all(np.diff(stamps) == 10_000_000), 'no frame lost inside'
    assert log.stat().st_size >= size_before


def test_params_file_namespace_and_duration(workspace, tmp_path, processes):
    params = workspace['install'] / 'feeder_sim' / 'share' / 'feeder_sim' / 'config' / \
        'sim_node.params.yaml'
    context = Context()
    rclpy.init(context=context)
    try:
        probe = Node('probe', context=context)
        states = []
        probe.create_subscription(JointState, '/cell1/feeder_sim/track_state', states.append, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        proc = start_node(workspace, processes, '--params-file', str(params), '-r', '__ns:=/cell1',
                          '-p', 'duration:=5.0', '-p', 'real_time_factor:=1.0')
        end = time.monotonic() + 90
        while proc.poll() is None and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        out, err = proc.communicate(timeout=30)
    finally:
        rclpy.shutdown(context=context)
    assert proc.returncode == 0, err
    assert 'duration reached' in err + out
    assert states and states[-1].name == ['box']
    # Paced at real time, the run lasts long enough for discovery on a loaded machine; the
    # node builds track_state only once the probe has matched, and stops by itself at 5 s.
    assert states[-1].header.stamp.sec * 10**9 + states[-1].header.stamp.nanosec >= 4 * 10**9


def test_bad_scene_is_one_clear_line_and_exit_status_2(workspace, processes):
    proc = start_node(workspace, processes, '-p', 'scene:=no_such_scene')
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert 'sim_node: error:' in err and 'no_such_scene' in err
    assert 'Traceback' not in err


def test_a_signal_during_start_up_still_exits_0(workspace, tmp_path, processes):
    log = tmp_path / 'early.mcap'
    proc = start_node(workspace, processes, '-p', f'record_path:={log}')
    time.sleep(0.3)                       # still importing or building the world
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert 'Traceback' not in err


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_a_signal_during_the_first_compile_exits_0_within_a_second(tmp_path, sig, processes):
    # a cold kernel cache: the first frame compiles for a minute, which nothing cuts short
    log = tmp_path / 'cold.mcap'
    env = {k: v for k, v in os.environ.items() if not k.startswith(('NUMBA_', 'FEEDER_SIM'))}
    env.update(FEEDER_SIM_CACHE_DIR=str(tmp_path / 'cache'),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    proc = subprocess.Popen([str(VENV_BIN / 'sim_node'), '--ros-args', '-p',
                             f'record_path:={log}', '-p', 'real_time_factor:=0.0'],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    processes.append(proc)
    seen = []
    while not any('compiling numba kernels for first use' in line for line in seen):
        line = proc.stderr.readline()
        assert line, ''.join(seen)
        seen.append(line)
    time.sleep(1.0)                     # well inside the compile
    assert proc.poll() is None
    t0 = time.monotonic()
    proc.send_signal(sig)
    proc.wait(timeout=30)
    elapsed = time.monotonic() - t0
    err = ''.join(seen) + proc.stderr.read()
    assert proc.returncode == 0, err
    assert elapsed < 1.0, err
    assert 'stopped during a first compile' in err and 'Traceback' not in err
    with open(log, 'rb') as f:
        summary = make_reader(f).get_summary()     # finalized: footer and summary written
    assert summary is not None
    assert {c.topic for c in summary.channels.values()} >= {'/feeder_sim/part_poses', '/clock'}


def run_node(workspace, *argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    exe = ros2_run_path(workspace['env'], 'feeder_sim', 'sim_node')
    return subprocess.run([str(exe), *argv], env=workspace['env'], capture_output=True,
                          text=True, timeout=timeout)


def test_whole_numbers_are_accepted_for_double_parameters(workspace):
    # the README's own `make run DURATION=20 RTF=0` passes integers
    proc = run_node(workspace, '--ros-args', '-p', 'duration:=1', '-p', 'real_time_factor:=0',
                    '-p', 'publish_rate:=50')
    assert proc.returncode == 0, proc.stderr
    assert 'duration reached: t = 1 s' in proc.stderr + proc.stdout


def test_help_prints_usage_and_starts_nothing(workspace):
    proc = run_node(workspace, '--help', timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith('usage: ros2 run feeder_sim sim_node')
    assert 'real_time_factor' in proc.stdout and 'steps_per_call' in proc.stdout
    assert 'scene ' not in proc.stderr              # no simulation started


@pytest.mark.parametrize('argv, message', [
    (['--ros-args', '-p'], 'bad --ros-args'),
    (['--ros-args', '--no-such-flag'], 'bad --ros-args'),
    (['--ros-args', '-p', 'time_step:=1e-300'], 'solver.time_step: 1e-300 is out of range'),
    (['--ros-args', '-p', 'duration:=1e300'], 'Parameter duration out of range'),
    (['--ros-args', '--params-file', '/no/such/params.yaml'],
     '--params-file /no/such/params.yaml: no such file'),
], ids=['trailing -p', 'unknown flag', 'time step 1e-300', 'endless duration',
        'missing params file'])
def test_bad_arguments_are_one_line_and_exit_2(workspace, argv, message):
    proc = run_node(workspace, *argv, timeout=60)
    assert proc.returncode == 2, proc.stderr
    ours = [line for line in proc.stderr.splitlines() if line.startswith('sim_node:')]
    assert len(ours) == 1 and message in ours[0], proc.stderr
    assert 'Traceback' not in proc.stderr


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_a_signal_ends_long_physics_within_a_second(workspace, tmp_path, sig, processes):
    # 1e-7 s steps and one frame per simulated second: a frame is 1e7 steps of time
    # stepping, minutes of wall time; it runs in slices that look at the stop request
    log = tmp_path / 'slow.mcap'
    proc = start_node(workspace, processes, '-p', f'record_path:={log}',
                      '-p', 'real_time_factor:=0.0', '-p', 'method:=time_stepping',
                      '-p', 'time_step:=1e-7', '-p', 'publish_rate:=1.0',
                      '-p', 'record_flush_period:=0.1')
    wait_for_messages(log, proc, min_bytes=1)
    time.sleep(4.0)                       # start-up done, deep inside a frame
    assert proc.poll() is None
    sent = time.monotonic()
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    elapsed = time.monotonic() - sent
    assert proc.returncode == 0, err
    assert elapsed < 1.5, f'{elapsed:.2f} s to stop'
    assert 'Traceback' not in err
    with open(log, 'rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None                   # finalized: summary section written
    # every frame logged is whole (clock, poses, contacts, track state alike)
    by_topic: dict[str, list] = {}
    for m in read_ros2_messages(log):
        by_topic.setdefault(m.channel.topic, []).append(m)
    frames = len(by_topic['/clock'])
    assert len(by_topic['/feeder_sim/part_poses']) == frames


def test_signals_at_random_moments_end_the_node_cleanly(workspace, tmp_path, processes):
    # seeded moments from the imports (the interpreter's own start-up, before any of our
    # code runs, ends with the signal's default action) to full speed, one signal or two
    rng = np.random.default_rng(5)
    for k, delay in enumerate([0.3, *rng.uniform(0.3, 4.0, 3)]):
        log = tmp_path / f'random_{k}.mcap'
        proc = start_node(workspace, processes, '-p', f'record_path:={log}',
                          '-p', 'real_time_factor:=0.0', '-p', 'record_flush_period:=0.1')
        time.sleep(delay)
        sig = signal.SIGINT if k % 2 else signal.SIGTERM
        sent = time.monotonic()
        proc.send_signal(sig)
        if k == 3:
            time.sleep(0.05)
            proc.send_signal(sig)                # a second signal: still a clean exit
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, (delay, err)
        assert 'Traceback' not in err, (delay, err)
        if log.exists() and log.stat().st_size:
            with open(log, 'rb') as f:               # finalized: the summary is there
                assert make_reader(f).get_summary() is not None, delay
        if delay > 3.0:                          # past start-up: within a second
            assert time.monotonic() - sent < 1.5, delay


def test_a_signal_ends_a_huge_step_call_within_a_second(workspace, tmp_path, processes):
    # ~/step with steps_per_call = 1e6 frames: hours of work inside one service callback
    from std_srvs.srv import Trigger
    log = tmp_path / 'steps.mcap'
    proc = start_node(workspace, processes, '-p', f'record_path:={log}',
                      '-p', 'start_paused:=true', '-p', 'steps_per_call:=1000000',
                      '-p', 'record_flush_period:=0.1')
    context = Context()
    rclpy.init(context=context)
    try:
        probe = Node('stepper', context=context)
        client = probe.create_client(Trigger, '/feeder_sim/step')
        assert client.wait_for_service(timeout_sec=60.0)
        client.call_async(Trigger.Request())
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        assert proc.poll() is None
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        elapsed = time.monotonic() - sent
    finally:
        rclpy.shutdown(context=context)
    assert proc.returncode == 0, err
    assert elapsed < 1.5, f'{elapsed:.2f} s to stop'
    with open(log, 'rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 100   # frames stepped
