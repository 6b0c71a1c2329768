"""Fault campaign of the node's requests and callbacks, over real DDS.

Generated part-service requests with extreme, NaN, infinite, huge or malformed fields must each
be refused within 2 s with one sentence naming a bad field, and the node steps on after the
storm; an exception no check foresaw, in any callback, is answered as a refusal, logged,
counted, and the node runs on.
"""

from __future__ import annotations

import copy
import math
import random
import re
import time

from geometry_msgs.msg import PoseArray
from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger
import test_sim_node as base
from test_world_changes import TOP, vertical_track_scene
import yaml

from feeder_sim.model.scene import MAX_LENGTH_M, MAX_SPEED_MPS, MAX_SPIN_RAD_S, scene_to_dict
from feeder_sim.ros import node as sim_node

srv = pytest.importorskip('feeder_sim_interfaces.srv')
Result = pytest.importorskip('feeder_sim_interfaces.msg').Result

pytestmark = pytest.mark.timeout(120)

# the in-process node of test_sim_node: a private context, the node and a probe
graph = base.graph
resting_scene = base.resting_scene
_pose_stamped = base._pose_stamped

ANSWER_S = 2.0
EXAMPLES = 30
STORM = settings(max_examples=EXAMPLES, deadline=None, database=None)
BODY_NAME = re.compile(r'[A-Za-z0-9_][A-Za-z0-9_-]*\Z')


def _beyond(limit: float):
    """NaN, infinities and finite numbers past +-limit, up to the largest double."""
    past = st.floats(min_value=math.nextafter(limit, math.inf), max_value=1.7e308)
    return st.one_of(st.sampled_from([math.nan, math.inf, -math.inf]), past,
                     past.map(lambda x: -x))


NOT_ZERO = st.floats().filter(lambda x: x != 0.0)
TEXT = st.text(st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00'),
               max_size=40)
NOT_A_NAME = TEXT.filter(lambda s: not BODY_NAME.match(s))


