"""``feeder-sim node ...``: talk to a running feeder_sim node from the venv (no ``ros2`` CLI).

One short-lived rclpy node per invocation, in a context of its own, destroyed on the way out.
Every wait is bounded by ``--timeout`` (wall seconds, default 5): finding the node, each
answer, each message. A node that is not there, a refusal, an answer or message that does not
come: one line on stderr and exit status 2.

What the subcommands use (relative to the node ``--node``, default ``/feeder_sim``)::

    vibration A F   the node's Float64MultiArray subscription (vibration_cmd, found in the
                    graph so that a remap is followed), checked first against its limits
    pause, resume   ~/pause (SetBool)        step, reset   ~/step, ~/reset (Trigger)
    list, spawn, delete   ~/get_entities, ~/spawn_entity, ~/delete_entity
    param N V       ~/get_parameters for N's type, then ~/set_parameters
    echo poses      ~/part_poses, named from ~/track_state (same frame stamp)
    echo sensor S   ~/sensors/S/{blocked,count,passed}
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import math
import os
import sys
import time

from diagnostic_msgs.msg import KeyValue
from geometry_msgs.msg import PoseArray
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.validate_full_topic_name import validate_full_topic_name
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, UInt32
from std_srvs.srv import SetBool, Trigger

DEFAULT_NODE = '/feeder_sim'
DEFAULT_TIMEOUT_S = 5.0
# How often graph conditions (a service appearing, a subscriber matching) are looked at: the
# executor is not woken by graph changes.
_POLL_S = 0.05
# Once the node is seen, how much longer its topics may take to show up in the graph (DDS
# announces a participant's endpoints one by one).
_ENDPOINTS_S = 1.0
_SENSOR_TYPES = {'blocked': Bool, 'count': UInt32, 'passed': KeyValue}
_COMMAND_TYPE = 'std_msgs/msg/Float64MultiArray'
# Services that only read: asking again is harmless. The first answer is awaited this long
# (wall s) before asking again, doubling each time.
_QUERIES = frozenset({'get_parameters', 'list_parameters', 'get_entities'})
_RESEND_S = 0.5


class Refused(Exception):
    """What went wrong, as the one line the user sees: a refusal, no node, no answer."""


def split_node_name(text: str) -> tuple[str, str]:
    """``(namespace, name)`` of a node given as ``/NAMESPACE/NAME`` (the leading slash may be
    left out)."""
    full = text if text.startswith('/') else '/' + text
    try:
        validate_full_topic_name(full)
    except Exception as err:   # rclpy's InvalidTopicNameException and kin
        raise Refused(f'--node {text}: not a node name ({str(err).splitlines()[0]}); give it '
                      'as /NAMESPACE/NAME, e.g. /cell1/feeder_sim') from None
    namespace, _, name = full.rpartition('/')
    return namespace or '/', name


class _Session:
    """A private context with one client node and its executor; ``with`` cleans them up."""

    def __init__(self, target: str, timeout_s: float) -> None:
        if not timeout_s > 0.0 or not math.isfinite(timeout_s):
            raise Refused(f'--timeout {timeout_s:g}: must be a positive number of seconds')
        self.namespace, self.name = split_node_name(target)
        self.fqn = self.namespace.rstrip('/') + '/' + self.name
        self.timeout_s = timeout_s
        self.context = Context()
        # Python's own SIGINT handling (KeyboardInterrupt): waits below are short slices
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        try:
            # a leading underscore keeps it out of node lists; the pid keeps two apart
            self.node = Node(f'_feeder_sim_cli_{os.getpid()}', context=self.context,
                             use_global_arguments=False, start_parameter_services=False)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise

    def __enter__(self) -> _Session:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.node.destroy_node()
            self.executor.shutdown(timeout_sec=1.0)
        finally:
            rclpy.try_shutdown(context=self.context)

    # -- waiting ---------------------------------------------------------------------------

    def deadline(self) -> float:
        return time.monotonic() + self.timeout_s

    def spin_until(self, done: Callable[[], bool], deadline: float) -> bool:
        """Serve callbacks until ``done()`` or the deadline (monotonic s); whether it is done."""
        while not done():
            left = deadline - time.monotonic()
            if left <= 0.0:
                return False
            self.executor.spin_once(timeout_sec=min(_POLL_S, left))
        return True

    def present(self) -> bool:
        return (self.name, self.namespace) in self.node.get_node_names_and_namespaces()

    def absent(self) -> str:
        domain = os.environ.get('ROS_DOMAIN_ID', '') or '0 (unset)'
        return (f'no node {self.fqn} answers (waited {self.timeout_s:g} s): is it running, '
                f'started with this ROS_DOMAIN_ID ({domain})? Another namespace: --node '
                '/NAMESPACE/feeder_sim')

    def wait_for_node(self) -> None:
        if not self.spin_until(self.present, self.deadline()):
            raise Refused(self.absent())

    # -- services --------------------------------------------------------------------------

    def call(self, srv_type, service: str, request, hint: str = ''):
        """The answer of the node's service ``~/<service>``.

        A server drops its answer when it has not yet matched the client's reply reader
        (Fast DDS waits 100 ms for that, then gives up): discovery is not symmetric, and
        ``service_is_ready`` sees only the client's half. A query is therefore sent again
        until answered; a request that changes the node is sent once, after a query on a
        client made later has been answered, since the server learns of a participant's
        readers in the order they were made."""
        client = self._ready_client(srv_type, service, hint)
        if service not in _QUERIES:
            self._ask(self._ready_client(GetParameters, 'get_parameters', hint),
                      GetParameters.Request(), resend=True)
        return self._ask(client, request, resend=service in _QUERIES)

    def _ready_client(self, srv_type, service: str, hint: str):
        client = self.node.create_client(srv_type, f'{self.fqn}/{service}')
        if not self.spin_until(client.service_is_ready, self.deadline()):
            if not self.present():
                raise Refused(self.absent())
            raise Refused(f'{self.fqn} does not serve {client.srv_name}'
                          + (f' ({hint})' if hint else ''))
        return client

    def _ask(self, client, request, resend: bool):
        deadline = self.deadline()
        wait_s = _RESEND_S
        futures = [client.call_async(request)]

        def answered() -> bool:
            return any(f.done() for f in futures)
        while not self.spin_until(answered, min(deadline, time.monotonic() + wait_s)):
            if time.monotonic() >= deadline:
                raise Refused(f'{client.srv_name} did not answer within {self.timeout_s:g} s '
                              '(a longer wait: --timeout S)')
            if resend:
                futures.append(client.call_async(request))
                wait_s *= 2.0
        return next(f for f in futures if f.done()).result()

    def parameters(self, names: list[str]) -> list[ParameterValue]:
        return list(self.call(GetParameters, 'get_parameters',
                              GetParameters.Request(names=names)).values)

    # -- topics ----------------------------------------------------------------------------

    def subscribe(self, msg_type, topic: str, callback: Callable, depth: int = 10) -> None:
        """A subscription that matches the publisher's reliability: a reliable reader gets
        nothing from a best-effort writer (``qos_overrides`` may have made it one)."""
        writers = self.node.get_publishers_info_by_topic(topic)
        best_effort = any(w.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                          for w in writers)
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                         else ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(msg_type, topic, callback, qos)

    def topics(self, prefix: str, until: Callable[[list[str]], bool]) -> list[str]:
        """The graph's topics under ``prefix`` once ``until(topics)`` holds, or as they are
        when the node's endpoints have had time to be announced."""
        end = min(self.deadline(), time.monotonic() + _ENDPOINTS_S)
        found: list[str] = []

        def look() -> bool:
            found[:] = sorted(t for t, _ in self.node.get_topic_names_and_types()
                              if t.startswith(prefix))
            return until(found)
        self.spin_until(look, end)
        return found

    def command_topic(self) -> str:
        """The node's vibration command topic: its one Float64MultiArray subscription as the
        graph shows it (a remap is followed), else ``<namespace>/vibration_cmd``."""
        topic: list[str] = []

        def look() -> bool:
            try:
                subs = self.node.get_subscriber_names_and_types_by_node(self.name,
                                                                         self.namespace)
            except Exception:   # noqa: BLE001 - the node is not in this graph's map yet
                return False
            topic[:] = [t for t, types in subs if _COMMAND_TYPE in types]
            return len(topic) == 1
        if self.spin_until(look, min(self.deadline(), time.monotonic() + _ENDPOINTS_S)):
            return topic[0]
        return self.namespace.rstrip('/') + '/vibration_cmd'

    def receive(self, topic: str, what: str, received: Callable[[], int], count: int) -> None:
        """Serve callbacks until ``received()`` reaches ``count``; each message may take
        ``timeout_s``."""
        seen = received()
        deadline = self.deadline()
        while seen < count:
            if not self.spin_until(lambda seen=seen: received() > seen, deadline):
                raise Refused(f'no {what} on {topic} within {self.timeout_s:g} s ({seen} of '
                              f'{count} received): paused? (feeder-sim node resume, or step); '
                              'busy compiling on a first run? (a longer --timeout)')
            seen, deadline = received(), self.deadline()


