"""The ROS 2 node in-process: real rclpy over real DDS, the node and a probe in one executor.

Every test starts its own context; what the probe receives is compared with the simulator's
own numbers or with an analytic value.
"""

from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path
import subprocess
import sys
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray
from mcap_ros2.reader import read_ros2_messages
import numpy as np
from paths import DATA, REPO
import pytest
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import Bool, Float64MultiArray, UInt32
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray
import yaml

from feeder_sim.model.scene import load_scene, scene_to_dict
from feeder_sim.output.recording import read_messages
from feeder_sim.reports.pointmass import Conveyor, mean_speed
from feeder_sim.ros.messages import PART_IMPULSE_FIELDS
from feeder_sim.ros.node import SimNode
from feeder_sim.simulator import Simulator

pytestmark = pytest.mark.timeout(180)


def _ns(stamp: Time) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class Graph:
    """A private ROS context with the node under test and a probe node in one executor."""

    def __init__(self) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.probe = Node('probe', context=self.context)
        self.executor.add_node(self.probe)
        self.node: SimNode | None = None
        self.received: dict[str, list] = {}

    def start(self, **params) -> SimNode:
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        self.node = SimNode(context=self.context, parameter_overrides=overrides,
                            use_global_arguments=False)
        self.executor.add_node(self.node)
        return self.node

    def listen(self, msg_type, topic: str, qos=10) -> list:
        box = self.received.setdefault(topic, [])
        self.probe.create_subscription(msg_type, topic, box.append, qos)
        return box

    def spin_until(self, predicate, timeout_s: float = 20.0) -> None:
        end = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > end:
                raise TimeoutError(f'condition not met within {timeout_s:.0f} s')
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, wall_s: float) -> None:
        end = time.monotonic() + wall_s
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def client(self, srv_type, name: str):
        client = self.probe.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=10.0), name
        return client

    def call(self, srv_type, name: str, request, client=None):
        client = client or self.client(srv_type, name)
        future = client.call_async(request)
        self.spin_until(future.done)
        return future.result()

    def publisher(self, msg_type, topic: str):
        pub = self.probe.create_publisher(msg_type, topic, 10)
        self.spin_until(lambda: pub.get_subscription_count() > 0)
        return pub

    def close(self) -> None:
        # every step runs even when one fails (a test may leave the node's callbacks patched):
        # a node left alive is a namesake that makes the next test's node stop itself
        try:
            if self.node is not None:
                try:
                    self.node.close()
                finally:
                    # destroyed, not left to the garbage collector: a lingering node keeps its
                    # latched geometry writer alive, and the next test's late subscriber would
                    # receive it
                    self.node.destroy_node()
        finally:
            try:
                self.probe.destroy_node()
                self.executor.shutdown()
            finally:
                rclpy.shutdown(context=self.context)


@pytest.fixture
def graph():
    g = Graph()
    yield g
    g.close()


@pytest.fixture
def resting_scene(tmp_path) -> Path:
    """The default track with the drive switched off: the box rests until commanded."""
    scene = load_scene('track_one_box')
    bodies = [replace(b, vibration=replace(b.vibration, amplitude=0.0))
              if b.vibration is not None else b for b in scene.bodies]
    path = tmp_path / 'resting.yaml'
    path.write_text(yaml.safe_dump(scene_to_dict(replace(scene, bodies=tuple(bodies)))))
    return path


