"""ROS 2 messages of the simulator's state: plain functions from arrays to messages.

Everything here is stamped with simulated time (integer nanoseconds) and drawn in the plane
z = 0 of frame ``world``. The contact cloud has the same fields and layout as the one the MCAP
recorder writes (:data:`feeder_sim.output.recording.CONTACT_FIELDS`), and so has the part
impulse cloud (``PART_IMPULSE_FIELDS``), so a subscriber and a log reader decode them the same
way.
"""

from __future__ import annotations

from collections.abc import Sequence
import math

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray, Quaternion
import numpy as np
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from feeder_sim.model.scene import MAX_LENGTH_M, MAX_SPEED_MPS, MAX_SPIN_RAD_S
from feeder_sim.model.scene.errors import _Invalid
from feeder_sim.model.scene.fields import _number
from feeder_sim.model.scene.parse import _body_name
from feeder_sim.model.world import perp
from feeder_sim.output.impulses import PartImpulses
from feeder_sim.output.recording import (
    CONTACT_FIELDS,
    CONTACT_POINT_STEP,
    PART_IMPULSE_FIELDS,
    PART_IMPULSE_STEP,
)

_NS = 1_000_000_000


def stamp(t_ns: int) -> Time:
    sec, nanosec = divmod(int(t_ns), _NS)
    return Time(sec=sec, nanosec=nanosec)


def header(t_ns: int, frame_id: str) -> Header:
    return Header(stamp=stamp(t_ns), frame_id=frame_id)


def clock(t_ns: int) -> Clock:
    return Clock(clock=stamp(t_ns))


def yaw_quaternion(angle: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * angle), w=math.cos(0.5 * angle))


def pose_array(t_ns: int, origin: np.ndarray, angle: np.ndarray, frame_id: str) -> PoseArray:
    """One pose per part: body-frame origin (m) and yaw (rad) as a quaternion about z."""
    msg = PoseArray(header=header(t_ns, frame_id))
    msg.poses = [Pose(position=Point(x=float(x), y=float(y), z=0.0), orientation=yaw_quaternion(a))
                 for (x, y), a in zip(origin.tolist(), angle.tolist())]
    return msg


def _point_fields(fields) -> list[PointField]:
    return [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields]


_CONTACT_POINT_FIELDS = _point_fields(CONTACT_FIELDS)
_PART_IMPULSE_POINT_FIELDS = _point_fields(PART_IMPULSE_FIELDS)


def _cloud(t_ns: int, frame_id: str, fields: list[PointField], step: int,
           rows: np.ndarray) -> PointCloud2:
    # The field list is shared between messages: publishing only reads it.
    return PointCloud2(header=header(t_ns, frame_id), height=1, width=len(rows), fields=fields,
                       is_bigendian=False, point_step=step, row_step=step * len(rows),
                       data=rows.tobytes(), is_dense=True)


def contact_cloud(t_ns: int, report, frame_id: str) -> PointCloud2:
    """One point per contact with its normal and the impulses (N s) since the last message."""
    rows = np.zeros((report.n, len(CONTACT_FIELDS)), dtype='<f4')
    rows[:, 0:2] = report.point
    rows[:, 3:5] = report.normal
    rows[:, 5] = report.normal_impulse
    rows[:, 6] = report.tangent_impulse
    ids = rows.view('<u4')
    ids[:, 7] = report.body_a
    ids[:, 8] = report.body_b
    return _cloud(t_ns, frame_id, _CONTACT_POINT_FIELDS, CONTACT_POINT_STEP, rows)


def part_impulse_cloud(t_ns: int, totals: PartImpulses, centre_of_mass: np.ndarray,
                       frame_id: str) -> PointCloud2:
    """One point per part at its centre of mass with the impulse totals since the last one."""
    n = len(totals.parts)
    rows = np.zeros((n, len(PART_IMPULSE_FIELDS)), dtype='<f4')
    rows[:, 0:2] = centre_of_mass[totals.parts]
    rows[:, 3:5] = totals.impulse
    rows[:, 5] = totals.angular_impulse
    rows[:, 6] = totals.normal_impulse
    ids = rows.view('<u4')
    ids[:, 7] = totals.contacts
    ids[:, 8] = np.arange(n)
    return _cloud(t_ns, frame_id, _PART_IMPULSE_POINT_FIELDS, PART_IMPULSE_STEP, rows)


def track_state(t_ns: int, names: Sequence[str], position: np.ndarray,
                velocity: np.ndarray) -> JointState:
    """Position (m) and speed (m/s) of each part along the track, named by part."""
    return JointState(header=header(t_ns, ''), name=list(names),
                      position=position.tolist(), velocity=velocity.tolist())


# -- RViz markers ----------------------------------------------------------------------------

_PALETTE = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
            (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5),
            (0.74, 0.74, 0.13), (0.09, 0.75, 0.81))