def _check_result(result, service: str) -> None:
    """A feeder_sim_interfaces Result that is not RESULT_OK, as a refusal."""
    if result.result != result.RESULT_OK:
        codes = {getattr(result, n): n for n in dir(result) if n.startswith('RESULT_')}
        why = result.error_message or codes.get(result.result, f'result {result.result}')
        raise Refused(f'{service} refused: {why}')


def _part_services():
    try:
        from feeder_sim_interfaces import srv
    except ImportError:
        raise Refused('the part services need feeder_sim_interfaces, not built in this venv: '
                      'python interfaces/build.py') from None
    return srv


_PART_HINT = ('its part services are off: feeder_sim_interfaces is not built where it runs; '
              'python interfaces/build.py there')


# -- subcommands ------------------------------------------------------------------------------

def _vibration(s: _Session, args: argparse.Namespace) -> None:
    from feeder_sim.model.vibration import CommandLimits, parse_command

    limits = [v.double_value for v in s.parameters(['max_amplitude_m', 'max_frequency_hz'])]
    if len(limits) != 2:
        raise Refused(f'{s.fqn} has no parameters max_amplitude_m, max_frequency_hz: not a '
                      'feeder_sim node? --node names the simulator, e.g. /cell1/feeder_sim')
    try:
        # the node's own check: what it would reject is refused here, with its reason
        amplitude, frequency = parse_command([args.amplitude, args.frequency],
                                             CommandLimits(*limits))
    except ValueError as err:
        limit = (f' (the limits are parameters of {s.fqn}: max_amplitude_m, '
                 'max_frequency_hz)' if 'limit' in str(err) else '')
        raise Refused(f'vibration: {err}{limit}') from None
    topic = args.topic or s.command_topic()
    pub = s.node.create_publisher(Float64MultiArray, topic,
                                  QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    # every reader the graph knows of matched, the node's among them, before the one message
    if not s.spin_until(lambda: pub.get_subscription_count() >= max(
            1, s.node.count_subscribers(topic)), s.deadline()):
        raise Refused(f'nothing subscribes to {topic} (waited {s.timeout_s:g} s): if the '
                      "node's vibration_cmd is remapped, give --topic")
    pub.publish(Float64MultiArray(data=[amplitude, frequency]))
    # the process ends right after: wait until the readers have the message
    if not pub.wait_for_all_acked(Duration(nanoseconds=round(s.timeout_s * 1e9))):
        raise Refused(f'the command on {topic} was not acknowledged within {s.timeout_s:g} s')
    print(f'vibration {amplitude:g} m at {frequency:g} Hz sent on {topic} (applied at the '
          "node's next frame)")


def _trigger(service: str, hint: str = '') -> Callable[[_Session, argparse.Namespace], None]:
    def command(s: _Session, args: argparse.Namespace) -> None:
        reply = s.call(Trigger, service, Trigger.Request())
        if not reply.success:
            raise Refused(f'{s.fqn}/{service} refused: {reply.message}{hint}')
        print(reply.message)
    return command


def _pause(data: bool) -> Callable[[_Session, argparse.Namespace], None]:
    def command(s: _Session, args: argparse.Namespace) -> None:
        reply = s.call(SetBool, 'pause', SetBool.Request(data=data))
        if not reply.success:
            raise Refused(f'{s.fqn}/pause refused: {reply.message}')
        print(reply.message)
    return command


def _list(s: _Session, args: argparse.Namespace) -> None:
    srv = _part_services()
    reply = s.call(srv.GetEntities, 'get_entities', srv.GetEntities.Request(), _PART_HINT)
    _check_result(reply.result, f'{s.fqn}/get_entities')
    for name in reply.entities:
        print(name)


def _spawn(s: _Session, args: argparse.Namespace) -> None:
    srv = _part_services()
    request = srv.SpawnEntity.Request(name=args.name or '', uri=args.template,
                                      allow_renaming=args.allow_renaming)
    if args.pose is not None:
        x, y, yaw = args.pose
        pose = request.initial_pose.pose
        pose.position.x, pose.position.y = x, y
        pose.orientation.z, pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    reply = s.call(srv.SpawnEntity, 'spawn_entity', request, _PART_HINT)
    _check_result(reply.result, f'{s.fqn}/spawn_entity')
    print(reply.entity_name)


def _delete(s: _Session, args: argparse.Namespace) -> None:
    srv = _part_services()
    reply = s.call(srv.DeleteEntity, 'delete_entity',
                   srv.DeleteEntity.Request(entity=args.name), _PART_HINT)
    _check_result(reply.result, f'{s.fqn}/delete_entity')
    print(f'deleted {args.name}')


_TRUE, _FALSE = ('true', 'yes', 'on', '1'), ('false', 'no', 'off', '0')
_KINDS = {ParameterType.PARAMETER_BOOL: ('a bool', 'true'),
          ParameterType.PARAMETER_INTEGER: ('a 64-bit integer', '3'),
          ParameterType.PARAMETER_DOUBLE: ('a double', '2.5'),
          ParameterType.PARAMETER_STRING: ('a string', 'text'),
          ParameterType.PARAMETER_BYTE_ARRAY: ('a byte array', '[1, 255]'),
          ParameterType.PARAMETER_BOOL_ARRAY: ('a bool array', '[true, false]'),
          ParameterType.PARAMETER_INTEGER_ARRAY: ('an integer array', '[1, 2]'),
          ParameterType.PARAMETER_DOUBLE_ARRAY: ('a double array', '[0.5, 1.0]'),
          ParameterType.PARAMETER_STRING_ARRAY: ('a string array', '[a, b]')}


def _scalar(text: str, kind: int):
    """``text`` as a value of the scalar parameter type ``kind``; ValueError if it is not."""
    if kind == ParameterType.PARAMETER_BOOL:
        if text.lower() in _TRUE + _FALSE:
            return text.lower() in _TRUE
        raise ValueError(text)
    if kind == ParameterType.PARAMETER_INTEGER:
        number = float(text)
        if not number.is_integer():
            raise ValueError(text)
        value = int(text) if text.lstrip('+-').isdigit() else int(number)
        if not -2**63 <= value < 2**63:
            raise ValueError(text)       # a ROS integer parameter is 64 bits
        return value
    if kind == ParameterType.PARAMETER_DOUBLE:
        return float(text)
    return text


def parameter_value(text: str, kind: int) -> ParameterValue:
    """``text`` as a ParameterValue of type ``kind`` (a parameter's current type); arrays as
    ``[a, b]`` or ``a,b``. ValueError when it cannot be one."""
    value = ParameterValue(type=kind)
    element = {ParameterType.PARAMETER_BYTE_ARRAY: ParameterType.PARAMETER_INTEGER,
               ParameterType.PARAMETER_BOOL_ARRAY: ParameterType.PARAMETER_BOOL,
               ParameterType.PARAMETER_INTEGER_ARRAY: ParameterType.PARAMETER_INTEGER,
               ParameterType.PARAMETER_DOUBLE_ARRAY: ParameterType.PARAMETER_DOUBLE,
               ParameterType.PARAMETER_STRING_ARRAY: ParameterType.PARAMETER_STRING}.get(kind)
    if element is None:
        field = {ParameterType.PARAMETER_BOOL: 'bool_value',
                 ParameterType.PARAMETER_INTEGER: 'integer_value',
                 ParameterType.PARAMETER_DOUBLE: 'double_value',
                 ParameterType.PARAMETER_STRING: 'string_value'}[kind]
        setattr(value, field, _scalar(text, kind))
        return value
    inner = text.strip().removeprefix('[').removesuffix(']')
    items = [_scalar(t.strip(), element) for t in inner.split(',') if t.strip()]
    if kind == ParameterType.PARAMETER_BYTE_ARRAY:
        value.byte_array_value = [bytes([i]) for i in items]   # ValueError beyond 0..255
    else:
        setattr(value, {ParameterType.PARAMETER_BOOL_ARRAY: 'bool_array_value',
                        ParameterType.PARAMETER_INTEGER_ARRAY: 'integer_array_value',
                        ParameterType.PARAMETER_DOUBLE_ARRAY: 'double_array_value',
                        ParameterType.PARAMETER_STRING_ARRAY: 'string_array_value'}[kind],
                items)
    return value


def _param(s: _Session, args: argparse.Namespace) -> None:
    name, text = args.name, args.value
    # an undeclared name: rclpy answers no value at all
    kind = next((v.type for v in s.parameters([name])), ParameterType.PARAMETER_NOT_SET)
    if kind == ParameterType.PARAMETER_NOT_SET:
        names = [n for n in s.call(ListParameters, 'list_parameters',
                                   ListParameters.Request()).result.names
                 if not n.startswith('qos_overrides.')]
        raise Refused(f'param {name}: {s.fqn} has no such parameter (its parameters: '
                      f'{", ".join(sorted(names))})')
    what, example = _KINDS[kind]
    try:
        value = parameter_value(text, kind)
    except (ValueError, OverflowError, AssertionError):   # rosidl checks ranges by assert
        raise Refused(f'param {name}: {text!r} is not {what}; {name} is {what} on {s.fqn} '
                      f'(e.g. {example})') from None
    reply = s.call(SetParameters, 'set_parameters',
                   SetParameters.Request(parameters=[ParameterMsg(name=name, value=value)]))
    result = reply.results[0]
    if not result.successful:
        raise Refused(f'param {name}: {s.fqn} refused {text}: {result.reason or "no reason"}')
    print(f'{name} = {parameter_value_to_python(value)!r}')


def _stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _echo_poses(s: _Session, count: int) -> None:
    poses_topic, names_topic = f'{s.fqn}/part_poses', f'{s.fqn}/track_state'
    s.topics(poses_topic, lambda found: poses_topic in found and names_topic in found)
    # PoseArray carries no names: the frame's JointState (same stamp) names its parts
    names: dict[int, list[str]] = {}
    waiting: dict[int, PoseArray] = {}
    printed, named = [0], [False]

    def show(stamp: int, part_names: list[str] | None) -> None:
        msg = waiting.pop(stamp)
        # older frames whose names never came (sent before the names reader matched) are
        # dropped: printed later they would be out of order
        for old in [t for t in waiting if t < stamp]:
            del waiting[old]
        if part_names is None or len(part_names) != len(msg.poses):
            part_names = [str(i) for i in range(len(msg.poses))]
        if printed[0] < count:
            lines = [f'--- t = {stamp / 1e9:.9g} s']
            for name, p in zip(part_names, msg.poses, strict=True):
                q = p.orientation
                yaw = math.remainder(2.0 * math.atan2(q.z, q.w), math.tau)
                lines.append(f'{name} {p.position.x:.9g} {p.position.y:.9g} {yaw:.9g}')
            print('\n'.join(lines), flush=True)
            printed[0] += 1

    def on_poses(msg: PoseArray) -> None:
        stamp = _stamp_ns(msg.header)
        waiting[stamp] = msg
        if stamp in names:
            show(stamp, names.pop(stamp))
        elif not named[0] and len(waiting) > 50:
            # frames go on and no names ever come (track_state not reaching us): indices
            show(min(waiting), None)

    def on_names(msg: JointState) -> None:
        named[0] = True
        stamp = _stamp_ns(msg.header)
        if stamp in waiting:
            show(stamp, list(msg.name))
        else:
            names[stamp] = list(msg.name)
        for old in [t for t in names if t < stamp - 1_000_000_000]:
            del names[old]      # a second of frames back: their poses are not coming

    s.subscribe(PoseArray, poses_topic, on_poses)
    s.subscribe(JointState, names_topic, on_names)
    s.receive(poses_topic, 'frame', lambda: printed[0], count)


def _echo_sensor(s: _Session, sensor: str, count: int) -> None:
    prefix = f'{s.fqn}/sensors/'
    mine = f'{prefix}{sensor}/'
    # the node's other topics seen: its sensors' are announced too by then
    found = s.topics(prefix, lambda topics: any(t.startswith(mine) for t in topics))
    topics = [t for t in found if t.startswith(mine) and t[len(mine):] in _SENSOR_TYPES]
    if not topics:
        others = sorted({t[len(prefix):].split('/')[0] for t in found})
        raise Refused(f'echo sensor {sensor}: {s.fqn} has no such sensor ('
                      + (f'its sensors: {", ".join(others)}' if others else
                         "its scene has no sensors") + ')')
    lines = [0]

    def printer(kind: str) -> Callable:
        def on_message(msg) -> None:
            if lines[0] >= count:
                return
            if kind == 'passed':
                text = f'{msg.key} {msg.value}'
            elif kind == 'blocked':
                text = 'true' if msg.data else 'false'
            else:
                text = str(msg.data)
            print(f'{kind} {text}', flush=True)
            lines[0] += 1
        return on_message

    for topic in topics:
        kind = topic[len(mine):]
        # the node keeps 100 of a sensor's messages: none of a burst is lost here either
        s.subscribe(_SENSOR_TYPES[kind], topic, printer(kind), depth=100)
    s.receive(mine + '*', 'message', lambda: lines[0], count)


def _echo(s: _Session, args: argparse.Namespace) -> None:
    if args.count < 1:
        raise Refused(f'--count {args.count}: must be at least 1')
    if args.what == 'poses' and args.name:
        raise Refused(f'echo poses {args.name}: poses takes no name (echo sensor NAME does)')
    if args.what == 'sensor' and not args.name:
        raise Refused("echo sensor: give the sensor's name, e.g. echo sensor beam")
    s.wait_for_node()
    if args.what == 'poses':
        _echo_poses(s, args.count)
    else:
        _echo_sensor(s, args.name, args.count)


COMMANDS: dict[str, Callable[[_Session, argparse.Namespace], None]] = {
    'vibration': _vibration,
    'pause': _pause(True),
    'resume': _pause(False),
    'step': _trigger('step', ' (feeder-sim node pause)'),
    'reset': _trigger('reset'),
    'list': _list,
    'spawn': _spawn,
    'delete': _delete,
    'param': _param,
    'echo': _echo,
}


def run(args: argparse.Namespace) -> int:
    """Run ``feeder-sim node <args.command>``: 0 done, 2 refused or no answer (one line on
    stderr), 130 interrupted."""
    try:
        with _Session(args.node, args.timeout) as session:
            COMMANDS[args.command](session, args)
        return 0
    except Refused as err:
        print(f'feeder-sim: error: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
