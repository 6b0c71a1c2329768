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
    """LINE_STRIP markers of body outlines, built once; each frame only moves their poses.

    ``outlines[i]`` lists the closed polygons of body ``i`` in its scene-file body frame (m).
    """

    def __init__(self, outlines: Sequence[Sequence[np.ndarray]], names: Sequence[str],
                 frame_id: str, line_width_m: float):
        self.frame_id = frame_id
        self._markers: list[list[Marker]] = []
        for i, (polygons, name) in enumerate(zip(outlines, names)):
            body = []
            for j, polygon in enumerate(polygons):
                m = Marker(ns=name, id=j, type=Marker.LINE_STRIP, action=Marker.ADD)
                m.header.frame_id = frame_id
                m.scale.x = line_width_m
                m.color = _colour(i)
                closed = np.vstack([polygon, polygon[:1]])
                m.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in closed.tolist()]
                m.pose.orientation.w = 1.0
                body.append(m)
            self._markers.append(body)

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