_GREY = ColorRGBA(r=0.35, g=0.35, b=0.35, a=1.0)
_IMPULSE_COLOUR = ColorRGBA(r=0.85, g=0.1, b=0.1, a=1.0)


def _colour(i: int) -> ColorRGBA:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return ColorRGBA(r=r, g=g, b=b, a=1.0)


class Outlines:
    """LINE_STRIP markers of body outlines, built once per body; each frame only moves their
    poses. Bodies come and go (:meth:`follow`): only a new body's markers are built, so a
    part added to a world of hundreds costs its own markers, not everyone's."""

    def __init__(self, frame_id: str, line_width_m: float):
        self.frame_id = frame_id
        self.line_width_m = line_width_m
        # name -> (its outlines as given, its markers); colours in order of first appearance
        self._known: dict[str, tuple[object, list[Marker]]] = {}
        self._seen = 0
        self._markers: list[list[Marker]] = []

    def follow(self, outlines: Sequence[Sequence[np.ndarray]], names: Sequence[str]) -> None:
        """The bodies now: ``outlines[i]`` lists the closed polygons of body ``i`` (named
        ``names[i]``) in its scene-file body frame (m)."""
        known = self._known
        for polygons, name in zip(outlines, names, strict=True):
            entry = known.get(name)
            if entry is None or entry[0] is not polygons:
                known[name] = (polygons, self._build(polygons, name, self._seen))
                self._seen += 1
        if len(known) > len(names):
            for name in set(known) - set(names):
                del known[name]
        self._markers = [known[name][1] for name in names]

    def _build(self, polygons: Sequence[np.ndarray], name: str, colour: int) -> list[Marker]:
        body = []
        for j, polygon in enumerate(polygons):
            m = Marker(ns=name, id=j, type=Marker.LINE_STRIP, action=Marker.ADD)
            m.header.frame_id = self.frame_id
            m.scale.x = self.line_width_m
            m.color = _colour(colour)
            closed = np.vstack([polygon, polygon[:1]])
            m.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in closed.tolist()]
            m.pose.orientation.w = 1.0
            body.append(m)
        return body

    def markers(self, t_ns: int, bodies: Sequence[int], origin: np.ndarray,
                angle: np.ndarray, grey: bool = False) -> list[Marker]:
        """The outlines of ``bodies`` at body-frame poses ``origin[k]``, ``angle[k]``."""
        out = []
        when = stamp(t_ns)
        for k, i in enumerate(bodies):
            q = yaw_quaternion(float(angle[k]))
            for m in self._markers[i]:
                m.header.stamp = when
                m.pose.position.x = float(origin[k, 0])
                m.pose.position.y = float(origin[k, 1])
                m.pose.orientation = q
                if grey:
                    m.color = _GREY
                out.append(m)
        return out


def impulse_arrows(t_ns: int, report, scale_m_per_ns: float, frame_id: str,
                   shaft_m: float) -> list[Marker]:
    """ARROW markers from each contact point along the impulse its vertex body received.

    The arrows are replaced as a whole every frame: a DELETEALL marker comes first.
    """
    clear = Marker(ns='impulses', action=Marker.DELETEALL)
    clear.header = header(t_ns, frame_id)
    out = [clear]
    if report.n == 0:
        return out
    vector = (report.normal_impulse[:, None] * report.normal
              + report.tangent_impulse[:, None] * perp(report.normal)) * scale_m_per_ns
    head = header(t_ns, frame_id)
    for k, ((x, y), (dx, dy)) in enumerate(zip(report.point.tolist(), vector.tolist())):
        m = Marker(header=head, ns='impulses', id=k, type=Marker.ARROW, action=Marker.ADD,
                   color=_IMPULSE_COLOUR)
        m.scale.x, m.scale.y, m.scale.z = shaft_m, 2.0 * shaft_m, 3.0 * shaft_m
        m.pose.orientation.w = 1.0
        m.points = [Point(x=x, y=y, z=0.0), Point(x=x + dx, y=y + dy, z=0.0)]
        out.append(m)
    return out


def delete_markers(t_ns: int, ns: str, frame_id: str) -> Marker:
    """Delete every marker of namespace ``ns`` (a part that left)."""
    m = Marker(ns=ns, action=Marker.DELETEALL)
    m.header = header(t_ns, frame_id)
    return m


def marker_array(markers: list[Marker]) -> MarkerArray:
    return MarkerArray(markers=markers)


# -- diagnostics -----------------------------------------------------------------------------

def key_values(values: dict[str, object]) -> list[tuple[str, str]]:
    """Diagnostic values as key/value strings (floats to 6 significant digits)."""
    return [(k, f'{v:.6g}' if isinstance(v, float) else str(v)) for k, v in values.items()]


def diagnostics(t_ns: int, name: str, level: bytes, message: str,
                values: dict[str, object]) -> DiagnosticArray:
    """A one-status DiagnosticArray; ``level`` is ``DiagnosticStatus.OK``, ``WARN``, ...;
    ``values`` become key/value strings."""
    status = DiagnosticStatus(level=level, name=name, message=message,
                              hardware_id='feeder_sim')
    status.values = [KeyValue(key=k, value=v) for k, v in key_values(values)]
    return DiagnosticArray(header=header(t_ns, ''), status=[status])


