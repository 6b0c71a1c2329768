"""``feeder-sim node ...`` as a user runs it: the venv's console script in a subprocess, against
the real node over DDS.

One node for the module, in this process (test_sim_node's Graph), spun while each client runs;
what a command did is read from the node itself. Every test starts from the scene's start,
running, at real-time factor 1.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import subprocess
import sys
import time

import pytest
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool, Trigger
from test_sim_node import Graph
import yaml

from feeder_sim.model.scene import load_scene, scene_to_dict

pytestmark = pytest.mark.timeout(300)   # the module's node may compile kernels first

_SCRIPT = Path(sys.executable).parent / 'feeder-sim'
FEEDER_SIM = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, '-m', 'feeder_sim.cli']
FRAME_S = 0.01      # publish_rate 100


@pytest.fixture(scope='module')
def scene(tmp_path_factory) -> Path:
    """The default track with its drive off: the box rests where the scene puts it."""
    track = load_scene('track_one_box')
    bodies = [replace(b, vibration=replace(b.vibration, amplitude=0.0))
              if b.vibration is not None else b for b in track.bodies]
    path = tmp_path_factory.mktemp('client') / 'resting.yaml'
    path.write_text(yaml.safe_dump(scene_to_dict(replace(track, bodies=tuple(bodies)))))
    return path


@pytest.fixture(scope='module')
def cell(scene):
    g = Graph()
    try:
        node = g.start(scene=str(scene), real_time_factor=1.0, publish_rate=1 / FRAME_S)
        g.spin_until(lambda: node.frames > 2, timeout_s=280)
        yield g
    finally:
        g.close()


@pytest.fixture
def graph(cell):
    """The module's node back at its scene's start (parts, drive, t = 0), running, paced."""
    cell.node.set_parameters([Parameter('real_time_factor', value=1.0)])
    assert cell.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
    assert cell.call(Trigger, '/feeder_sim/reset', Trigger.Request()).success
    return cell


def feeder_sim(graph: Graph, *args: str, wall_s: float = 60.0) -> subprocess.CompletedProcess:
    """``feeder-sim node ARGS``, the node served until the client exits."""
    proc = subprocess.Popen([*FEEDER_SIM, 'node', *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        graph.spin_until(lambda: proc.poll() is not None, timeout_s=wall_s)
    finally:
        if proc.poll() is None:
            proc.kill()
        out, err = proc.communicate(timeout=30)   # a few lines: the pipes never fill
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def refused(result: subprocess.CompletedProcess) -> str:
    """The one line of a refusal (exit status 2)."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('feeder-sim: error: '), result.stderr
    return lines[0]


def test_no_node_is_one_line_and_exit_2_within_the_timeout():
    start = time.monotonic()
    result = subprocess.run([*FEEDER_SIM, 'node', 'pause', '--node', '/nobody_here/feeder_sim'],
                            capture_output=True, text=True, timeout=60)
    elapsed = time.monotonic() - start
    line = refused(result)
    assert '/nobody_here/feeder_sim' in line and 'ROS_DOMAIN_ID' in line
    # the default 5 s, and the interpreter's start on a loaded two-core machine
    assert 5.0 <= elapsed < 5.0 + 10.0


def test_an_answer_the_server_loses_is_asked_for_again_and_a_change_is_made_once():
    """A server drops its answer when it has not yet matched the client's reply reader (Fast
    DDS gives up after 100 ms; seen on a loaded machine). A node that loses its first answer
    on ~/get_parameters: the client asks again, then pauses it exactly once."""
    g = Graph()
    try:
        node = Node('lossy', context=g.context, start_parameter_services=False)
        g.executor.add_node(node)
        asked, paused = [], []

        def get_parameters(request, response):
            asked.append(request)
            return response

        def pause(request, response):
            paused.append(request.data)
            response.success, response.message = True, 'paused'
            return response
        service = node.create_service(GetParameters, '/lossy/get_parameters', get_parameters)
        node.create_service(SetBool, '/lossy/pause', pause)
        send, lost = service.send_response, []

        def lose_the_first(response, header) -> None:
            if lost:
                send(response, header)
            lost.append(header)
        service.send_response = lose_the_first
        result = feeder_sim(g, 'pause', '--node', '/lossy')
        assert result.returncode == 0, result.stderr
        assert paused == [True] and len(asked) >= 2
    finally:
        g.close()


def test_vibration_is_checked_sent_and_applied(graph):
    node = graph.node
    drive = node.sim.world.drives[node.sim.world.driven[0]]
    assert drive.amplitude_m == 0.0
    accepted, rejected = node.commands_accepted, node.commands_rejected
    result = feeder_sim(graph, 'vibration', '3.5e-4', '50')
    assert result.returncode == 0, result.stderr
    assert 'sent on /vibration_cmd' in result.stdout
    # acknowledged before the client left: the node has it, and applies it at a frame
    graph.spin_until(lambda: (drive.amplitude_m, drive.frequency_hz) == (3.5e-4, 50.0),
                     timeout_s=5.0)
    assert node.commands_accepted == accepted + 1
    # beyond the node's max_amplitude_m (0.1 m): refused here, nothing sent
    line = refused(feeder_sim(graph, 'vibration', '0.5', '50'))
    assert 'amplitude 0.5 m exceeds the limit 0.1 m' in line and 'max_amplitude_m' in line
    assert (node.commands_accepted, node.commands_rejected) == (accepted + 1, rejected)
    assert (drive.amplitude_m, drive.frequency_hz) == (3.5e-4, 50.0)