def test_clock_and_poses_are_simulated_time_and_match_the_simulator(graph):
    clock = graph.listen(Clock, '/clock',
                         QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses')
    node = graph.start(real_time_factor=0.0, publish_rate=100.0)
    graph.spin_until(lambda: len(poses) >= 30 and clock)
    stamps = np.array([_ns(p.header.stamp) for p in poses])
    assert np.all(np.diff(stamps) > 0)
    assert np.all(stamps % 10_000_000 == 0), 'stamps are whole frames of 10 ms simulated time'
    assert _ns(clock[-1].clock) > 0
    assert all(p.header.frame_id == 'world' for p in poses)
    # The same scene run bare, to the time of one received frame, gives the same pose.
    msg = poses[25]
    bare = Simulator('track_one_box')
    for k in range(1, _ns(msg.header.stamp) // 10_000_000 + 1):
        bare.advance(k * 0.01)
    _, origin, angle = bare.part_poses()
    p = msg.poses[0]
    assert p.position.x == pytest.approx(origin[0, 0], abs=1e-12)
    assert p.position.y == pytest.approx(origin[0, 1], abs=1e-12)
    assert 2 * math.atan2(p.orientation.z, p.orientation.w) == pytest.approx(angle[0], abs=1e-12)
    assert node.commands_rejected == 0


def test_vibration_command_starts_and_stops_feeding(graph, resting_scene):
    track = graph.listen(JointState, '/feeder_sim/track_state')
    node = graph.start(scene=str(resting_scene), real_time_factor=0.0)
    # Messages are built once the probe has been discovered: wait for a few of them.
    graph.spin_until(lambda: len(track) >= 20)
    s0 = track[-1].position[0]
    assert abs(s0 - track[0].position[0]) < 1e-9, 'without vibration the box stays put'

    amplitude, frequency = 3.5e-4, 50.0
    graph.publisher(Float64MultiArray, 'vibration_cmd').publish(
        Float64MultiArray(data=[amplitude, frequency]))
    graph.spin_until(lambda: node.commands_accepted == 1)
    t_on = node.sim.t
    graph.spin_until(lambda: _ns(track[-1].header.stamp) / 1e9 >= t_on + 1.5)
    # Feeding speed over the last second, against the analytic point-mass conveyor
    # (a flat box on a hopping track feeds like the point mass: 0.3 % in test_conveying).
    t = np.array([_ns(m.header.stamp) / 1e9 for m in track])
    s = np.array([m.position[0] for m in track])
    window = t >= t_on + 0.5
    speed = (s[window][-1] - s[window][0]) / (t[window][-1] - t[window][0])
    psi = math.radians(20.0)
    omega = 2 * math.pi * frequency
    exact = mean_speed(Conveyor(psi=psi, theta=0.0, mu_s=0.5, mu_k=0.5,
                                gamma=amplitude * omega ** 2 * math.sin(psi) / 9.81))
    assert speed == pytest.approx(exact, rel=0.02)

    graph.publisher(Float64MultiArray, 'vibration_cmd').publish(
        Float64MultiArray(data=[0.0, frequency]))
    graph.spin_until(lambda: node.commands_accepted == 2)
    t_off = node.sim.t
    graph.spin_until(lambda: _ns(track[-1].header.stamp) / 1e9 >= t_off + 0.5)
    # The drive fades out within one period; a quarter second later the box is at rest.
    late = [m for m in track if _ns(m.header.stamp) / 1e9 >= t_off + 0.25]
    assert abs(late[-1].position[0] - late[0].position[0]) < 1e-6
    assert abs(late[-1].velocity[0]) < 1e-6


def test_pause_step_and_reset(graph):
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses')
    node = graph.start(real_time_factor=0.0, steps_per_call=3, publish_rate=200.0)
    graph.spin_until(lambda: len(poses) >= 5)         # the probe is matched
    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=True)).success
    t_paused = node.sim.t
    graph.spin_for(0.3)
    assert node.sim.t == t_paused
    n_before = len(poses)
    reply = graph.call(Trigger, '/feeder_sim/step', Trigger.Request())
    assert reply.success, reply.message
    assert node.sim.t == pytest.approx(t_paused + 3 / 200.0, abs=1e-12)
    graph.spin_until(lambda: len(poses) >= n_before + 3)
    assert _ns(poses[-1].header.stamp) == round((t_paused + 3 / 200.0) * 1e9)

    reply = graph.call(Trigger, '/feeder_sim/reset', Trigger.Request())
    assert reply.success
    assert node.sim.t == 0.0
    graph.spin_until(lambda: _ns(poses[-1].header.stamp) == 0)
    initial = load_scene('track_one_box').bodies[1].pose
    assert poses[-1].poses[0].position.x == pytest.approx(initial[0], abs=1e-12)

    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
    reply = graph.call(Trigger, '/feeder_sim/step', Trigger.Request())
    assert not reply.success and 'pause' in reply.message
    graph.spin_until(lambda: node.sim.t > 0.02)


def test_parameters_are_validated(graph):
    node = graph.start(real_time_factor=0.0, start_paused=True)

    def set_param(name, value):
        msg = Parameter(name, value=value).to_parameter_msg()
        request = SetParameters.Request(parameters=[msg])
        return graph.call(SetParameters, '/feeder_sim/set_parameters', request).results[0]

    assert set_param('real_time_factor', 5.0).successful
    assert node.get_parameter('real_time_factor').value == 5.0
    assert not set_param('real_time_factor', -1.0).successful
    assert not set_param('real_time_factor', 5000.0).successful
    assert not set_param('scene', 'incline_stick').successful          # read-only
    assert not set_param('publish_rate', 10.0).successful              # read-only
    assert not set_param('real_time_factor', 'fast').successful        # wrong type
    assert node.get_parameter('real_time_factor').value == 5.0


def test_construction_rejects_bad_parameters():
    g = Graph()
    try:
        with pytest.raises(Exception, match='real_time_factor'):
            g.start(real_time_factor=-2.0)
        with pytest.raises(ValueError, match='method'):
            g.start(method='verlet')
        with pytest.raises(ValueError, match='scene'):
            g.start(scene='no_such_scene')
        with pytest.raises(ValueError, match="log_time must be 'wall' or 'sim'"):
            g.start(log_time='gps')
        # each refused node has left the graph (the exceptions above still hold them): a
        # lingering one would be a namesake that makes the next node stop itself
        g.spin_for(0.2)
        assert ('feeder_sim', '/') not in g.probe.get_node_names_and_namespaces()
    finally:
        g.close()


