"""``ros2 run feeder_sim sim_node``: the simulator as a ROS 2 node that owns ``/clock``.

The node is a thin shell over :class:`feeder_sim.simulator.Simulator`. Simulated time advances
in frames of ``1 / publish_rate`` seconds; after each frame the node publishes the state,
stamped with simulated time, and appends it to the MCAP log. Physics never reads a ROS clock:
the wall clock only paces the frames (``real_time_factor``; 0 runs as fast as possible), so the
same scene with the same commands at the same simulated times gives the same log (with
``log_time:=sim``; by default log times start at the recording's wall-clock time).

Topics (relative to the node's namespace; ``~`` is the node name)::

    /clock                  rosgraph_msgs/Clock           simulated time, once per frame
    ~/part_poses            geometry_msgs/PoseArray       one pose per part, scene order
    ~/contacts              sensor_msgs/PointCloud2       one point per contact, impulses N s
    ~/part_impulses         sensor_msgs/PointCloud2       impulse totals per part
    ~/track_state           sensor_msgs/JointState        position/speed along the track
    ~/markers               visualization_msgs/MarkerArray  part outlines and impulse arrows
    ~/geometry              visualization_msgs/MarkerArray  static bodies (latched)
    /diagnostics            diagnostic_msgs/DiagnosticArray real-time factor, solver health
    ~/sensors/<name>/blocked  std_msgs/Bool               a scene's beam: an outline cuts it
    ~/sensors/<name>/count  std_msgs/UInt32               parts that passed a scene's sensor
    ~/sensors/<name>/passed diagnostic_msgs/KeyValue      inspection: part, orientation
    vibration_cmd (in)      std_msgs/Float64MultiArray    [amplitude_m, frequency_hz]

Services: ``~/reset`` (Trigger), ``~/pause`` (SetBool), ``~/step`` (Trigger, while paused),
and, where feeder_sim_interfaces is built, ``~/spawn_entity``, ``~/delete_entity``,
``~/set_entity_state``, ``~/get_entities`` (parts while running).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import functools
import inspect
import math
import os
import signal
import sys
import threading
import time
import traceback

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray
import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import Bool, Float64MultiArray, UInt32
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

from feeder_sim.compiled.jit import in_first_use, kernel_load_seconds
from feeder_sim.model.scene import METHODS, SceneError
from feeder_sim.model.vibration import (
    CommandLimits,
    MAX_AMPLITUDE_M,
    MAX_FREQUENCY_HZ,
    parse_command,
)
from feeder_sim.model.world import DYNAMIC
from feeder_sim.output import frames
from feeder_sim.output.frames import Frame, open_recorder, record_frame
from feeder_sim.output.recording import RecordingError, SENSOR_TOPICS
from feeder_sim.ros import messages as msgs
from feeder_sim.simulator import Simulator, UnknownPart

NODE_NAME = 'feeder_sim'
_NS = 1_000_000_000
# Longest stretch of physics before commands and services are served (wall s). Each return
# to the executor costs a wait-set rebuild (about a millisecond in rclpy), so a free-running
# node takes longer turns than a paced one, which is idle most of the time anyway.
_WALL_BUDGET_S = 0.01
# Every request a service receives is kept until it is answered (rclpy's default keeps the
# last 10: 90 of 100 resets sent at once were dropped unanswered); each is answered in its
# turn, between frames. A reliable client is held back by the middleware's flow control
# rather than losing requests.
_SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
_WALL_BUDGET_FREE_S = 0.025
_MAX_LAG_S = 0.25          # wall time behind schedule after which pacing forgets the debt
_NAMESAKE_WINDOW_S = 10.0  # after start-up, the node looks this long for a namesake (DDS
#                            discovery on a loaded machine takes seconds)
_SLOW_PERIODS = 3          # diagnostics periods below the requested rate before a warning
# A frame expected to take longer than _SLICE_ABOVE_S runs in slices of about _SLICE_WALL_S,
# so that SIGINT/SIGTERM end the node within a second. A cheaper one runs whole, as the bare
# simulator runs it (slices change event_driven's bits): a stall of the machine of a few
# tenths of a second must not slice the frames after it.
_SLICE_ABOVE_S = 0.5
_SLICE_WALL_S = 0.1
_SLICE_FIRST_STEPS = 20_000  # steps of a time-stepped method tried before any cost is known
# A stop that arrives while a kernel compiles (a minute on a cold cache, not cut short) ends
# the node from another thread: the log finalized, exit status 0, within this second.
_FIRST_USE_POLL_S = 0.05


@dataclass(frozen=True)
class _Param:
    name: str
    default: object
    description: str
    read_only: bool = True
    low: float | None = None
    high: float | None = None


PARAMETERS = (
    _Param('scene', 'track_one_box', 'scene file path, or the name of a scene shipped in config/'),
    _Param('record_path', '', 'MCAP file to write; empty = no recording'),
    _Param('real_time_factor', 1.0, 'simulated seconds per wall second; 0 = as fast as possible',
           read_only=False, low=0.0, high=1000.0),
    _Param('duration', 0.0, 'stop cleanly after this much simulated time (s); 0 = never',
           low=0.0, high=1e9),
    _Param('publish_rate', 100.0, 'frames per simulated second: state is published and recorded '
           'once per frame', low=0.1, high=100000.0),
    _Param('method', '', "override solver.method of the scene ('' keeps the scene's)"),
    _Param('time_step', 0.0, "override solver.time_step of the scene (s); 0 keeps the scene's",
           low=0.0, high=1.0),
    _Param('frame_id', 'world', 'frame of every published pose, point and marker'),
    _Param('start_paused', False, 'start paused (use ~/pause or ~/step)'),
    _Param('steps_per_call', 1, 'frames advanced by one ~/step call', read_only=False,
           low=1, high=1000000),
    _Param('max_amplitude_m', MAX_AMPLITUDE_M,
           'largest vibration amplitude accepted on vibration_cmd (m)',
           read_only=False, low=0.0, high=MAX_AMPLITUDE_M),
    _Param('max_frequency_hz', MAX_FREQUENCY_HZ, 'largest vibration frequency accepted (Hz)',
           read_only=False, low=0.0, high=MAX_FREQUENCY_HZ),
    _Param('on_record_error', 'continue', "when the log cannot be written: 'continue' "
           "simulating without it, or 'stop' the node (exit status 1)"),
    _Param('log_time', 'wall', "MCAP log times: 'wall' (the recording's start plus the simulated "
           "time: viewers show dates) or 'sim' (simulated time alone: reproducible files)"),
    _Param('record_flush_period', 1.0, 'wall seconds after which the open MCAP chunk is written '
           'out, bounding what a hard kill loses', low=0.01, high=3600.0),
    _Param('marker_rate', 20.0, 'wall-clock Hz at which ~/markers (outlines, impulse arrows) '
           'follow the frames; 0 = no markers', read_only=False, low=0.0, high=1000.0),
    _Param('impulse_marker_scale', 0.0, 'arrow length per impulse (m per N s); 0 = a part size '
           "for a contact carrying one part's weight for one frame", read_only=False,
           low=0.0, high=1e9),
    _Param('diagnostics_period', 1.0, 'wall seconds between /diagnostics messages',
           low=0.01, high=3600.0),
)


def _descriptor(p: _Param) -> ParameterDescriptor:
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.low is not None:
        if isinstance(p.default, int) and not isinstance(p.default, bool):
            d.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=0)]
        else:
            d.floating_point_range = [FloatingPointRange(from_value=float(p.low),
                                                         to_value=float(p.high), step=0.0)]
    return d


_DOUBLES = {p.name for p in PARAMETERS if isinstance(p.default, float)}


def _as_declared(param: Parameter) -> Parameter:
    """An integer given for a double parameter, as that double."""
    if param.name in _DOUBLES and param.type_ == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    return param


def usage() -> str:
    """``sim_node --help``: how to run it and every parameter with its default."""
    lines = ['usage: ros2 run feeder_sim sim_node [--help] [--ros-args -p NAME:=VALUE ...]', '',
             'Simulates a feeder scene and publishes it over ROS 2 (see the README for the',
             'topics and services). Parameters (default):']
    for p in PARAMETERS:
        lines.append(f'  {p.name} ({p.default!r}): {p.description}')
    return '\n'.join(lines)


def _failure(request, response, sentence: str):
    """The failure answer of a service type: a Result's RESULT_OPERATION_FAILED (the part
    services), success = false (Trigger, SetBool), or the type's default answer."""
    if hasattr(response, 'result') and hasattr(response.result, 'error_message'):
        response.result.result = response.result.RESULT_OPERATION_FAILED
        response.result.error_message = sentence
    elif hasattr(response, 'success'):
        response.success = False
        if hasattr(response, 'message'):
            response.message = sentence
    return response