def test_pause_step_resume_advance_one_frame_while_paused(graph):
    node = graph.node
    result = feeder_sim(graph, 'pause')
    assert result.returncode == 0 and result.stdout.startswith('paused at t = '), result.stderr
    assert node.paused
    t0 = node.sim.t
    graph.spin_for(0.2)
    assert node.sim.t == t0
    result = feeder_sim(graph, 'step')
    assert result.returncode == 0, result.stderr
    assert node.sim.t == pytest.approx(t0 + FRAME_S, abs=1e-12)      # steps_per_call 1
    assert result.stdout.strip() == f't = {node.sim.t:.6g} s'
    graph.spin_for(0.2)
    assert node.sim.t == pytest.approx(t0 + FRAME_S, abs=1e-12)
    result = feeder_sim(graph, 'resume')
    assert result.returncode == 0 and result.stdout.startswith('running at t = ')
    assert not node.paused
    graph.spin_until(lambda: node.sim.t > t0 + 5 * FRAME_S)
    # a running node refuses a step, in its words, with the client's fix
    line = refused(feeder_sim(graph, 'step'))
    assert '/feeder_sim/step refused: not paused' in line and 'feeder-sim node pause' in line


def test_reset_goes_back_to_the_start(graph):
    from feeder_sim_interfaces.srv import SpawnEntity
    node = graph.node
    request = SpawnEntity.Request(name='visitor', uri='box')
    request.initial_pose.pose.position.x, request.initial_pose.pose.position.y = -0.2, 0.005
    assert graph.call(SpawnEntity, '/feeder_sim/spawn_entity', request).entity_name == 'visitor'
    graph.spin_until(lambda: node.sim.t > 0.2)
    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=True)).success
    result = feeder_sim(graph, 'reset')
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "scene 'track_one_box' reset to t = 0"
    assert node.sim.t == 0.0
    names, origin, angle = node.sim.part_poses()
    assert list(names) == ['box']
    assert tuple(origin[0]) == (-0.4, 0.005) and angle[0] == 0.0


def test_spawn_list_delete_and_a_refusal(graph):
    node = graph.node
    result = feeder_sim(graph, 'spawn', 'box', '--name', 'extra', '--pose', '-0.3', '0.005',
                        '0')
    assert result.returncode == 0, result.stderr
    assert result.stdout == 'extra\n'
    t = node.sim.t
    graph.spin_until(lambda: node.sim.t > t)
    names, origin, _ = node.sim.part_poses()
    assert list(names) == ['box', 'extra']
    # resting on the idle track: where it was put, to the settling of a frame (1 um)
    assert tuple(origin[1]) == pytest.approx((-0.3, 0.005), abs=1e-6)
    result = feeder_sim(graph, 'list')
    assert result.returncode == 0 and result.stdout.splitlines() == ['box', 'extra']
    result = feeder_sim(graph, 'delete', 'extra')
    assert result.returncode == 0, result.stderr
    assert list(node.sim.part_poses()[0]) == ['box']
    result = feeder_sim(graph, 'list')
    assert result.returncode == 0 and result.stdout.splitlines() == ['box']
    # an unknown part: the node's refusal, on one line
    line = refused(feeder_sim(graph, 'delete', 'extra'))
    assert "/feeder_sim/delete_entity refused: entity: no part named 'extra'" in line


def test_param_converts_to_the_parameter_type_and_relays_a_refusal(graph):
    node = graph.node
    # a whole number for a double parameter: sent as the double
    result = feeder_sim(graph, 'param', 'real_time_factor', '3')
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == 'real_time_factor = 3.0'
    assert node.get_parameter('real_time_factor').value == 3.0
    line = refused(feeder_sim(graph, 'param', 'real_time_factor', '5000'))
    assert 'param real_time_factor: /feeder_sim refused 5000' in line and '1000' in line
    assert node.get_parameter('real_time_factor').value == 3.0


def test_echo_poses_prints_the_named_parts_of_consecutive_frames(graph):
    result = feeder_sim(graph, 'echo', 'poses', '--count', '2')
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 4 and lines[0].startswith('--- t = ') and lines[2].startswith('--- t = ')
    t = [float(lines[k].split()[3]) for k in (0, 2)]
    assert t[1] - t[0] == pytest.approx(FRAME_S, abs=1e-9)
    for line in lines[1], lines[3]:
        name, x, y, yaw = line.split()
        # the box rests where the scene puts it: (-0.4 m, 0.005 m), yaw 0
        assert name == 'box'
        assert (float(x), float(y), float(yaw)) == pytest.approx((-0.4, 0.005, 0.0), abs=1e-6)