def test_bad_commands_are_rejected_counted_and_the_last_good_one_stays(graph):
    node = graph.start(real_time_factor=0.0, start_paused=True)
    drive = node.sim.world.drives[node.sim.world.driven[0]]
    pub = graph.publisher(Float64MultiArray, 'vibration_cmd')
    pub.publish(Float64MultiArray(data=[2e-4, 60.0]))
    graph.spin_until(lambda: node.commands_accepted == 1)
    assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success
    assert (drive.amplitude_m, drive.frequency_hz) == (2e-4, 60.0)
    # denormals and values below what the physics resolves too: a*omega underflows to 0
    bad = [[math.nan, 50.0], [1e-3, math.inf], [-1e-3, 50.0], [0.2, 50.0], [1e-3, 2000.0],
           [1e-3], [1e-3, 50.0, 1.0], [1e-310, 1e-310], [5e-324, 50.0], [1e-3, 1e-320],
           [1e-12, 50.0], [1e-3, 1e-6]]
    for k, data in enumerate(bad, 1):          # one at a time: the queue holds ten
        pub.publish(Float64MultiArray(data=data))
        graph.spin_until(lambda k=k: node.commands_rejected == k)
    assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success
    assert (drive.amplitude_m, drive.frequency_hz) == (2e-4, 60.0)
    assert node.commands_accepted == 1
    assert node.status()['commands_rejected'] == len(bad)


def test_part_impulses_carry_the_weight_of_a_resting_part(graph):
    impulses = graph.listen(PointCloud2, '/feeder_sim/part_impulses')
    node = graph.start(scene='incline_stick', real_time_factor=0.0, publish_rate=50.0)
    graph.spin_until(lambda: len(impulses) >= 20)
    names = [f.name for f in impulses[-1].fields]
    assert names == [name for name, _, _ in PART_IMPULSE_FIELDS]
    row = np.frombuffer(bytes(impulses[-1].data), dtype='<f4').reshape(-1, len(names))
    weight = node.sim.world.mass[node.sim.part_indices[0]] * 9.81
    # A block stuck on the incline: the track pushes it up by exactly its weight, N s per frame.
    assert row[0, 3] == pytest.approx(0.0, abs=1e-9)
    assert row[0, 4] == pytest.approx(weight / 50.0, rel=1e-5)
    assert row[0, 7].view('<u4') >= 2


