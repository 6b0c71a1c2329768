"""ROS 2 message definitions used by the MCAP recorder, as plain text.

The recorder writes logs with the ``ros2msg`` schema encoding, which wants the complete
definition of a message type: its own field lines followed by the definition of every type it
depends on, each introduced by a separator line of 80 ``=`` and a ``MSG: pkg/Type`` line (the
layout rosbag2 uses when it records to MCAP).  Only field and constant lines are kept here; the
definitions must describe exactly the wire layout the ROS 2 Jazzy interfaces produce.

This module has no ROS dependency.
"""

from __future__ import annotations

import re

__all__ = ['SEPARATOR', 'definition', 'dependencies', 'field_lines', 'normalize_type_name']

SEPARATOR = '=' * 80

# Field-only definitions, keyed by ``pkg/Type``.  Relative type names (no package) refer to the
# package of the message they appear in, as in .msg files.
_FIELDS: dict[str, str] = {
    'builtin_interfaces/Time': """\
int32 sec
uint32 nanosec
""",
    'std_msgs/Header': """\
builtin_interfaces/Time stamp
string frame_id
""",
    'rosgraph_msgs/Clock': """\
builtin_interfaces/Time clock
""",
    'std_msgs/Bool': """\
bool data
""",
    'std_msgs/UInt32': """\
uint32 data
""",
    'diagnostic_msgs/KeyValue': """\
string key
string value
""",
    'geometry_msgs/Point': """\
float64 x
float64 y
float64 z
""",
    'geometry_msgs/Quaternion': """\
float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    'geometry_msgs/Pose': """\
Point position
Quaternion orientation
""",
    'geometry_msgs/PoseArray': """\
std_msgs/Header header
Pose[] poses
""",
    'sensor_msgs/PointField': """\
uint8 INT8 = 1
uint8 UINT8 = 2
uint8 INT16 = 3
uint8 UINT16 = 4
uint8 INT32 = 5
uint8 UINT32 = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8 datatype
uint32 count
""",
    'sensor_msgs/PointCloud2': """\
std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
""",
    'sensor_msgs/JointState': """\
std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
""",
    'builtin_interfaces/Duration': """\
int32 sec
uint32 nanosec
""",
    'std_msgs/ColorRGBA': """\
float32 r
float32 g
float32 b
float32 a
""",
    'geometry_msgs/Vector3': """\
float64 x
float64 y
float64 z
""",
    'geometry_msgs/Transform': """\
Vector3 translation
Quaternion rotation
""",
    'geometry_msgs/TransformStamped': """\
std_msgs/Header header
string child_frame_id
Transform transform
""",
    'tf2_msgs/TFMessage': """\
geometry_msgs/TransformStamped[] transforms
""",
    'sensor_msgs/CompressedImage': """\
std_msgs/Header header
string format
uint8[] data
""",
    'visualization_msgs/UVCoordinate': """\
float32 u
float32 v
""",
    'visualization_msgs/MeshFile': """\
string filename
uint8[] data
""",
    'visualization_msgs/Marker': """\
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ARROW_STRIP=12
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
UVCoordinate[] uv_coordinates
string text
string mesh_resource
MeshFile mesh_file
bool mesh_use_embedded_materials
""",
    'visualization_msgs/MarkerArray': """\
Marker[] markers
""",
    'diagnostic_msgs/DiagnosticStatus': """\
byte OK=0
byte WARN=1
byte ERROR=2
byte STALE=3
byte level
string name
string message
string hardware_id
KeyValue[] values
""",
    'diagnostic_msgs/DiagnosticArray': """\
std_msgs/Header header
DiagnosticStatus[] status
""",
    'std_msgs/MultiArrayDimension': """\
string label
uint32 size
uint32 stride
""",
    'std_msgs/MultiArrayLayout': """\
MultiArrayDimension[] dim
uint32 data_offset
""",
    'std_msgs/Float64MultiArray': """\
MultiArrayLayout layout
float64[] data
""",
}

_PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'int8', 'uint8', 'int16', 'uint16', 'int32', 'uint32',
    'int64', 'uint64', 'float32', 'float64', 'string', 'wstring',
})

# Array suffixes ``[]``, ``[N]``, ``[<=N]`` and bounded strings ``string<=N``.
_ARRAY_SUFFIX = re.compile(r'\[[^\]]*\]$')
_BOUND_SUFFIX = re.compile(r'<=\d+$')


def normalize_type_name(type_name: str) -> str:
    """Return ``pkg/Type`` for ``pkg/Type`` or ``pkg/msg/Type``."""
    parts = type_name.strip().split('/')
    if len(parts) == 3 and parts[1] == 'msg':
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(parts):
        raise ValueError(f'not a ROS message type name: {type_name!r}')
    return '/'.join(parts)


def field_lines(type_name: str) -> list[str]:
    """Return the field and constant lines of one message type (no dependencies)."""
    key = normalize_type_name(type_name)
    try:
        text = _FIELDS[key]
    except KeyError:
        raise KeyError(f'no definition for message type {type_name!r}') from None
    return [line for line in text.splitlines() if line.strip()]


def dependencies(type_name: str) -> list[str]:
    """Return the direct non-primitive dependencies of a type as sorted ``pkg/Type`` names."""
    key = normalize_type_name(type_name)
    package = key.split('/')[0]
    deps = set()
    for line in field_lines(key):
        field_type = line.split()[0]
        field_type = _BOUND_SUFFIX.sub('', _ARRAY_SUFFIX.sub('', field_type))
        if field_type in _PRIMITIVES:
            continue
        if '/' not in field_type:
            field_type = f'{package}/{field_type}'
        deps.add(normalize_type_name(field_type))
    return sorted(deps)


def definition(type_name: str) -> str:
    """Return the full rosbag2-style definition text of a message type.

    The top-level field lines come first; then, depth first with each type's dependencies in
    sorted order and every type listed once, a separator line, ``MSG: pkg/Type`` and that type's
    field lines.
    """
    root = normalize_type_name(type_name)
    seen = {root}
    out: list[str] = []

    def visit(key: str) -> None:
        out.extend(field_lines(key))
        for dep in dependencies(key):
            if dep in seen:
                continue
            seen.add(dep)
            out.append(SEPARATOR)
            out.append(f'MSG: {dep}')
            visit(dep)

    visit(root)
    return '\n'.join(out) + '\n'