@st.composite
def bad_quaternions(draw) -> tuple[float, float, float, float]:
    kind = draw(st.sampled_from(['zero', 'not finite', 'tilted']))
    if kind == 'zero':
        return draw(st.tuples(*[st.sampled_from([0.0, -0.0])] * 4))
    if kind == 'not finite':
        q = list(draw(st.tuples(*[st.floats(-1e300, 1e300)] * 4)))
        q[draw(st.integers(0, 3))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        return tuple(q)
    # a turn out of the plane: x or y at least 1 % of the largest component, at any scale
    unit = st.floats(-1.0, 1.0)
    x, y, z, w = draw(st.tuples(unit, unit, unit, unit).filter(
        lambda q: max(abs(q[0]), abs(q[1])) >= 0.01 * max(map(abs, q))))
    scale = draw(st.sampled_from([1e-300, 1e-5, 1.0, 1e200, 1e300]))
    return x * scale, y * scale, z * scale, w * scale


def _pose_fields(pose: str, twist: str) -> dict:
    return {
        f'{pose}.header.frame_id': TEXT.filter(lambda s: s not in ('', 'world')),
        f'{pose}.pose.position.x': _beyond(MAX_LENGTH_M),
        f'{pose}.pose.position.y': _beyond(MAX_LENGTH_M),
        f'{pose}.pose.position.z': NOT_ZERO,
        f'{pose}.pose.orientation': bad_quaternions(),
        f'{twist}.linear.x': _beyond(MAX_SPEED_MPS),
        f'{twist}.linear.y': _beyond(MAX_SPEED_MPS),
        f'{twist}.linear.z': NOT_ZERO,
        f'{twist}.angular.x': NOT_ZERO,
        f'{twist}.angular.y': NOT_ZERO,
        f'{twist}.angular.z': _beyond(MAX_SPIN_RAD_S),
    }


BAD_FIELDS = {
    'spawn_entity': {'name': NOT_A_NAME.filter(bool), 'uri': NOT_A_NAME,
                     **_pose_fields('initial_pose', 'initial_twist')},
    'set_entity_state': {'entity': NOT_A_NAME, **_pose_fields('pose', 'twist')},
}


def _set(request, path: str, value) -> None:
    *parents, last = path.split('.')
    target = request
    for key in parents:
        target = getattr(target, key)
    if last == 'orientation':
        q = getattr(target, last)
        q.x, q.y, q.z, q.w = value
    else:
        setattr(target, last, value)


@st.composite
def bad_requests(draw, service: str, good):
    """``good`` with one to three of its fields made bad: (request, the bad fields)."""
    table = BAD_FIELDS[service]
    fields = draw(st.lists(st.sampled_from(sorted(table)), min_size=1, max_size=3,
                           unique=True))
    request = copy.deepcopy(good)
    for field in fields:
        _set(request, field, draw(table[field]))
    return request, fields


def _storm(graph, service: str, good) -> dict[str, int]:
    """Every generated request refused in time with one sentence naming a bad field; the
    fields named, counted."""
    srv_type = {'spawn_entity': srv.SpawnEntity, 'set_entity_state': srv.SetEntityState}[service]
    client = graph.client(srv_type, f'/feeder_sim/{service}')
    named: dict[str, int] = {}

    @STORM
    @given(bad_requests(service, good))
    def ask(case):
        request, fields = case
        start = time.monotonic()
        future = client.call_async(request)
        graph.spin_until(future.done, timeout_s=ANSWER_S)
        assert time.monotonic() - start < ANSWER_S
        result = future.result().result
        assert result.result == Result.RESULT_OPERATION_FAILED, (fields, result)
        message = result.error_message
        assert message and '\n' not in message and len(message) < 400, message
        field = next((f for f in fields if message.startswith(f)), None)
        assert field is not None, (fields, message)
        named[field] = named.get(field, 0) + 1

    ask()
    return named


def _steps_on(graph, node, poses: list) -> None:
    n, t = len(poses), node.sim.t
    graph.spin_until(lambda: len(poses) > n + 2 and node.sim.t > t, timeout_s=10)


@pytest.mark.parametrize('service', ['spawn_entity', 'set_entity_state'])
def test_a_storm_of_bad_part_requests_is_refused_field_by_field_and_the_node_steps_on(
        graph, resting_scene, service):
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses')
    node = graph.start(scene=str(resting_scene), real_time_factor=1.0)
    graph.spin_until(lambda: len(poses) >= 2)
    if service == 'spawn_entity':
        good = srv.SpawnEntity.Request(name='', uri='box',
                                       initial_pose=_pose_stamped(-0.3, 0.005, 0.0))
    else:
        good = srv.SetEntityState.Request(entity='box', pose=_pose_stamped(-0.4, 0.005, 0.0))
    named = _storm(graph, service, good)
    print(f'{service}: {sum(named.values())} generated requests refused, naming {named}')
    assert list(node.sim.part_poses()[0]) == ['box'] and node.callback_exceptions == 0
    _steps_on(graph, node, poses)


def test_a_huge_but_planar_quaternion_is_a_rotation_about_z(graph, resting_scene):
    # components of 1e300 overflowed when squared and ended the node; scaled, they are a yaw
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses')
    node = graph.start(scene=str(resting_scene), real_time_factor=0.0, start_paused=True)
    graph.spin_until(lambda: node.pub_poses.get_subscription_count() > 0)
    _, origin, angle = node.sim.part_poses()
    x, y, yaw = *origin[0], angle[0]
    for scale in (1e300, 1e-300, 1e200, -1e250):
        pose = _pose_stamped(x, y, yaw, frame='')
        q = pose.pose.orientation
        q.z, q.w = scale * q.z, scale * q.w
        reply = graph.call(srv.SetEntityState, '/feeder_sim/set_entity_state',
                           srv.SetEntityState.Request(entity='box', pose=pose))
        assert reply.result.result == Result.RESULT_OK, reply.result.error_message
        turned = node.sim.part_poses()[2][0] - yaw      # -q is the same rotation
        assert abs(math.remainder(turned, 2 * math.pi)) < 1e-12
    assert graph.call(SetBool, '/feeder_sim/pause', SetBool.Request(data=False)).success
    _steps_on(graph, node, poses)


def test_an_unexpected_exception_in_any_callback_is_a_refusal_and_the_node_runs_on(
        graph, resting_scene, monkeypatch, capfd):
    from diagnostic_msgs.msg import DiagnosticArray
    poses = graph.listen(PoseArray, '/feeder_sim/part_poses')
    diagnostics = graph.listen(DiagnosticArray, '/diagnostics')
    node = graph.start(scene=str(resting_scene), real_time_factor=1.0, diagnostics_period=0.1)
    graph.spin_until(lambda: len(poses) >= 2)

    def broken(*args, **kwargs):
        raise ZeroDivisionError('float division by zero')

    # services answer with their type's failure and the exception in one sentence
    monkeypatch.setattr(node.sim, 'add_part', broken)
    for _ in range(2):
        reply = graph.call(srv.SpawnEntity, '/feeder_sim/spawn_entity', srv.SpawnEntity.Request(
            uri='box', initial_pose=_pose_stamped(-0.3, 0.005, 0.0)))
        assert reply.result.result == Result.RESULT_OPERATION_FAILED
        assert reply.result.error_message == ('service /feeder_sim/spawn_entity failed '
                                              'unexpectedly: ZeroDivisionError: float division '
                                              'by zero')
    monkeypatch.setattr(node.sim, 'reset', broken)
    reply = graph.call(Trigger, '/feeder_sim/reset', Trigger.Request())
    assert not reply.success and 'ZeroDivisionError: float division by zero' in reply.message
    # the vibration command's subscription
    monkeypatch.setattr(sim_node, 'parse_command', broken)
    graph.publisher(Float64MultiArray, 'vibration_cmd').publish(
        Float64MultiArray(data=[1e-4, 50.0]))
    graph.spin_until(lambda: node.callback_exceptions == 4)
    # the frame timer: one frame fails, the next ones run
    advance = node.sim.advance_to
    failing = [True]

    def once(t_end):
        if failing.pop() if failing else False:
            raise FloatingPointError('overflow in a frame')
        advance(t_end)

    monkeypatch.setattr(node.sim, 'advance_to', once)
    graph.spin_until(lambda: node.callback_exceptions == 5)
    _steps_on(graph, node, poses)
    # a parameter callback: the change is refused with the sentence
    monkeypatch.setattr(sim_node, 'CommandLimits', broken)
    from rclpy.parameter import Parameter
    result = node.set_parameters([Parameter('max_amplitude_m', value=0.01)])[0]
    assert not result.successful and 'ZeroDivisionError' in result.reason
    assert node.callback_exceptions == 6
    graph.spin_until(lambda: diagnostics and dict(
        (kv.key, kv.value) for kv in diagnostics[-1].status[0].values).get(
        'callback_exceptions') == '6')
    _steps_on(graph, node, poses)
    # logged once per type of exception, in one line each
    err = capfd.readouterr().err
    assert err.count('ZeroDivisionError') == 1 and err.count('FloatingPointError') == 1


def test_parts_come_and_go_at_any_phase_of_a_vertical_stroke(graph, tmp_path):
    """Spawn, move and delete at random moments of a simulated minute on a track moving
    straight up and down (the parts ride 4 mm below their scene-file places at the low
    point): each request is answered within 2 s, done or refused in one sentence, and the
    node runs on with what the answers said."""
    path = tmp_path / 'vertical.yaml'
    path.write_text(yaml.safe_dump(scene_to_dict(vertical_track_scene())))
    node = graph.start(scene=str(path), real_time_factor=4.0, method='time_stepping')
    rng = random.Random(3)
    clients = {name: graph.client(kind, f'/feeder_sim/{name}') for name, kind in (
        ('spawn_entity', srv.SpawnEntity), ('set_entity_state', srv.SetEntityState),
        ('delete_entity', srv.DeleteEntity))}
    expected = {'box', 'rider'}
    outcomes: dict[str, int] = {}
    while node.sim.t < 60.0:
        graph.spin_for(rng.uniform(0.0, 0.02))
        what = rng.choice(['spawn_entity'] * 3 + ['set_entity_state', 'delete_entity'] * 2)
        x, y = rng.uniform(-0.45, 0.45), TOP + rng.uniform(-0.006, 0.02)
        pose = _pose_stamped(x, y, rng.uniform(-math.pi, math.pi))
        if what == 'spawn_entity':
            request = srv.SpawnEntity.Request(name='', uri='box', initial_pose=pose)
        elif what == 'set_entity_state':
            request = srv.SetEntityState.Request(entity=rng.choice(sorted(expected | {'x'})),
                                                 pose=pose)
        else:
            request = srv.DeleteEntity.Request(entity=rng.choice(sorted(expected | {'x'})))
        asked = time.monotonic()
        reply = _answer(graph, clients[what], request)
        assert time.monotonic() - asked < ANSWER_S, what
        code = reply.result.result
        assert code in (Result.RESULT_OK, Result.RESULT_OPERATION_FAILED,
                        Result.RESULT_NOT_FOUND), (what, reply.result.error_message)
        assert '\n' not in reply.result.error_message
        if code == Result.RESULT_OK and what == 'spawn_entity':
            expected.add(reply.entity_name)
        elif code == Result.RESULT_OK and what == 'delete_entity':
            expected.discard(request.entity)
        said = reply.result.error_message
        key = f'{what}: ' + ('done' if code == Result.RESULT_OK else 'overlap' if ' overlap by '
                             in said else 'no such part' if 'no part named' in said else said)
        outcomes[key] = outcomes.get(key, 0) + 1
    print(sorted(outcomes.items()))
    assert not node.done and node.callback_exceptions == 0
    assert set(node.sim.part_poses()[0]) == expected - {n for _, n in node.sim.lost_parts}
    done = sum(v for k, v in outcomes.items() if k.endswith('done'))
    assert done >= 50 and len(outcomes) == 7, outcomes     # every kind of answer came
    s = node.sim.state
    assert all(np.isfinite(a).all() for a in (s.position, s.velocity, s.angle, s.omega))


def _answer(graph, client, request):
    future = client.call_async(request)
    graph.spin_until(future.done, timeout_s=ANSWER_S)
    return future.result()


def test_a_hundred_resets_at_once_are_all_answered(graph):
    """Requests sent together are queued (KEEP_ALL), none is dropped; each is
    answered in its turn between frames."""
    node = graph.start(real_time_factor=1.0)
    graph.spin_for(0.3)
    client = graph.client(Trigger, '/feeder_sim/reset')
    futures = [client.call_async(Trigger.Request()) for _ in range(100)]
    graph.spin_until(lambda: all(f.done() for f in futures), timeout_s=10.0)
    assert [f.result().message for f in futures] == ["scene 'track_one_box' reset to t = 0"] * 100
    assert not node.done and node.callback_exceptions == 0


def test_pause_reset_and_parts_are_answered_during_a_long_step(graph, resting_scene):
    """~/step of 2 000 frames runs in the frame timer a wall budget at a time: ~/get_entities
    and ~/reset are answered within a second meanwhile, and ~/pause false answers the step
    at once, saying it was resumed."""
    node = graph.start(scene=str(resting_scene), real_time_factor=0.0, start_paused=True,
                       steps_per_call=2000, publish_rate=1000.0)
    step = graph.client(Trigger, '/feeder_sim/step')
    entities = graph.client(srv.GetEntities, '/feeder_sim/get_entities')
    reset = graph.client(Trigger, '/feeder_sim/reset')
    pause = graph.client(SetBool, '/feeder_sim/pause')
    stepping = step.call_async(Trigger.Request())
    graph.spin_until(lambda: node.frames > 20)
    for client, request in ((entities, srv.GetEntities.Request()),
                            (reset, Trigger.Request())):
        asked = time.monotonic()
        reply = _answer(graph, client, request)
        assert time.monotonic() - asked < 1.0
        assert not stepping.done()
    assert list(reply.message.split()[:1]) == ['scene'] and node.sim.t < 2.0
    asked = time.monotonic()
    assert _answer(graph, pause, SetBool.Request(data=False)).success
    graph.spin_until(stepping.done, timeout_s=1.0)
    assert time.monotonic() - asked < 1.0
    assert stepping.result().success and 'resumed' in stepping.result().message
    assert node.callback_exceptions == 0


def test_two_thousand_spawns_sent_at_once_are_all_answered(graph, resting_scene):
    """2 000 spawn requests sent without waiting (the node paused: only the services work)
    are each answered, added or refused for the place being taken, and the parts added are
    the ones the answers named."""
    node = graph.start(scene=str(resting_scene), real_time_factor=0.0, start_paused=True)
    client = graph.probe.create_client(srv.SpawnEntity, '/feeder_sim/spawn_entity',
                                       qos_profile=sim_node._SERVICE_QOS)
    assert client.wait_for_service(timeout_sec=10.0)
    rng = random.Random(5)
    futures = [client.call_async(srv.SpawnEntity.Request(
        name='', uri='box', initial_pose=_pose_stamped(rng.uniform(-0.45, 0.45),
                                                       rng.uniform(0.02, 1.0), 0.0)))
        for _ in range(2000)]
    answered = []
    for f in futures:
        f.add_done_callback(answered.append)
    graph.spin_until(lambda: len(answered) == len(futures), timeout_s=90.0)
    codes = [f.result().result.result for f in futures]
    assert set(codes) <= {Result.RESULT_OK, Result.RESULT_OPERATION_FAILED}
    added = {f.result().entity_name for f in futures
             if f.result().result.result == Result.RESULT_OK}
    assert len(added) > 500 and codes.count(Result.RESULT_OPERATION_FAILED) > 100
    assert set(node.sim.part_poses()[0]) == added | {'box'}
    assert node.callback_exceptions == 0


def test_pausing_from_python_stops_and_starts_the_frames(graph):
    # the frame timer is off while paused: a script that sets `paused` itself must start it
    node = graph.start(real_time_factor=0.0, start_paused=True)
    graph.spin_for(0.2)
    assert node.frames == 0
    node.paused = False
    graph.spin_until(lambda: node.frames > 5)
    node.paused = True
    graph.spin_for(0.05)
    frames = node.frames
    graph.spin_for(0.2)
    assert node.frames == frames