def test_geometry_is_latched_and_markers_follow_parts(graph):
    node = graph.start(real_time_factor=0.0, publish_rate=50.0)
    graph.spin_until(lambda: node.frames >= 5)
    # A subscriber that joins late still gets the static geometry.
    geometry = graph.listen(MarkerArray, '/feeder_sim/geometry',
                            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
    markers = graph.listen(MarkerArray, '/feeder_sim/markers')
    graph.spin_until(lambda: geometry and len(markers) >= 3)
    assert [m.ns for m in geometry[0].markers] == ['track']
    outline = [m for m in markers[-1].markers if m.ns == 'box'][0]
    assert len(outline.points) == 5            # closed rectangle
    stamp = _ns(markers[-1].markers[0].header.stamp)
    assert stamp % 20_000_000 == 0


def test_qos_can_be_overridden_by_parameter(graph):
    node = graph.start(**{
        'real_time_factor': 0.0,
        'qos_overrides./feeder_sim/part_poses.publisher.reliability': 'best_effort',
        'qos_overrides./feeder_sim/part_poses.publisher.depth': 1})
    assert node.pub_poses.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert node.pub_poses.qos_profile.depth == 1
    assert node.pub_contacts.qos_profile.reliability == ReliabilityPolicy.RELIABLE


def test_real_time_factor_paces_and_changes_at_run_time(graph):
    node = graph.start(real_time_factor=1.0)
    graph.spin_for(0.3)
    t0, w0 = node.sim.t, time.monotonic()
    graph.spin_for(1.0)
    rate_1 = (node.sim.t - t0) / (time.monotonic() - w0)
    node.set_parameters([Parameter('real_time_factor', value=0.25)])
    t0, w0 = node.sim.t, time.monotonic()
    graph.spin_for(1.0)
    rate_q = (node.sim.t - t0) / (time.monotonic() - w0)
    # Paced runs never get ahead of the wall clock; a loaded machine may fall behind.
    assert 0.6 < rate_1 <= 1.05
    assert 0.15 < rate_q <= 0.27


def test_recording_failure_continues_or_stops(graph, tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    node = graph.start(real_time_factor=0.0, record_path=str(blocker / 'x.mcap'))
    graph.spin_until(lambda: node.sim.t > 0.1)
    assert node.status()['recording'].startswith('failed') and not node.done

    g = Graph()
    try:
        stopped = g.start(real_time_factor=0.0, record_path=str(blocker / 'y.mcap'),
                          on_record_error='stop')
        assert stopped.done and stopped.exit_code == 1
    finally:
        g.close()


@pytest.mark.skipif(not Path('/dev/full').exists(), reason='needs /dev/full')
def test_a_full_disk_is_reported_and_the_simulation_goes_on(graph):
    # Every write to /dev/full fails with ENOSPC, as on a full disk.
    node = graph.start(real_time_factor=0.0, record_path='/dev/full')
    graph.spin_until(lambda: node.sim.t > 0.2)
    assert 'No space left' in node.status()['recording'] and not node.done


def test_the_log_read_by_mcap_ros2_holds_what_the_simulator_computed(graph, tmp_path):
    log = tmp_path / 'node.mcap'
    before = time.time_ns()
    node = graph.start(real_time_factor=0.0, record_path=str(log), start_paused=True,
                       steps_per_call=40)
    assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success
    node.close()
    messages = list(read_ros2_messages(log))
    types = {m.channel.topic: m.schema.name for m in messages}
    assert types == {'/clock': 'rosgraph_msgs/msg/Clock',
                     '/feeder_sim/part_poses': 'geometry_msgs/msg/PoseArray',
                     '/feeder_sim/contacts': 'sensor_msgs/msg/PointCloud2',
                     '/feeder_sim/track_state': 'sensor_msgs/msg/JointState',
                     '/vibration_cmd': 'std_msgs/msg/Float64MultiArray',
                     '/tf': 'tf2_msgs/msg/TFMessage',
                     '/feeder_sim/geometry': 'visualization_msgs/msg/MarkerArray',
                     '/feeder_sim/part_impulses': 'sensor_msgs/msg/PointCloud2'}
    poses = [m for m in messages if m.channel.topic == '/feeder_sim/part_poses']
    assert len(poses) == 41                     # the initial frame and 40 steps
    assert [_ns(m.ros_msg.header.stamp) for m in poses] == [k * 10_000_000 for k in range(41)]
    # log times: the recording's start on the wall clock (a whole second) plus simulated time,
    # so that viewers show when the run was, not 1970
    from mcap.reader import make_reader
    with open(log, 'rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}['feeder_sim']
    origin = int(meta['log_time_origin_ns'])
    assert before - 1_000_000_000 < origin <= time.time_ns() and origin % 1_000_000_000 == 0
    assert all(m.log_time_ns == origin + _ns(m.ros_msg.header.stamp) for m in poses)
    bare = Simulator('track_one_box')
    for k in range(1, 41):
        bare.advance(k * 0.01)
    _, origin, angle = bare.part_poses()
    p = poses[-1].ros_msg.poses[0]
    assert (p.position.x, p.position.y) == (origin[0, 0], origin[0, 1])
    assert 2 * math.atan2(p.orientation.z, p.orientation.w) == pytest.approx(angle[0], abs=1e-15)


def test_same_commands_at_the_same_simulated_times_give_the_same_log(tmp_path):
    # log_time 'sim': log times are simulated time alone (by default they start at the
    # recording's wall-clock time, which no two runs share)
    logs = []
    for run in range(2):
        g = Graph()
        try:
            path = tmp_path / f'run{run}.mcap'
            node = g.start(real_time_factor=0.0, start_paused=True, record_path=str(path),
                           steps_per_call=7, log_time='sim')
            pub = g.publisher(Float64MultiArray, 'vibration_cmd')
            for command in ([5e-4, 40.0], [2e-4, 70.0]):
                for _ in range(3):
                    assert g.call(Trigger, '/feeder_sim/step', Trigger.Request()).success
                pub.publish(Float64MultiArray(data=command))
                g.spin_until(lambda n=node, c=command: n._pending_command == tuple(c))
            for _ in range(5):
                g.call(Trigger, '/feeder_sim/step', Trigger.Request())
            node.close()
        finally:
            g.close()
        # /diagnostics runs on the wall clock (pacing, real-time factor): a run that takes a
        # second longer, as a process's first one loading its kernels may, has one more
        logs.append([m for m in read_messages(path) if m[0] != '/diagnostics'])
    assert len(logs[0]) > 100
    assert logs[0] == logs[1]


def test_diagnostics_report_pacing_and_solver_health(graph, tmp_path):
    diagnostics = graph.listen(DiagnosticArray, '/diagnostics')
    log = tmp_path / 'diagnostics.mcap'
    node = graph.start(real_time_factor=0.0, diagnostics_period=0.2, record_path=str(log))
    graph.spin_until(lambda: len(diagnostics) >= 3)
    status = diagnostics[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.OK
    for key in ('real_time_factor_achieved', 'solver_fallbacks', 'max_penetration_m',
                'commands_rejected', 'lcp_solves'):
        assert key in values
    assert float(values['real_time_factor_achieved']) > 0.5    # as fast as possible
    assert int(values['solver_fallbacks']) == node.sim.stats.fallbacks
    for key in ('frictionless_answers', 'unresolved_force_lcps'):
        assert int(values[key]) == 0
    # an answer without friction (counted as the fallback ladder counts it) turns the
    # status to ERROR, with the count in the message
    node.sim.stats.frictionless_answers = 3
    seen = len(diagnostics)
    graph.spin_until(lambda: len(diagnostics) > seen + 1)
    status = diagnostics[-1].status[0]
    assert status.level == DiagnosticStatus.ERROR
    assert status.message.startswith('3 contact LCPs answered without friction')
    assert {kv.key: kv.value for kv in status.values}['frictionless_answers'] == '3'
    # the log holds what was published, stamped with the simulated time it was sent at
    node.close()
    logged = [m.ros_msg for m in read_ros2_messages(str(log), topics=['/diagnostics'])]
    published = {_ns(d.header.stamp): d.status[0] for d in diagnostics}
    assert len(logged) >= len(published) >= 4
    for d in logged:
        status = d.status[0]
        if _ns(d.header.stamp) in published:
            sent = published[_ns(d.header.stamp)]
            assert (status.level, status.name, status.message) == (
                sent.level[0] if isinstance(sent.level, bytes) else sent.level, sent.name,
                sent.message)
            assert [(kv.key, kv.value) for kv in status.values] == [
                (kv.key, kv.value) for kv in sent.values]
    assert logged[-1].status[0].level == 2                       # ERROR


@pytest.mark.timeout(600)   # the suite's: a cold cache compiles time_stepping for minutes
def test_a_real_time_factor_not_reached_is_a_warning_logged_once(graph, capfd):
    # a 10-part pile asked to run 1000 times faster than real time on this machine
    diagnostics = graph.listen(DiagnosticArray, '/diagnostics')
    node = graph.start(scene='track_ten_boxes', real_time_factor=1000, diagnostics_period=0.1)
    # the first frame may compile the pile's kernels (minutes on a cold cache): the rate is
    # judged from there on
    graph.spin_until(lambda: node.frames > 0, timeout_s=500)
    graph.spin_until(lambda: any(d.status[0].level == DiagnosticStatus.WARN
                                 for d in diagnostics), timeout_s=60)
    status = next(d.status[0] for d in diagnostics if d.status[0].level == DiagnosticStatus.WARN)
    achieved = float({kv.key: kv.value for kv in status.values}['real_time_factor_achieved'])
    assert achieved < 900 and 'real-time factor' in status.message
    seen = len(diagnostics)
    graph.spin_until(lambda: len(diagnostics) >= seen + 5)
    # the node's own log lines, as rcutils writes them to stderr
    warned = [line for line in capfd.readouterr().err.splitlines()
              if 'WARN' in line and 'real-time factor' in line]
    assert len(warned) == 1 and '1000 requested' in warned[0]
    # a factor it reaches clears it: 0 = as fast as possible is always reached
    node.set_parameters([Parameter('real_time_factor', value=0)])     # an integer, too
    seen = len(diagnostics)
    graph.spin_until(lambda: len(diagnostics) >= seen + 2)
    assert diagnostics[-1].status[0].level == DiagnosticStatus.OK
    assert node.status()['real_time_factor_requested'] == 0.0


FLOOD = '''
import sys, time, rclpy
from std_msgs.msg import Float64MultiArray
rclpy.init()
node = rclpy.create_node('flood')
pub = node.create_publisher(Float64MultiArray, 'vibration_cmd', 10)
end = time.monotonic() + 20
while pub.get_subscription_count() == 0 and time.monotonic() < end:
    time.sleep(0.01)
print('ready', flush=True)
good, bad = Float64MultiArray(data=[3e-4, 50.0]), Float64MultiArray(data=[float('nan'), 50.0])
n, t0 = 0, time.monotonic()
while time.monotonic() - t0 < float(sys.argv[1]):
    pub.publish(good if n % 2 else bad)
    n += 1
    if n % 20 == 0:                                  # about 10 kHz, without a busy wait
        time.sleep(max(0.0, t0 + n / 10000 - time.monotonic()))
print(n / (time.monotonic() - t0), flush=True)
'''


def test_a_command_flood_does_not_stall_the_simulation(graph):
    node = graph.start(real_time_factor=0.0)
    graph.spin_until(lambda: node.frames > 20)
    t0, w0 = node.sim.t, time.monotonic()
    graph.spin_for(1.5)
    calm_rate = (node.sim.t - t0) / (time.monotonic() - w0)
    # Matched before the flood: what is measured is how fast a known service answers,
    # not how fast a new endpoint is discovered on a saturated two-core machine.
    pause = graph.client(SetBool, '/feeder_sim/pause')

    flood = subprocess.Popen([sys.executable, '-c', FLOOD, '4'], stdout=subprocess.PIPE,
                             text=True)
    try:
        assert flood.stdout.readline().strip() == 'ready'
        graph.spin_for(0.5)
        t0, w0 = node.sim.t, time.monotonic()
        graph.spin_for(1.5)
        flood_rate = (node.sim.t - t0) / (time.monotonic() - w0)
        start = time.monotonic()
        assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False),
                          client=pause).success
        service_latency = time.monotonic() - start
        sent_per_s = float(flood.communicate(timeout=30)[0].strip())
    finally:
        flood.kill()
    assert sent_per_s > 5000
    # Frames and callbacks take turns every 10 ms of wall time: the queue (depth 10) drops
    # what the node cannot judge, and what it takes is judged one by one.
    assert node.commands_accepted > 0 and node.commands_rejected > 0
    graph.spin_for(0.2)
    drive = node.sim.world.drives[node.sim.world.driven[0]]
    assert drive.amplitude_m == 3e-4
    # Under the flood the simulation must keep faster than real time (the node's default
    # pace), sharing the two cores with the flooding process and the DDS threads. (Not a
    # fraction of the calm rate: that grows with every speed-up of the physics, while what a
    # flood costs, the middleware's work per message, does not.)
    assert flood_rate > 1.0, (flood_rate, calm_rate)
    assert service_latency < 2.0


@pytest.mark.parametrize('duration', [0.015, 0.004])
def test_duration_is_simulated_exactly(graph, duration):
    # not a whole number of 10 ms frames: the last frame is shorter, none is skipped
    clock = graph.listen(Clock, '/clock')
    node = graph.start(duration=duration, real_time_factor=0.0)
    graph.spin_until(lambda: node.done)
    assert node.sim.t == pytest.approx(duration, abs=1e-12)
    graph.spin_until(lambda: clock and clock[-1].clock.nanosec == round(duration * 1e9))


def test_reset_while_recording_starts_an_episode_with_monotonic_log_time(graph, tmp_path):
    from mcap.reader import make_reader
    from rerun.chunk import RrdReader

    from feeder_sim.output.replay import replay

    log = tmp_path / 'episodes.mcap'
    node = graph.start(real_time_factor=0.0, record_path=str(log), start_paused=True,
                       steps_per_call=10, log_time='sim')
    drive = node.sim.world.drives[node.sim.world.driven[0]]
    initial = (drive.amplitude_m, drive.frequency_hz)
    assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success    # to 0.1 s
    node.sim.command_vibration(2e-4, 60.0)         # a command the reset must undo
    assert graph.call(Trigger, '/feeder_sim/reset', Trigger.Request()).success
    assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success    # to 0.1 s
    node.close()

    with open(log, 'rb') as f:
        reader = make_reader(f)
        messages = [(channel.topic, message) for _, channel, message in
                    reader.iter_messages(log_time_order=False)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    log_times = [m.log_time for _, m in messages]
    assert log_times == sorted(log_times)                   # in file order, never back
    clock = [m.log_time for topic, m in messages if topic == '/clock']
    # episode 0: frames 0..0.1 s; episode 1 starts one frame (10 ms) after, at 0.11 s
    assert metadata['episode_1'] == {'index': '1', 'log_time_ns': str(110_000_000),
                                     'reason': 'reset'}
    assert clock == [k * 10_000_000 for k in range(11)] + \
        [110_000_000 + k * 10_000_000 for k in range(11)]
    # the messages keep the simulated time: the clock says 0 again at the reset
    clock_ns = [m.ros_msg.clock.sec * 10**9 + m.ros_msg.clock.nanosec
                for m in read_ros2_messages(log, topics=['/clock'])]
    assert clock_ns == 2 * [k * 10_000_000 for k in range(11)]
    # the drive the reset restored is in the log at the episode's start
    commands = [(m.log_time_ns, tuple(m.ros_msg.data))
                for m in read_ros2_messages(log, topics=['/vibration_cmd'])]
    assert commands[-1] == (110_000_000, initial)

    # the replay keeps the episodes apart: an episode timeline and a mark at the reset
    rrd = replay(log, tmp_path / 'episodes.rrd', spawn=False)
    episodes, marks = set(), []
    for chunk in RrdReader(str(rrd)).stream().to_chunks():
        batch = chunk.to_record_batch()
        if chunk.entity_path == '/world/parts/origins' and 'episode' in batch.schema.names:
            episodes.update(batch.column('episode').to_pylist())
        if chunk.entity_path == '/episodes':
            marks += batch.column('TextLog:text').to_pylist()
    assert episodes == {0, 1}
    assert len(marks) == 1 and 'reset' in str(marks[0])


def test_a_second_node_of_the_same_name_refuses_to_run(graph):
    from feeder_sim.ros.node import _NAMESAKE_WINDOW_S
    first = graph.start(real_time_factor=1.0)
    graph.spin_for(_NAMESAKE_WINDOW_S + 0.5)       # past its own start-up check
    g = Graph()
    try:
        second = g.start(real_time_factor=1.0)
        g.spin_until(lambda: second.done, timeout_s=2 * _NAMESAKE_WINDOW_S)
        assert second.exit_code == 2
    finally:
        g.close()
    graph.spin_for(0.5)
    assert not first.done and first.exit_code == 0


def test_a_node_in_its_own_namespace_runs_but_is_told_of_a_shared_clock(graph, capfd):
    first = graph.start(real_time_factor=1.0)
    graph.spin_for(0.5)
    g = Graph()
    try:
        second = SimNode(context=g.context, namespace='cell2', use_global_arguments=False,
                         parameter_overrides=[Parameter('real_time_factor', value=1.0)])
        g.node = second
        g.executor.add_node(second)
        err = []
        g.spin_until(lambda: err.append(capfd.readouterr().err) or
                     'another node publishes /clock' in ''.join(err), timeout_s=10.0)
        assert not second.done
    finally:
        g.close()
    assert not first.done


def test_a_fed_scene_publishes_the_parts_as_they_come_and_go(graph):
    # sources add a box every 0.5 s, a sink takes them away 0.15 m on: the poses' length
    # follows, track_state names them, the node keeps going and deletes a leaving part's
    # markers
    scene = DATA / 'fed_track.yaml'
    track = graph.listen(JointState, '/feeder_sim/track_state', 10_000)
    # deep queues: frames run as fast as possible, a burst between two spins must not drop
    # the message that deletes a part's markers
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses', 10_000)
    markers = graph.listen(MarkerArray, '/feeder_sim/markers', 10_000)
    node = graph.start(scene=str(scene), real_time_factor=0.0, duration=4.0,
                       marker_rate=1000.0, start_paused=True)
    # everyone matched before the parts start to leave (discovery may take seconds)
    graph.spin_until(lambda: all(p.get_subscription_count() for p in (
        node.pub_poses, node.pub_track, node.pub_markers)), timeout_s=60)
    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
    graph.spin_until(lambda: node.done, timeout_s=120)
    graph.spin_for(0.3)
    counts = {len(m.poses) for m in poses}
    assert max(counts) >= 3 and min(counts) <= 2
    named = {tuple(m.name) for m in track}
    assert ('box', 'box_1') in named or ('box_1',) in named
    assert all(len(m.name) == len(m.position) for m in track)
    feed = node.sim.feed.counts()
    assert feed['added'] == 9 and feed['left'] >= 2                # at 0, 0.5, ... 4 s
    deleted = {mk.ns for m in markers for mk in m.markers if mk.action == mk.DELETEALL}
    assert any(name.startswith('box') for name in deleted)        # parts that left


def test_sensors_over_dds_match_the_crossings_of_the_published_poses(graph):
    # two boxes slide at 0.1 m/s through a beam at x = 0.05 m and an inspection line at
    # x = 0.1 m (test/data/sensor_slide.yaml): every frame's count is the number of pose
    # crossings so far, the beam is blocked while an outline overlaps it, and each part
    # that passes the inspection line is one message naming its orientation
    scene = DATA / 'sensor_slide.yaml'
    deep = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE)
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses', deep)
    blocked = graph.listen(Bool, '/feeder_sim/sensors/beam/blocked', deep)
    beam = graph.listen(UInt32, '/feeder_sim/sensors/beam/count', deep)
    camera = graph.listen(UInt32, '/feeder_sim/sensors/camera/count', deep)
    passed = graph.listen(KeyValue, '/feeder_sim/sensors/camera/passed', deep)
    node = graph.start(scene=str(scene), real_time_factor=0.0, duration=2.0,
                       publish_rate=100.0, start_paused=True)
    pubs = [node.pub_poses, *node.pub_sensors['beam'].values(),
            *node.pub_sensors['camera'].values()]
    graph.spin_until(lambda: all(p.get_subscription_count() for p in pubs), timeout_s=60)
    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
    graph.spin_until(lambda: node.done and len(camera) >= 201, timeout_s=120)
    graph.spin_for(0.3)
    # the frame at start-up (subscribers may have missed it) and then 200 frames
    poses, blocked, beam, camera = (x[-200:] for x in (poses, blocked, beam, camera))
    start = {'flat_box': 0.0, 'upright_box': -0.05}
    half = {'flat_box': 0.01, 'upright_box': 0.005}
    for x, counts in ((0.05, beam), (0.1, camera)):
        crossed = [sum(a.position.x < x <= b.position.x for a, b in zip(p0.poses, p1.poses))
                   for p0, p1 in zip(poses, poses[1:])]
        assert [m.data for m in counts[1:]] == list(np.cumsum(crossed) + counts[0].data)
    assert beam[-1].data == camera[-1].data == 2
    for pose, b in zip(poses, blocked, strict=True):
        t = _ns(pose.header.stamp) / 1e9
        gap = min(abs(start[n] + 0.1 * t - 0.05) - half[n] for n in start)
        assert b.data == (gap < 0.0) or abs(gap) < 1e-9
    assert [(m.key, m.value) for m in passed] == [('flat_box', 'flat'), ('upright_box', 'upright')]


def _pose_stamped(x: float, y: float, yaw: float, frame: str = 'world'):
    from geometry_msgs.msg import PoseStamped
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.pose.position.x, msg.pose.position.y = x, y
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return msg


def test_part_services_add_place_and_remove_parts_at_the_next_frame(graph, resting_scene,
                                                                    tmp_path):
    from feeder_sim_interfaces.msg import Result
    from feeder_sim_interfaces.srv import DeleteEntity, GetEntities, SetEntityState, SpawnEntity
    log = tmp_path / 'parts.mcap'
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses', 10_000)
    node = graph.start(scene=str(resting_scene), real_time_factor=0.0, start_paused=True,
                       publish_rate=100.0, record_path=str(log))
    graph.spin_until(lambda: node.pub_poses.get_subscription_count() > 0)

    def call(srv_type, service, **fields):
        return graph.call(srv_type, f'/feeder_sim/{service}', srv_type.Request(**fields))

    def step() -> PoseArray:
        n = len(poses)
        assert graph.call(Trigger, '/feeder_sim/step', Trigger.Request()).success
        graph.spin_until(lambda: len(poses) > n)
        return poses[-1]

    assert list(call(GetEntities, 'get_entities').entities) == ['box']
    reply = call(SpawnEntity, 'spawn_entity', name='second', uri='box',
                 initial_pose=_pose_stamped(-0.3, 0.005, 0.0))
    assert reply.result.result == Result.RESULT_OK and reply.entity_name == 'second'
    frame = step()
    assert len(frame.poses) == 2
    # resting on the idle track: where it was put, to the settling of one frame (1 um)
    assert (frame.poses[1].position.x, frame.poses[1].position.y) == pytest.approx(
        (-0.3, 0.005), abs=1e-6)
    reply = call(SetEntityState, 'set_entity_state', entity='second',
                 pose=_pose_stamped(-0.2, 0.005, math.pi))
    assert reply.result.result == Result.RESULT_OK, reply.result.error_message
    frame = step()
    p = frame.poses[1]
    assert (p.position.x, p.position.y) == pytest.approx((-0.2, 0.005), abs=1e-6)
    assert abs(math.remainder(2 * math.atan2(p.orientation.z, p.orientation.w) - math.pi,
                              2 * math.pi)) < 1e-6
    assert call(DeleteEntity, 'delete_entity', entity='second').result.result == Result.RESULT_OK
    assert len(step().poses) == 1

    # refusals: one sentence naming what is wrong, the simulation unchanged
    cases = [
        (SpawnEntity, 'spawn_entity', {'name': 'x', 'uri': 'cup'}, Result.RESULT_NOT_FOUND,
         'template'),
        (SpawnEntity, 'spawn_entity', {'name': 'box', 'uri': 'box'},
         Result.RESULT_INCORRECT_STATE, 'allow_renaming'),
        (SpawnEntity, 'spawn_entity', {'name': 'x', 'uri': 'box',
                                       'initial_pose': _pose_stamped(-0.4, 0.005, 0.0)},
         Result.RESULT_OPERATION_FAILED, 'box'),               # inside the first box
        (SpawnEntity, 'spawn_entity', {'name': 'x', 'uri': 'box',
                                       'initial_pose': _pose_stamped(0.0, 0.1, 0.0, 'map')},
         Result.RESULT_OPERATION_FAILED, 'frame_id'),
        (DeleteEntity, 'delete_entity', {'entity': 'track'}, Result.RESULT_NOT_FOUND, 'box'),
        (SetEntityState, 'set_entity_state', {'entity': 'nothing'}, Result.RESULT_NOT_FOUND,
         'no part named'),
    ]
    for srv_type, service, fields, code, words in cases:
        reply = call(srv_type, service, **fields)
        assert reply.result.result == code and words in reply.result.error_message, fields
    assert list(call(GetEntities, 'get_entities').entities) == ['box']
    renamed = call(SpawnEntity, 'spawn_entity', name='box', uri='box', allow_renaming=True,
                   initial_pose=_pose_stamped(0.0, 0.005, 0.0))
    assert renamed.result.result == Result.RESULT_OK and renamed.entity_name == 'box_1'
    step()
    node.close()
    # recorded: the parts' outlines appear and go in the log's geometry
    actions = [(m.ns, m.action) for t, msg in [
        (x.log_time_ns, x.ros_msg) for x in read_ros2_messages(str(log),
                                                             topics=['/feeder_sim/geometry'])]
        for m in msg.markers if m.ns in ('second', 'box_1')]
    assert actions == [('second', 0), ('second', 2), ('box_1', 0)]


def test_the_example_controller_keeps_the_queue_between_its_thresholds_for_a_minute(
        graph, tmp_path):
    # examples/queue_controller.py against the node on config/queue_cell.yaml: after the
    # queue first fills, every frame holds 1 to 5 boxes in the queue zone (x > 0.10 m, the
    # stop at 0.19 m, a box 0.02 m long), the drive switches off and on, the robot picks.
    # The frames are read from the node's log (every one; a subscriber of a node running
    # as fast as it can may be passed by its publisher's history).
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        'queue_controller', REPO / 'examples' / 'queue_controller.py')
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    log = tmp_path / 'cell.mcap'
    node = graph.start(scene='queue_cell', real_time_factor=0.0, duration=60.0,
                       publish_rate=50.0, start_paused=True, record_path=str(log))
    controller = example.QueueController(context=graph.context)
    graph.executor.add_node(controller)
    try:
        graph.spin_until(lambda: controller.pick.service_is_ready()
                         and all(p.get_subscription_count() for p in (
                             *[node.pub_sensors[n]['blocked'] for n in ('queue_full',
                                                                        'at_stop')],
                             node.pub_track, node.pub_clock)), timeout_s=60)
        assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
        graph.spin_until(lambda: node.done, timeout_s=600)
        graph.spin_for(0.3)
    finally:
        graph.executor.remove_node(controller)
        controller.destroy_node()
    node.close()
    poses = [m.ros_msg for m in read_ros2_messages(str(log), topics=['/feeder_sim/part_poses'])]
    assert len(poses) == 3001
    queue = [(_ns(m.header.stamp) / 1e9, sum(p.position.x > 0.10 for p in m.poses))
             for m in poses]
    filled = next(t for t, q in queue if q >= 3)
    held = [q for t, q in queue if t > filled + 1.0]
    assert filled < 20.0 and 1 <= min(held) and max(held) <= 5
    offs = [t for t, on in controller.switches if not on]
    assert len(offs) >= 5 and len(controller.switches) >= 9
    assert len(controller.picks) >= 20                       # at most one per 2 s: 30
    assert all(p.position.x < 0.19 for m in poses for p in m.poses)   # none past the stop
    assert node.sim.t == pytest.approx(60.0, abs=1e-9)