def _nothing(*args) -> None:
    return None


class SimNode(Node):
    """The ``feeder_sim`` node. Construct after ``rclpy.init``; ``close()`` finalizes the log.

    ``done`` becomes true when ``duration`` is reached (or the log failed with
    ``on_record_error: stop``); ``exit_code`` is then what the process should return.
    """

    def __init__(self, **node_options) -> None:
        # before Node.__init__: the parameter services it creates are guarded too
        self.callback_exceptions = 0
        self._exception_types: set[str] = set()
        self._last_exception = ''
        super().__init__(NODE_NAME, **node_options)
        try:
            self._set_up()
        except BaseException:
            # A node that failed to start leaves the graph now: left to the garbage collector,
            # its name would stay visible for an unknown time, and a node started after it
            # would take it for a namesake and refuse to run.
            if hasattr(self, '_closing'):
                self.close()
            self.destroy_node()
            raise

    def _set_up(self) -> None:
        # `-p duration:=20` arrives as an INTEGER: a whole number is a fine double
        for name, given in list(self._parameter_overrides.items()):
            self._parameter_overrides[name] = _as_declared(given)
        self.add_pre_set_parameters_callback(
            lambda params: [_as_declared(p) for p in params])
        for p in PARAMETERS:
            self.declare_parameter(p.name, p.default, _descriptor(p))
        value = {p.name: self.get_parameter(p.name).value for p in PARAMETERS}
        if value['method'] and value['method'] not in METHODS:
            raise ValueError(f"parameter method must be one of {', '.join(METHODS)} or '', got "
                             f"{value['method']!r}")
        if value['log_time'] not in ('wall', 'sim'):
            raise ValueError("parameter log_time must be 'wall' or 'sim', got "
                             f"{value['log_time']!r}")
        if value['on_record_error'] not in ('continue', 'stop'):
            raise ValueError("parameter on_record_error must be 'continue' or 'stop', got "
                             f"{value['on_record_error']!r}")
        self.sim = Simulator(value['scene'], method=value['method'] or None,
                             time_step=value['time_step'] or None)
        self.frame_id: str = value['frame_id']
        self.period_ns = max(1, round(_NS / value['publish_rate']))
        if value['duration'] > 0:
            self.sim.check_duration(value['duration'], 'parameter duration')
        self.duration_ns = round(value['duration'] * _NS)
        self._frame_timer = None
        self.paused = value['start_paused']
        # ~/step requests not answered yet: [frames left, future answered when they are done]
        self._steps_asked: list[list] = []
        self.done = False
        # set by main() from SIGINT/SIGTERM: long physics is cut into slices that look at it
        self.stop = threading.Event()
        self._wall_per_sim_s: float | None = None    # measured cost of simulated time
        self.exit_code = 0
        self.frames = 0
        self.commands_accepted = 0
        self.commands_rejected = 0
        self._pending_command: tuple[float, float] | None = None
        self._on_record_error = value['on_record_error']
        self._rtf = value['real_time_factor']
        self._limits = CommandLimits(value['max_amplitude_m'], value['max_frequency_hz'])
        self._record_status = 'off'
        self.recorder = None
        self._closing = threading.Lock()   # the loop and a stop during first use both close
        if value['record_path']:
            self._open_recording(value['record_path'], value['record_flush_period'],
                                 value['log_time'])

        self._parts = self.sim.part_indices
        self._line_width, self._auto_impulse_scale = self._marker_sizes()
        self._last_markers = -np.inf
        self._world = None
        self._outlines = msgs.Outlines(self.frame_id, self._line_width)
        self._s_start: dict[str, float] = {}   # where each part started along the track, m
        self._gone: list[str] = []          # parts taken away since the last markers
        self._follow_parts()
        self.add_on_set_parameters_callback(self._on_set_parameters)

        overridable = QoSOverridingOptions.with_default_policies()

        def stream() -> QoSProfile:
            # A profile per publisher: rclpy writes QoS overrides into the object it is given.
            return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)

        self.pub_clock = self.create_publisher(
            ClockMsg, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.pub_poses = self.create_publisher(
            PoseArray, '~/part_poses', stream(), qos_overriding_options=overridable)
        self.pub_contacts = self.create_publisher(
            PointCloud2, '~/contacts', stream(), qos_overriding_options=overridable)
        self.pub_impulses = self.create_publisher(
            PointCloud2, '~/part_impulses', stream(), qos_overriding_options=overridable)
        self.pub_track = self.create_publisher(
            JointState, '~/track_state', stream(), qos_overriding_options=overridable)
        self.pub_markers = self.create_publisher(
            MarkerArray, '~/markers', stream(), qos_overriding_options=overridable)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_geometry = self.create_publisher(MarkerArray, '~/geometry', latched)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # the scene's sensors: a frame's reading on each topic of its kind (recording.py's
        # SENSOR_TOPICS); every passing part is a message, none is dropped
        self.sensors = frames.sensor_bank(self.sim)
        frames.read_sensors(self.sim, self.sensors)
        self.pub_sensors: dict[str, dict[str, Publisher]] = {}
        for spec in self.sensors.specs:
            types = {'blocked': Bool, 'count': UInt32, 'passed': KeyValue}
            self.pub_sensors[spec.name] = {
                suffix: self.create_publisher(types[suffix], f'~/sensors/{spec.name}/{suffix}',
                                              QoSProfile(depth=100,
                                                         reliability=ReliabilityPolicy.RELIABLE))
                for suffix, _ in SENSOR_TOPICS[spec.kind]}
        self.create_subscription(Float64MultiArray, 'vibration_cmd', self._on_vibration_cmd,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
                                 qos_overriding_options=overridable)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(SetBool, '~/pause', self._on_pause)
        # its own group: a step request waits for its frames without holding the default
        # group, in which the frame timer runs them and the other services are answered
        self.create_service(Trigger, '~/step', self._on_step,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self._create_part_services()

        # Pacing and diagnostics run on the steady clock: with use_sim_time set on this node
        # a ROS-time timer would wait for the /clock the node itself has to publish.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._anchor()
        self._diag_wall = time.perf_counter()
        self._diag_sim_ns = self.t_ns
        self._rtf_achieved = 0.0
        self._slow_periods = 0
        self._rtf_told: float | None = None
        # off while paused with no step to take: an idle 1 ms tick would take turns with
        # every request the services answer
        self._frame_timer = self.create_timer(0.001, self._on_timer, clock=steady)
        if self.paused:
            self._frame_timer.cancel()
        self.create_timer(value['diagnostics_period'], self._publish_diagnostics, clock=steady)
        self._started_wall = time.perf_counter()
        self._clock_shared = False
        self._namesake_since: float | None = None
        self._namesake_timer = self.create_timer(0.2, self._look_for_namesakes, clock=steady)
        self._publish_geometry()
        self._publish_frame(Frame.take(self.sim, self.sensors))
        self.get_logger().info(
            f"scene '{self.sim.scene.name}' ({self.sim.method}, step "
            f'{self.sim.scene.solver.time_step:g} s, {len(self._parts)} parts), '
            f'{1e9 / self.period_ns:g} frames per simulated s, real-time factor {self._rtf:g}'
            + (f', recording to {self.recorder.path}' if self.recorder else '')
            + (', paused' if self.paused else ''))

    # -- callbacks: an exception in one never ends the node ---------------------------------

    def _guarded(self, callback: Callable, where: str,
                 failed: Callable[..., object]) -> Callable:
        """``callback`` such that an exception it raises (a bug, a request no check foresaw)
        is logged once per type, counted in /diagnostics and answered by ``failed(*args,
        sentence)``; rclpy would let it out of ``spin_once`` and end the node."""
        if inspect.iscoroutinefunction(callback):
            @functools.wraps(callback)
            async def guarded_async(*args):
                try:
                    return await callback(*args)
                except ExternalShutdownException:
                    raise
                except Exception as err:   # noqa: BLE001 - any type: none may end the node
                    return failed(*args, self._unexpected(where, err))
            return guarded_async

        @functools.wraps(callback)
        def guarded(*args):
            try:
                return callback(*args)
            except ExternalShutdownException:
                raise
            except Exception as err:   # noqa: BLE001 - any type: none may end the node
                return failed(*args, self._unexpected(where, err))
        return guarded

    def _unexpected(self, where: str, err: Exception) -> str:
        """Count and log (once per type) an exception a callback let out; the sentence that
        answers a request with it."""
        kind = type(err).__name__
        text = ' '.join(str(err).split())[:300] or 'no message'
        sentence = f'{where} failed unexpectedly: {kind}: {text}'
        self.callback_exceptions += 1
        self._last_exception = sentence
        if kind not in self._exception_types:
            self._exception_types.add(kind)
            self.get_logger().error(f'{sentence}; refused, counted in /diagnostics '
                                    '(callback_exceptions), the node runs on')
            self.get_logger().debug(''.join(traceback.format_exception(err)))
        return sentence

    def create_service(self, srv_type, srv_name: str, callback: Callable, **kwargs):
        """A service whose callback is guarded (:meth:`_guarded`): an unexpected exception is
        answered with the type's failure (a Result's RESULT_OPERATION_FAILED, success =
        false) and the sentence; its queue keeps every request (KEEP_ALL)."""
        kwargs.setdefault('qos_profile', _SERVICE_QOS)
        return super().create_service(
            srv_type, srv_name, self._guarded(
                callback, f'service {self.resolve_service_name(srv_name)}', _failure),
            **kwargs)

    def create_subscription(self, msg_type, topic: str, callback: Callable, *args, **kwargs):
        return super().create_subscription(
            msg_type, topic, self._guarded(
                callback, f'subscription {self.resolve_topic_name(topic)}', _nothing),
            *args, **kwargs)

    def create_timer(self, timer_period_sec: float, callback: Callable, *args, **kwargs):
        name = getattr(callback, '__name__', 'timer')
        return super().create_timer(
            timer_period_sec, self._guarded(callback, f'timer {name}', _nothing), *args,
            **kwargs)

    def add_on_set_parameters_callback(self, callback: Callable) -> None:
        super().add_on_set_parameters_callback(self._guarded(
            callback, 'parameter change',
            lambda params, sentence: SetParametersResult(successful=False, reason=sentence)))

    def add_pre_set_parameters_callback(self, callback: Callable) -> None:
        super().add_pre_set_parameters_callback(self._guarded(
            callback, 'parameter change', lambda params, sentence: params))

    # -- time ------------------------------------------------------------------------------

    @property
    def t_ns(self) -> int:
        """Simulated time of the current frame, ns."""
        return round(self.sim.t * _NS)

    def _anchor(self) -> None:
        self._anchor_wall = time.perf_counter()
        self._anchor_sim_ns = self.t_ns

    @property
    def paused(self) -> bool:
        """Whether frames wait for ~/pause false or a ~/step (settable from Python too)."""
        return self._paused

    @paused.setter
    def paused(self, value: bool) -> None:
        self._paused = bool(value)
        if self._frame_timer is not None:
            if self._paused and not self._steps_asked:
                self._frame_timer.cancel()
            else:
                self._frame_timer.reset()

    def _on_timer(self) -> None:
        if self.paused and self._steps_asked:
            self._step_while_paused()
        if self.paused or self.done:
            return
        start = time.perf_counter()
        # The context goes invalid when SIGINT/SIGTERM arrive; stop publishing right there.
        while not self.done and self.context.ok() and not self.stop.is_set():
            now = time.perf_counter()
            if self._rtf > 0.0:
                due_ns = self._anchor_sim_ns + self._rtf * (now - self._anchor_wall) * _NS
                if self.t_ns + self.period_ns > due_ns:
                    break
                if (due_ns - self.t_ns) / _NS / self._rtf > _MAX_LAG_S:
                    # Too slow for the requested factor: run flat out, without a debt to
                    # repay later by running faster than asked.
                    self._anchor()
            if now - start > (_WALL_BUDGET_S if self._rtf > 0.0 else _WALL_BUDGET_FREE_S):
                break
            self.advance_frame()

    def advance_frame(self) -> None:
        """Apply the pending command, simulate one frame, publish and record it."""
        if self._pending_command is not None:
            amplitude_m, frequency_hz = self._pending_command
            self._pending_command = None
            self.sim.command_vibration(amplitude_m, frequency_hz)
            self._record(lambda r: r.write_vibration_cmd(self.t_ns, amplitude_m, frequency_hz))
        t_next_ns = self.t_ns + self.period_ns
        if self.duration_ns:
            t_next_ns = min(t_next_ns, self.duration_ns)    # the last frame may be shorter
        if not self._advance_to(t_next_ns / _NS):
            return
        self.frames += 1
        self._publish_frame(Frame.take(self.sim, self.sensors))
        if self.duration_ns and self.t_ns >= self.duration_ns:
            s, _ = self.sim.track_coordinates()
            names = self.sim.part_poses()[0]
            feed = ', '.join(f'{name} {1e3 * (b - self._s_start[name]) / self.sim.t:.2f} mm/s'
                             for name, b in zip(names[:5], s))
            self.get_logger().info(f'duration reached: t = {self.sim.t:.6g} s simulated; mean '
                                   f'speed along the track: {feed}'
                                   + (' ...' if len(s) > 5 else ''))
            self.close()
            self.done = True

    def _advance_to(self, t_end: float) -> bool:
        """Simulate to ``t_end`` (s); False if a stop request cut it short.

        A frame expected to cost more than ``_SLICE_ABOVE_S`` of wall time (a tiny time step,
        a slow scene) runs in slices of about ``_SLICE_WALL_S``, so SIGINT/SIGTERM end the
        node within a second whatever the frame costs. Frames that are cheaper run whole, as
        the bare simulator runs them, to the bit."""
        sim = self.sim
        wall_per_s = self._wall_per_sim_s
        if wall_per_s is None and sim.stepping.fixed_steps:
            # not measured yet: a guess from the number of steps
            wall_per_s = _SLICE_WALL_S / (_SLICE_FIRST_STEPS * sim.scene.solver.time_step)
        while True:
            if self.stop.is_set():
                return False
            remaining = span = t_end - sim.t
            if wall_per_s is not None and span * wall_per_s > _SLICE_ABOVE_S:
                # whole steps: a time-stepped method's grid is not cut by a slice
                h = sim.scene.solver.time_step
                span = max(1, math.floor(_SLICE_WALL_S / wall_per_s / h)) * h
            last = span >= remaining
            t0, wall0, load0 = sim.t, time.perf_counter(), kernel_load_seconds()
            sim.advance_to(t_end if last else t0 + span)
            if sim.t > t0 and kernel_load_seconds() == load0:
                # a span that loaded or compiled kernels measures their first use (0.6 s for
                # one box's first 10 ms frame), not the next frames: counted, it sliced the
                # frames after it in a process's first run only, and changed their bits
                measured = (time.perf_counter() - wall0) / (sim.t - t0)
                wall_per_s = self._wall_per_sim_s = (
                    measured if self._wall_per_sim_s is None
                    else 0.7 * self._wall_per_sim_s + 0.3 * measured)
            if last:
                return True

    # -- publishing ------------------------------------------------------------------------

    def _follow_parts(self) -> None:
        """Sources, sinks or a reset changed the parts: follow them (indices, outlines; the
        markers of parts that left are deleted with the next markers)."""
        world = self.sim.world
        if world is self._world:
            return
        if self._world is not None:
            self._gone += sorted(set(self._world.names) - set(world.names))
        self._world = world
        self._parts = self.sim.part_indices
        self._others = np.flatnonzero(world.body_type != DYNAMIC)
        self._outlines.follow([b.outlines for b in world.scene.bodies], world.names)
        for name, s0 in zip(self.sim.part_poses()[0], self.sim.track_coordinates()[0]):
            self._s_start.setdefault(name, s0)

    def _publish_frame(self, frame: Frame) -> None:
        self._follow_parts()
        t_ns, contacts = frame.t_ns, frame.contacts
        # A message nobody subscribes to is not built: serializing it is most of the cost.
        if self.pub_clock.get_subscription_count():
            self.pub_clock.publish(msgs.clock(t_ns))
        if self.pub_poses.get_subscription_count():
            self.pub_poses.publish(msgs.pose_array(t_ns, frame.origin, frame.angle,
                                                   self.frame_id))
        if self.pub_contacts.get_subscription_count():
            self.pub_contacts.publish(msgs.contact_cloud(t_ns, contacts, self.frame_id))
        if self.pub_impulses.get_subscription_count():
            self.pub_impulses.publish(msgs.part_impulse_cloud(
                t_ns, frame.impulses, frame.centre_of_mass, self.frame_id))
        if self.pub_track.get_subscription_count():
            self.pub_track.publish(msgs.track_state(t_ns, frame.names, frame.s, frame.speed))
        if self.pub_markers.get_subscription_count():
            self._publish_markers(frame)
        for reading in frame.sensors:
            pubs = self.pub_sensors[reading.name]
            if 'blocked' in pubs:
                pubs['blocked'].publish(Bool(data=reading.blocked))
            pubs['count'].publish(UInt32(data=reading.count))
            for part, orientation in reading.passed if 'passed' in pubs else ():
                pubs['passed'].publish(KeyValue(key=part, value=orientation))
        self._record(lambda r: record_frame(r, frame))

    def _publish_markers(self, frame: Frame) -> None:
        # RViz redraws a few tens of times per second: markers for every frame would cost
        # more than the physics of a small scene, so they follow the frames at marker_rate.
        rate = self.get_parameter('marker_rate').value
        now = time.perf_counter()
        if rate <= 0.0 or now - self._last_markers < 1.0 / rate:
            return
        self._last_markers = now
        markers = [msgs.delete_markers(frame.t_ns, name, self.frame_id) for name in self._gone]
        self._gone = []
        markers += self._outlines.markers(frame.t_ns, self._parts, frame.origin, frame.angle)
        markers += msgs.impulse_arrows(frame.t_ns, frame.contacts, self._impulse_scale(),
                                       self.frame_id, 0.1 * self._line_width)
        self.pub_markers.publish(msgs.marker_array(markers))

    def _publish_geometry(self) -> None:
        origin, angle = self.sim.world.body_frame_pose(self.sim.state)
        markers = self._outlines.markers(self.t_ns, self._others, origin[self._others],
                                         angle[self._others], grey=True)
        self.pub_geometry.publish(msgs.marker_array(markers))

    def _impulse_scale(self) -> float:
        scale = self.get_parameter('impulse_marker_scale').value
        return scale if scale > 0.0 else self._auto_impulse_scale

    def _marker_sizes(self) -> tuple[float, float]:
        """Outline line width (m) and the automatic arrow scale (m per N s)."""
        world = self.sim.world
        if not len(self._parts):
            return 1e-3, 0.0
        size = 2.0 * float(np.median(world.radius[self._parts]))
        weight_impulse = (float(np.median(world.mass[self._parts]))
                          * max(float(np.linalg.norm(world.gravity)), 1e-3)
                          * self.period_ns / _NS)
        return 0.025 * size, size / weight_impulse

    def _publish_diagnostics(self) -> None:
        now = time.perf_counter()
        wall = now - self._diag_wall
        if wall > 0:
            self._rtf_achieved = (self.t_ns - self._diag_sim_ns) / _NS / wall
        self._diag_wall, self._diag_sim_ns = now, self.t_ns
        slow = self._below_requested_rate()
        stats = self.sim.stats
        level, message = DiagnosticStatus.OK, 'running'
        if slow:
            level, message = DiagnosticStatus.WARN, slow
        if self.paused:
            message = 'paused'
        if self.done:
            message = 'finished'
        if self._record_status.startswith('failed'):
            level, message = DiagnosticStatus.ERROR, f'recording {self._record_status}'
        elif inexact := stats.inexact():
            # a fallback changed the physics (friction lost): an error the user must see
            level, message = DiagnosticStatus.ERROR, '; '.join(inexact.values())
        elif stats.fallbacks or stats.unconverged:
            level, message = DiagnosticStatus.WARN, (
                f'{stats.fallbacks} solver fallbacks, {stats.unconverged} unconverged solves')
        elif self.callback_exceptions:
            level, message = DiagnosticStatus.WARN, (
                f'{self.callback_exceptions} unexpected exceptions in callbacks, the last: '
                f'{self._last_exception}')
        name, values = 'feeder_sim: simulation', self.status()
        self.pub_diagnostics.publish(msgs.diagnostics(self.t_ns, name, level, message, values))
        self._record(lambda r: r.write_diagnostics(
            self.t_ns, name, int.from_bytes(level, 'little') if isinstance(level, bytes)
            else int(level), message, msgs.key_values(values)))

    def _look_for_namesakes(self) -> None:
        """While starting up: refuse to run beside another node of the same name (their
        services and parameters would be one), warn when another node publishes our clock
        (two simulated times would interleave on it)."""
        if time.perf_counter() - self._started_wall > _NAMESAKE_WINDOW_S or self.done:
            self._namesake_timer.cancel()
            return
        me = (self.get_name(), self.get_namespace())
        seen = self.get_node_names_and_namespaces().count(me) > 1
        # seen for a second on end: not a node of a run that just ended, still in the graph
        self._namesake_since = (self._namesake_since or time.perf_counter()) if seen else None
        if seen and time.perf_counter() - self._namesake_since >= 1.0:
            name = self.get_fully_qualified_name()
            self.get_logger().error(
                f'another node named {name} is running; this one stops. Start it in its own '
                'namespace with its own clock: --ros-args -r __ns:=/cell2 -r /clock:=/cell2/clock')
            self._namesake_timer.cancel()
            self.close()
            self.done, self.exit_code = True, 2
            return
        clock = self.pub_clock.topic_name
        if not self._clock_shared and self.count_publishers(clock) > 1:
            self._clock_shared = True
            self.get_logger().warning(
                f'another node publishes {clock}: two simulated times would interleave there. '
                f'Remap this one: --ros-args -r {clock}:=<namespace>{clock}')

    def _below_requested_rate(self) -> str:
        """'' or why the run is slower than asked: the achieved real-time factor stayed under
        90 % of the requested one for _SLOW_PERIODS diagnostics periods (logged once per
        requested factor)."""
        running = not (self.paused or self.done) and self._rtf > 0.0
        if running and self._rtf_achieved < 0.9 * self._rtf:
            self._slow_periods += 1
        else:
            self._slow_periods = 0
        if self._slow_periods < _SLOW_PERIODS:
            return ''
        text = (f'real-time factor {self._rtf_achieved:.3g} achieved, {self._rtf:g} requested: '
                'the scene is too slow for it on this machine')
        if self._rtf_told != self._rtf:
            self._rtf_told = self._rtf
            self.get_logger().warning(text + ' (real_time_factor 0 runs as fast as possible)')
        return text

    def status(self) -> dict[str, object]:
        """What /diagnostics reports: pacing, solver health, commands, recording."""
        stats = self.sim.stats
        return {
            'simulated_time_s': self.sim.t,
            'real_time_factor_requested': float(self._rtf),
            'real_time_factor_achieved': float(self._rtf_achieved),
            'paused': self.paused,
            'frames': self.frames,
            'method': self.sim.method,
            'lcp_solves': stats.lcp_solves,
            'solver_fallbacks': stats.fallbacks,
            'unconverged_solves': stats.unconverged,
            'frictionless_answers': stats.frictionless_answers,
            'unresolved_force_lcps': stats.unresolved_force_lcps,
            'tangential_impacts': stats.tangential_impacts,
            'max_lcp_residual': float(stats.max_residual),
            'max_penetration_m': float(stats.max_penetration_m),
            'commands_accepted': self.commands_accepted,
            'commands_rejected': self.commands_rejected,
            'recording': self._record_status,
            'callback_exceptions': self.callback_exceptions,
            'last_callback_exception': self._last_exception,
        }

    # -- recording -------------------------------------------------------------------------

    def _open_recording(self, path: str, flush_period_s: float, log_time: str) -> None:
        try:
            directory = os.path.dirname(os.path.abspath(path))
            os.makedirs(directory, exist_ok=True)
            self.recorder = open_recorder(self.sim, path, log_time=log_time,
                                          flush_interval=flush_period_s)
            self._record_status = f'ok: {path}'
        except OSError as err:
            self._recording_failed(err)

    def _record(self, write) -> None:
        if self.recorder is None:
            return
        try:
            write(self.recorder)
        except RecordingError as err:
            self._recording_failed(err)

    def _recording_failed(self, err: OSError) -> None:
        self._record_status = f'failed: {err}'
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        if self._on_record_error == 'stop':
            self.get_logger().error(f'recording failed, stopping (on_record_error=stop): {err}')
            self.done = True
            self.exit_code = 1
        else:
            self.get_logger().error(f'recording failed, simulation goes on without it: {err}')

    def close(self) -> None:
        """Finalize the MCAP log (idempotent; safe after the ROS context is shut down)."""
        with self._closing:
            recorder, self.recorder = self.recorder, None
        if recorder is not None:
            try:
                recorder.close()
            except RecordingError as err:
                self._record_status = f'failed: {err}'
                print(f'sim_node: {err}', file=sys.stderr)

    # -- commands, parameters, services ---------------------------------------------------

    def _on_vibration_cmd(self, msg: Float64MultiArray) -> None:
        try:
            command = parse_command(msg.data, self._limits)
        except (ValueError, TypeError) as err:
            self.commands_rejected += 1
            self.get_logger().warning(
                f'vibration_cmd rejected ({err}); keeping the previous command',
                throttle_duration_sec=1.0)
            return
        self.commands_accepted += 1
        self._pending_command = command

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        limits = self._limits
        for p in params:
            if p.name == 'real_time_factor':
                self._rtf = float(p.value)
                self._anchor()
            elif p.name == 'max_amplitude_m':
                limits = CommandLimits(float(p.value), limits.max_frequency_hz)
            elif p.name == 'max_frequency_hz':
                limits = CommandLimits(limits.max_amplitude_m, float(p.value))
        self._limits = limits
        return SetParametersResult(successful=True)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.sim.reset()
        self.sensors.reset()
        frames.read_sensors(self.sim, self.sensors)
        self._pending_command = None
        self._anchor()
        # the log goes on: a new episode one frame after the last, with the drive restored
        self._record(lambda r: r.begin_episode(self.period_ns))
        for i in self.sim.world.driven[:1]:
            d = self.sim.world.drives[i]
            self._record(lambda r, d=d: r.write_vibration_cmd(0, d.amplitude_m, d.frequency_hz))
        self._publish_frame(Frame.take(self.sim, self.sensors))
        response.success = True
        response.message = f"scene '{self.sim.scene.name}' reset to t = 0"
        return response

    def _on_pause(self, request: SetBool.Request, response: SetBool.Response):
        self.paused = bool(request.data)
        if not self.paused:
            self._answer_steps(' (resumed before its frames were done)')
        self._anchor()
        response.success = True
        response.message = f"{'paused' if self.paused else 'running'} at t = {self.sim.t:.6g} s"
        return response

    # -- parts while running (feeder_sim_interfaces, after simulation_interfaces) -----------

    def _create_part_services(self) -> None:
        try:
            from feeder_sim_interfaces import srv
        except ImportError:
            self.get_logger().info(
                'part services (~/spawn_entity, ~/delete_entity, ~/set_entity_state, '
                '~/get_entities) are off: feeder_sim_interfaces is not built here '
                '(python interfaces/build.py, or colcon build in a workspace)')
            return
        self.create_service(srv.SpawnEntity, '~/spawn_entity', self._on_spawn_entity)
        self.create_service(srv.DeleteEntity, '~/delete_entity', self._on_delete_entity)
        self.create_service(srv.SetEntityState, '~/set_entity_state', self._on_set_entity_state)
        self.create_service(srv.GetEntities, '~/get_entities', self._on_get_entities)

    @staticmethod
    def _result(response, code_name: str, message: str = ''):
        from feeder_sim_interfaces.msg import Result
        response.result = Result(result=getattr(Result, code_name), error_message=message)
        return response

    def _frames(self) -> tuple[str, ...]:
        """Frame ids a request's pose may be in: the world's, named as the node names it."""
        return ('', 'world', self.frame_id)

    def _changed_parts(self, what: str) -> None:
        self._follow_parts()
        self.get_logger().info(what)

    def _on_spawn_entity(self, request, response):
        try:
            msgs.body_name(request.name, 'name', empty=True)
            msgs.body_name(request.uri, 'uri')
            pose, velocity = msgs.planar_state(request.initial_pose, request.initial_twist,
                                               'initial_pose', 'initial_twist', self._frames())
        except msgs.RequestError as err:
            return self._result(response, 'RESULT_OPERATION_FAILED', str(err))
        name = request.name
        taken = name in self.sim.world.names
        if not name or (taken and request.allow_renaming):
            name = self.sim.free_name(name or request.uri)
        elif taken:
            return self._result(response, 'RESULT_INCORRECT_STATE',
                                f'name: a body is already named {name!r} (set allow_renaming '
                                'to get a free name)')
        try:
            self.sim.add_part(request.uri, name, pose, velocity)
        except UnknownPart as err:
            return self._result(response, 'RESULT_NOT_FOUND', f'uri: {err}')
        except (ValueError, SceneError) as err:
            return self._result(response, 'RESULT_OPERATION_FAILED', str(err))
        response.entity_name = name
        self._changed_parts(f'spawned {name} ({request.uri}) at t = {self.sim.t:.6g} s')
        return self._result(response, 'RESULT_OK')

    def _on_delete_entity(self, request, response):
        try:
            msgs.body_name(request.entity, 'entity')
        except msgs.RequestError as err:
            return self._result(response, 'RESULT_OPERATION_FAILED', str(err))
        try:
            self.sim.remove_part(request.entity)
        except UnknownPart as err:
            return self._result(response, 'RESULT_NOT_FOUND', f'entity: {err}')
        self._changed_parts(f'deleted {request.entity} at t = {self.sim.t:.6g} s')
        return self._result(response, 'RESULT_OK')

    def _on_set_entity_state(self, request, response):
        try:
            msgs.body_name(request.entity, 'entity')
            pose, velocity = msgs.planar_state(request.pose, request.twist, 'pose', 'twist',
                                               self._frames())
        except msgs.RequestError as err:
            return self._result(response, 'RESULT_OPERATION_FAILED', str(err))
        try:
            self.sim.set_part_pose(request.entity, pose, velocity)
        except UnknownPart as err:
            return self._result(response, 'RESULT_NOT_FOUND', f'entity: {err}')
        except (ValueError, SceneError) as err:
            return self._result(response, 'RESULT_OPERATION_FAILED', str(err))
        self._changed_parts(f'placed {request.entity} at t = {self.sim.t:.6g} s')
        return self._result(response, 'RESULT_OK')

    def _on_get_entities(self, request, response):
        response.entities = list(self.sim.part_poses()[0])
        return self._result(response, 'RESULT_OK')

    async def _on_step(self, request: Trigger.Request, response: Trigger.Response):
        """``steps_per_call`` frames while paused, answered when they are done. The frames run
        in the frame timer, a wall budget at a time (:meth:`_step_while_paused`), so that
        ~/pause, ~/reset and the part services are answered while a long step runs; resumed
        (~/pause false) or stopped before its frames are done, a step is answered at once."""
        if not self.paused:
            response.success = False
            response.message = 'not paused: call ~/pause with data: true first'
            return response
        done = Future()
        self._steps_asked.append([self.get_parameter('steps_per_call').value, done])
        self._frame_timer.reset()
        await done
        response.success = True
        response.message = f't = {self.sim.t:.6g} s' + done.result()
        return response

    def _step_while_paused(self) -> None:
        """Frames of the step requests, oldest first, for at most the frame timer's wall
        budget (one frame at least); a request whose frames are done is answered."""
        start = time.perf_counter()
        while self._steps_asked:
            asked = self._steps_asked[0]
            if self.done or self.stop.is_set():
                self._answer_steps(' (the node stopped)')
                return
            if asked[0] <= 0:
                self._steps_asked.pop(0)[1].set_result('')
                if not self._steps_asked:
                    self._frame_timer.cancel()
                continue
            if time.perf_counter() - start > _WALL_BUDGET_S:
                return
            self.advance_frame()
            asked[0] -= 1

    def _answer_steps(self, why: str) -> None:
        """Answer every pending step request now, saying ``why`` it ended early."""
        asked, self._steps_asked = self._steps_asked, []
        for _, done in asked:
            done.set_result(why)


def main(args: list[str] | None = None, stop: threading.Event | None = None,
         wakeup_fd: int | None = None) -> int:
    """Run the node: spin until duration, Ctrl-C or SIGTERM; finalize the log.

    SIGINT and SIGTERM only set ``stop``, which the loop reads between callbacks: an exception
    thrown into the middle of a frame (a kernel being compiled, a chunk being written) would
    leave a traceback instead of a clean exit with a finalized log. ``stop`` is given by the
    console entry point (:mod:`feeder_sim.ros.entry`), which sets the handlers up before
    anything heavy is imported, and passes ``wakeup_fd``, the read end of the signal wake-up
    pipe. A stop during a kernel's first compile ends the process from another thread
    (:func:`_end_during_first_use`): ``main`` is the executable's, not a function to embed.
    """
    previous = {}
    if stop is None:
        stop = threading.Event()
        previous = {sig: signal.signal(sig, lambda signum, frame: stop.set())
                    for sig in (signal.SIGINT, signal.SIGTERM)}
    argv = sys.argv[1:] if args is None else args[1:]
    own = argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
    if '-h' in own or '--help' in own:
        print(usage())
        return 0
    # rcl's own message for a params file it cannot read suggests nothing useful: name it
    ros_args = argv[len(own):]
    for flag, path in zip(ros_args, ros_args[1:]):
        if flag == '--params-file' and not os.path.isfile(path):
            print(f'sim_node: error: --params-file {path}: no such file (give the path of a '
                  'YAML parameter file, e.g. config/sim_node.params.yaml)', file=sys.stderr)
            _restore(previous)
            return 2
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:   # rcl's argument errors come as several types
        print(f'sim_node: error: bad --ros-args ({str(err).splitlines()[0]}); write them as '
              '--ros-args -p NAME:=VALUE', file=sys.stderr)
        _restore(previous)
        return 2
    try:
        node = SimNode()
    except (ParameterException, SceneError, ValueError, OSError, NotImplementedError) as err:
        print(f'sim_node: error: {err}', file=sys.stderr)
        rclpy.try_shutdown()
        _restore(previous)
        return 2
    node.stop = stop
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    loop_done = threading.Event()
    threading.Thread(target=_end_during_first_use, args=(node, stop, loop_done, wakeup_fd),
                     name='stop during first use', daemon=True).start()
    try:
        while rclpy.ok() and not node.done and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        loop_done.set()
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()
        _restore(previous)
    return node.exit_code


def _end_during_first_use(node: SimNode, stop: threading.Event, loop_done: threading.Event,
                          wakeup_fd: int | None) -> None:
    """After a stop request, end the process here if the loop is held in a kernel's first
    compile: numba's compile cannot be cut short, and the loop would see the request only
    when it ends. The log is finalized first (the loop is not writing it: it is compiling),
    as the loop would; nothing else is left to do that the process's end does not.

    The request is read from the signal wake-up pipe when there is one: ``stop`` is set by
    the handler, which runs only when the compiling main thread next runs Python."""
    if wakeup_fd is not None:
        try:
            os.read(wakeup_fd, 1)   # a signal number: SIGINT or SIGTERM, the only handled
        except OSError:
            return
        stop.set()
    else:
        stop.wait()
    while not loop_done.wait(_FIRST_USE_POLL_S):
        if in_first_use():
            node.close()
            print('sim_node: stopped during a first compile of the numba kernels; the log is '
                  'final', file=sys.stderr, flush=True)
            sys.stdout.flush()
            os._exit(node.exit_code)


def _restore(handlers: dict) -> None:
    for sig, handler in handlers.items():
        signal.signal(sig, handler)


if __name__ == '__main__':
    sys.exit(main())