# -- requests --------------------------------------------------------------------------------

class RequestError(ValueError):
    """A request field a scene file would refuse: one sentence naming the field."""


# |x|, |y| of an orientation's axis, relative to the quaternion's norm, still taken as a
# rotation about z: a quaternion built from a yaw has them exactly 0
_TILT = 1e-9
_SHOWN_CHARS = 60    # of a refused text: a name of a megabyte must not come back whole


def _shown(text: str) -> str:
    r = repr(text)
    return r if len(r) <= _SHOWN_CHARS else r[:_SHOWN_CHARS] + '...'


def _scene_checked(check, value, field: str):
    """``check`` of model/scene/ (the rule a scene file's field has), its refusal naming
    ``field``."""
    try:
        return check(value, field)
    except _Invalid as err:
        raise RequestError(f'{err.path}: {err.message}') from None


def body_name(value: str, field: str, *, empty: bool = False) -> str:
    """A part or template name by the scene files' rule for body names (``empty``: '' too)."""
    if empty and value == '':
        return value
    try:
        return _body_name(value, field)
    except _Invalid as err:
        text = err.message.replace(repr(value), _shown(value), 1)
        raise RequestError(f'{field}: {text}') from None


def _bounded(value: float, field: str, limit: float, unit: str) -> float:
    return _scene_checked(
        lambda v, p: _number(v, p, -limit, limit, unit=unit,
                             hint='larger values do not keep a run finite and meaningful'),
        value, field)


def _zero(value: float, field: str, why: str) -> None:
    if value != 0.0:                           # NaN too
        raise RequestError(f'{field} must be 0 ({why}), got {value:g}')


def planar_yaw(q, field: str) -> float:
    """The yaw (rad) of quaternion ``q`` (any norm), a rotation about z; RequestError naming
    ``field`` for one that is not finite, zero or turns out of the plane.

    The components are scaled by the largest before squaring: 1e200 squared overflows."""
    c = (q.x, q.y, q.z, q.w)
    shown = f'({c[0]:g}, {c[1]:g}, {c[2]:g}, {c[3]:g})'
    if not all(math.isfinite(v) for v in c):
        raise RequestError(f'{field} must be a quaternion of finite numbers, got {shown}')
    largest = max(abs(v) for v in c)
    if largest == 0.0:
        raise RequestError(f'{field} must be a rotation, got the zero quaternion: give w = 1 '
                           'for none')
    x, y, z, w = (v / largest for v in c)
    norm = math.sqrt(x * x + y * y + z * z + w * w)      # in [1, 2]
    if abs(x) > _TILT * norm or abs(y) > _TILT * norm:
        raise RequestError(f'{field} must be a rotation about z (x = y = 0): the simulation is '
                           f'planar, got {shown}')
    return 2.0 * math.atan2(z, w)


def planar_state(pose_stamped, twist, pose_field: str, twist_field: str,
                 frames: Sequence[str]) -> tuple[list[float], list[float]]:
    """[x, y, yaw] and [vx, vy, omega] of a request's PoseStamped and Twist, every field
    checked as a scene file's ``pose`` and ``velocity`` are (model/scene/specs.py's bounds); a
    RequestError naming the first field that is not."""
    frame = pose_stamped.header.frame_id
    if frame not in frames:
        allowed = ' or '.join(repr(f) for f in dict.fromkeys(frames) if f)
        raise RequestError(f'{pose_field}.header.frame_id must be {allowed} or empty (poses '
                           f'are in the world frame), got {_shown(frame)}')
    p, q = pose_stamped.pose.position, pose_stamped.pose.orientation
    at = f'{pose_field}.pose.position'
    x = _bounded(p.x, f'{at}.x', MAX_LENGTH_M, 'm')
    y = _bounded(p.y, f'{at}.y', MAX_LENGTH_M, 'm')
    _zero(p.z, f'{at}.z', 'the scene is the plane z = 0')
    yaw = planar_yaw(q, f'{pose_field}.pose.orientation')
    lin, ang = twist.linear, twist.angular
    vx = _bounded(lin.x, f'{twist_field}.linear.x', MAX_SPEED_MPS, 'm/s')
    vy = _bounded(lin.y, f'{twist_field}.linear.y', MAX_SPEED_MPS, 'm/s')
    _zero(lin.z, f'{twist_field}.linear.z', 'parts move in the plane z = 0')
    _zero(ang.x, f'{twist_field}.angular.x', 'parts turn about z only')
    _zero(ang.y, f'{twist_field}.angular.y', 'parts turn about z only')
    omega = _bounded(ang.z, f'{twist_field}.angular.z', MAX_SPIN_RAD_S, 'rad/s')
    return [x, y, yaw], [vx, vy, omega]
