"""MCAP recording of feeder_sim runs with ROS 2 message encoding, without ROS.

Logs use the ``ros2`` MCAP profile: channel message encoding ``cdr``, schema encoding
``ros2msg`` with the full message definition (see :mod:`feeder_sim.output.msgdefs`), so that
``ros2 bag``, Foxglove, mcap-ros2-support and rerun read them.  The payloads are serialized
here (XCDR1, little endian, encapsulation header ``00 01 00 00``) for the few message types
the simulator publishes; nothing from rclpy or the ROS message packages is imported.

Durability: the file is written through a small wrapper that hands every finished chunk and its
message index to the operating system right away, so a process killed with SIGKILL leaves a
file from which :func:`read_messages` recovers every message of the completed chunks.  Only
:meth:`McapRecorder.close` writes the summary and footer (and fsyncs once).
"""

from __future__ import annotations

from collections.abc import Container, Iterable, Iterator, Mapping, Sequence
import contextlib
import importlib.metadata
import io
import operator
import os
import struct
import sys
import threading
import time
from typing import Self
import warnings

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer
import numpy as np

from feeder_sim.output import msgdefs

try:
    import zstandard  # noqa: F401
except ImportError:  # pragma: no cover - depends on the environment
    _HAVE_ZSTD = False
else:
    _HAVE_ZSTD = True

try:
    import lz4.frame  # noqa: F401
except ImportError:  # pragma: no cover - depends on the environment
    _HAVE_LZ4 = False
else:
    _HAVE_LZ4 = True

__all__ = [
    'CONTACT_FIELDS',
    'CONTACT_POINT_DTYPE',
    'CONTACT_POINT_STEP',
    'DEFAULT_COMPRESSION',
    'TOPICS',
    'TOPIC_CLOCK',
    'TOPIC_CONTACTS',
    'TOPIC_PART_POSES',
    'TOPIC_TRACK_STATE',
    'TOPIC_VIBRATION_CMD',
    'McapRecorder',
    'RecordingError',
    'read_messages',
]

TOPIC_CLOCK = '/clock'
TOPIC_PART_POSES = '/feeder_sim/part_poses'
TOPIC_CONTACTS = '/feeder_sim/contacts'
TOPIC_TRACK_STATE = '/feeder_sim/track_state'
TOPIC_VIBRATION_CMD = '/vibration_cmd'
TOPIC_TF = '/tf'
TOPIC_PART_IMPULSES = '/feeder_sim/part_impulses'
TOPIC_DIAGNOSTICS = '/diagnostics'
TOPIC_GEOMETRY = '/feeder_sim/geometry'
SENSOR_PREFIX = '/feeder_sim/sensors/'

#: the topics of a sensor of each kind: (suffix, ROS 2 message type)
SENSOR_TOPICS: dict[str, tuple[tuple[str, str], ...]] = {
    'beam': (('blocked', 'std_msgs/msg/Bool'), ('count', 'std_msgs/msg/UInt32')),
    'inspection': (('count', 'std_msgs/msg/UInt32'), ('passed', 'diagnostic_msgs/msg/KeyValue')),
}


def sensor_topics(name: str, kind: str) -> dict[str, str]:
    """Topic -> ROS 2 message type of the sensor ``name`` of ``kind`` (see ``SENSOR_TOPICS``)."""
    return {f'{SENSOR_PREFIX}{name}/{suffix}': type_name
            for suffix, type_name in SENSOR_TOPICS[kind]}

#: topic -> ROS 2 message type, in the order the channels are registered.
TOPICS: dict[str, str] = {
    TOPIC_CLOCK: 'rosgraph_msgs/msg/Clock',
    TOPIC_PART_POSES: 'geometry_msgs/msg/PoseArray',
    TOPIC_CONTACTS: 'sensor_msgs/msg/PointCloud2',
    TOPIC_TRACK_STATE: 'sensor_msgs/msg/JointState',
    TOPIC_VIBRATION_CMD: 'std_msgs/msg/Float64MultiArray',
    # what a viewer (Foxglove's 3D panel, RViz-style tools) needs to draw the scene by itself:
    # each body's frame in the world every frame, and each body's outline once, in its frame
    TOPIC_TF: 'tf2_msgs/msg/TFMessage',
    TOPIC_GEOMETRY: 'visualization_msgs/msg/MarkerArray',
    TOPIC_PART_IMPULSES: 'sensor_msgs/msg/PointCloud2',
    # the node's health, as it published it (feeder-sim run has none to write)
    TOPIC_DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
}

DEFAULT_COMPRESSION = 'zstd' if _HAVE_ZSTD else 'none'

# sensor_msgs/PointField datatype codes.
_FLOAT32 = 7
_UINT32 = 6


def _packed(floats: tuple[str, ...], counts: tuple[str, ...]) -> tuple[tuple[str, int, int], ...]:
    """(name, byte offset, PointField datatype) of float32 fields then uint32 ones, packed."""
    kinds = [_FLOAT32] * len(floats) + [_UINT32] * len(counts)
    return tuple((name, 4 * k, kind) for k, (name, kind) in enumerate(zip(floats + counts, kinds)))


#: (name, byte offset, PointField datatype) of each field of a contact point.
CONTACT_FIELDS = _packed(('x', 'y', 'z', 'normal_x', 'normal_y', 'normal_impulse',
                          'tangent_impulse'), ('body_a', 'body_b'))
CONTACT_POINT_STEP = 4 * len(CONTACT_FIELDS)

#: (name, byte offset, PointField datatype) of each field of a part's impulse point: at the
#: centre of mass, the frame's totals over the part's contacts (N s, N m s), how many
#: contacts and the part's index in the frame's poses.
PART_IMPULSE_FIELDS = _packed(('x', 'y', 'z', 'impulse_x', 'impulse_y', 'angular_impulse',
                               'normal_impulse'), ('contacts', 'part'))
PART_IMPULSE_STEP = 4 * len(PART_IMPULSE_FIELDS)

#: numpy dtype of one contact point in PointCloud2.data (for decoding logs).
CONTACT_POINT_DTYPE = np.dtype({
    'names': [name for name, _, _ in CONTACT_FIELDS],
    'formats': ['<f4' if code == _FLOAT32 else '<u4' for _, _, code in CONTACT_FIELDS],
    'offsets': [offset for _, offset, _ in CONTACT_FIELDS],
    'itemsize': CONTACT_POINT_STEP,
})

_ENCAPSULATION = b'\x00\x01\x00\x00'  # CDR, little endian, no options
_NS_PER_S = 1_000_000_000
_MAX_STAMP_NS = (2 ** 31) * _NS_PER_S  # builtin_interfaces/Time.sec is an int32
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD_HEADER = struct.Struct('<BQ')


class RecordingError(OSError):
    """The MCAP file could not be opened, written or finalized, or the recorder is unusable."""


def _library_version() -> str:
    package = sys.modules.get(__package__ or '')
    version = getattr(package, '__version__', None)
    if isinstance(version, str) and version:
        return version
    try:
        return importlib.metadata.version('feeder_sim')
    except importlib.metadata.PackageNotFoundError:
        return 'unknown'


def _io_error(action: str, path: str, exc: BaseException) -> RecordingError:
    cause = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    errno = exc.errno if isinstance(exc, OSError) and exc.errno else None
    message = f'{action} MCAP recording {path!r}: {cause}'
    if errno is None:
        return RecordingError(message)
    return RecordingError(errno, message)


# --------------------------------------------------------------------------------------------
# CDR building blocks


def _pad(offset: int, alignment: int) -> bytes:
    return b'\x00' * (-offset % alignment)


def _cdr_string(text: str) -> bytes:
    """Length-prefixed, NUL-terminated UTF-8 string (not padded)."""
    if not isinstance(text, str):
        raise TypeError(f'expected a str, got {type(text).__name__}')
    raw = text.encode('utf-8')
    if b'\x00' in raw:
        raise ValueError(f'string {text!r} contains a NUL character')
    return _U32.pack(len(raw) + 1) + raw + b'\x00'


def _stamp(t_ns: int) -> bytes:
    """builtin_interfaces/Time of an integer nanosecond time, validated."""
    try:
        t = operator.index(t_ns)
    except TypeError:
        raise TypeError(
            f'time must be an integer number of nanoseconds, got {type(t_ns).__name__}') from None
    if not 0 <= t < _MAX_STAMP_NS:
        raise ValueError(f'time {t} ns is outside [0, 2**31 s)')
    sec, nanosec = divmod(t, _NS_PER_S)
    return _STAMP.pack(sec, nanosec)


def _pointfield_block(fields: tuple[tuple[str, int, int], ...]) -> bytes:
    """The `fields` sequence of a PointCloud2; starts at a 4-aligned offset."""
    parts = [_U32.pack(len(fields))]
    size = 4
    for name, offset, code in fields:
        name_bytes = _cdr_string(name)
        parts.append(name_bytes)
        size += len(name_bytes)
        parts.append(_pad(size, 4))
        size += len(parts[-1])
        parts.append(struct.pack('<IB3xI', offset, code, 1))
        size += 12
    return b''.join(parts)


_POINTFIELDS = _pointfield_block(CONTACT_FIELDS)
_PART_POINTFIELDS = _pointfield_block(PART_IMPULSE_FIELDS)
_CLOUD_TAIL = struct.Struct('<?3xIII')  # is_bigendian, point_step, row_step, len(data)
_CLOUD_SIZE = struct.Struct('<II')  # height, width
_MULTIARRAY_2 = struct.Struct('<III4xdd')  # no dims, data_offset, len(data) = 2, two float64
_DENSE = b'\x01'


class _Cdr:
    """A CDR body (little endian) written field by field; each field aligned to its size
    from the start of the body, as the encapsulation header's rules want."""

    __slots__ = ('parts', 'size')

    def __init__(self) -> None:
        self.parts: list[bytes] = [_ENCAPSULATION]
        self.size = 0

    def put(self, fmt: struct.Struct, *values, align: int) -> None:
        pad = -self.size % align
        if pad:
            self.parts.append(b'\x00' * pad)
        data = fmt.pack(*values)
        self.parts.append(data)
        self.size += pad + len(data)

    def string(self, text: str) -> None:
        data = _cdr_string(text)
        self.put(_U32, len(data) - 4, align=4)
        self.parts.append(data[4:])
        self.size += len(data) - 4

    def stamp(self, t_ns: int, frame_id: str) -> None:
        """A std_msgs/Header."""
        sec, nanosec = _STAMP.unpack(_stamp(t_ns))
        self.put(_STAMP, sec, nanosec, align=4)
        self.string(frame_id)

    def payload(self) -> bytes:
        return b''.join(self.parts)


_I32 = struct.Struct('<i')
_BOOL = struct.Struct('<?')
_F64_3 = struct.Struct('<3d')
_F64_4 = struct.Struct('<4d')
_F32_4 = struct.Struct('<4f')
_LINE_STRIP, _ADD, _DELETE = 4, 0, 2


class _Frame:
    """Per-frame_id constant part of a std_msgs/Header: the encoded string and its padding."""

    __slots__ = ('offset', 'padded', 'string')

    def __init__(self, frame_id: str):
        self.string = _cdr_string(frame_id)
        # Offset (within the CDR body) just past the header, then padded to 4.
        end = 8 + len(self.string)
        self.padded = self.string + _pad(end, 4)
        self.offset = end + (-end % 4)


def _as_float_array(name: str, value, shape_tail: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 1 + len(shape_tail) or array.shape[1:] != shape_tail:
        if array.size == 0:
            return array.reshape((0, *shape_tail))
        want = '(n, ' + ', '.join(map(str, shape_tail)) + ')' if shape_tail else '(n,)'
        raise ValueError(f'{name} must have shape {want}, got {array.shape}')
    return array


def _as_index_array(name: str, value, count: int) -> np.ndarray:
    array = np.asarray(value)
    if array.size == 0:
        array = array.astype(np.int64)
    if array.ndim != 1 or array.shape[0] != count:
        raise ValueError(f'{name} must have shape ({count},), got {array.shape}')
    if array.dtype.kind not in 'iub':
        raise TypeError(f'{name} must hold integer body indices, got dtype {array.dtype}')
    if count and (int(array.min()) < 0 or int(array.max()) > 0xFFFFFFFF):
        raise ValueError(f'{name} holds values outside the uint32 range')
    return array


# --------------------------------------------------------------------------------------------
# File wrapper


class _ChunkFile:
    """Output stream for mcap's Writer that reaches the OS only at record boundaries.

    The writer only calls write() and tell().  Data is collected in memory and handed to the
    OS by flush(), which the recorder calls after each operation that completed records
    (a chunk and its message indexes, a metadata record, the header, the summary).  If a write
    fails, the file is cut back to the end of the last complete flush, so that it still holds
    only whole records.
    """

    def __init__(self, path: str):
        self.path = path
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, 'O_CLOEXEC', 0)
        self._fd: int | None = os.open(path, flags, 0o666)
        self._parts: list[bytes] = []
        self._pending = 0
        self._written = 0  # bytes handed to the OS

    @property
    def pending(self) -> int:
        return self._pending

    def write(self, data) -> int:
        size = len(data)
        if size:
            self._parts.append(bytes(data))
            self._pending += size
        return size

    def tell(self) -> int:
        return self._written + self._pending

    def seekable(self) -> bool:  # pragma: no cover - not used by the writer
        return False

    def flush(self) -> None:
        if not self._pending:
            return
        if self._fd is None:
            raise ValueError('file is closed')
        data = self._parts[0] if len(self._parts) == 1 else b''.join(self._parts)
        self._parts.clear()
        self._pending = 0
        view = memoryview(data)
        good_end = self._written
        try:
            while view:
                count = os.write(self._fd, view)
                if count <= 0:  # pragma: no cover - os.write raises instead
                    raise OSError(0, 'write returned no progress')
                view = view[count:]
                self._written += count
        except OSError:
            self._cut_back(good_end)
            raise

    def _cut_back(self, size: int) -> None:
        self._parts.clear()
        self._pending = 0
        try:
            os.ftruncate(self._fd, size)
            os.lseek(self._fd, size, os.SEEK_SET)
            self._written = size
        except OSError:
            pass  # best effort: e.g. a character device cannot be truncated

    def sync(self) -> None:
        try:
            os.fsync(self._fd)
        except OSError as exc:
            # Devices and some pseudo file systems do not support fsync; that is not a failure.
            if exc.errno not in (22, 95):  # EINVAL, EOPNOTSUPP
                raise

    def close(self) -> None:
        fd, self._fd = self._fd, None
        self._parts.clear()
        self._pending = 0
        if fd is not None:
            os.close(fd)


# --------------------------------------------------------------------------------------------
# Recorder

_OPEN, _CLOSING, _CLOSED, _FAILED = 'open', 'closing', 'closed', 'failed'

_COMPRESSIONS = {
    'zstd': (CompressionType.ZSTD, _HAVE_ZSTD, 'zstandard'),
    'lz4': (CompressionType.LZ4, _HAVE_LZ4, 'lz4'),
    'none': (CompressionType.NONE, True, ''),
    '': (CompressionType.NONE, True, ''),
}


class McapRecorder:
    """Writes one feeder_sim run to an MCAP file with ROS 2 (CDR) messages.

    All channels of :data:`TOPICS` are registered when the file is opened.  Times are simulated
    time in integer nanoseconds; each message's log time, publish time and header stamp are
    that time (after a reset, :meth:`begin_episode`, log and publish times go on from where
    the previous episode ended).  Methods raise :class:`RecordingError` when the file cannot
    be written; after such an error the recorder stops writing (the file keeps every chunk
    completed before the error) and further writes raise :class:`RecordingError` too.

    ``close()`` finalizes the file; it is idempotent, thread safe and may be called from a
    signal handler, also while a write is in progress in the interrupted code: the close then
    happens as soon as that write returns.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        chunk_size: int = 256 * 1024,
        metadata: Mapping[str, str] | None = None,
        compression: str = DEFAULT_COMPRESSION,
        flush_interval: float | None = None,
        sensors: Sequence[tuple[str, str]] = (),
        log_time_origin_ns: int = 0,
    ):
        """Open ``path`` (truncating it) and write header, schemas and channels.

        ``flush_interval`` (wall-clock seconds, optional) also closes the open chunk when it is
        older than that, bounding what a hard kill can lose in slow runs.  ``metadata`` is
        written as a metadata record named ``feeder_sim``. ``sensors`` ((name, kind) pairs)
        adds the channels of :func:`sensor_topics` after those of :data:`TOPICS`. Log times
        are the simulated time plus ``log_time_origin_ns`` (ns since the Unix epoch: the
        wall-clock time at which simulated time 0 is shown; header stamps stay simulated
        time).
        """
        log_time_origin_ns = operator.index(log_time_origin_ns)
        if log_time_origin_ns < 0:
            raise ValueError(f'log_time_origin_ns must be >= 0, got {log_time_origin_ns}')
        self._path = os.fspath(path)
        if isinstance(self._path, bytes):
            self._path = os.fsdecode(self._path)
        if int(chunk_size) <= 0:
            raise ValueError(f'chunk_size must be positive, got {chunk_size}')
        try:
            compression_type, available, module = _COMPRESSIONS[str(compression).lower()]
        except KeyError:
            raise ValueError(
                f"compression must be 'zstd', 'lz4' or 'none', got {compression!r}") from None
        if not available:
            raise ValueError(f'compression {compression!r} needs the {module} package')
        if flush_interval is not None and not flush_interval > 0:
            raise ValueError(f'flush_interval must be positive, got {flush_interval}')

        self._lock = threading.RLock()
        self._busy = False
        self._close_requested = False
        self._state = _FAILED  # until fully opened
        self._error: RecordingError | None = None
        self._messages = 0
        self._flush_interval = flush_interval
        self._last_flush = time.monotonic()
        self._frames: dict[str, _Frame] = {}
        self._names_cache: tuple[tuple[str, ...], bytes] = ((), _U32.pack(0))
        self._episode = 0             # index of the running episode (reset count)
        self.log_time_origin_ns = log_time_origin_ns
        # log time = simulated time + this: the origin, then moved on by each begin_episode
        self._log_offset_ns = log_time_origin_ns
        self._last_log_ns = 0
        # the bodies whose outlines are in the log (name -> outline count), for write_outlines'
        # callers that draw parts as they come and delete them as they go
        self.outlines_drawn: dict[str, int] = {}

        try:
            self._file = _ChunkFile(self._path)
        except OSError as exc:
            raise _io_error('cannot create', self._path, exc) from exc
        try:
            self._writer = Writer(
                self._file, chunk_size=int(chunk_size), compression=compression_type)
            self._writer.start(profile='ros2', library=f'feeder_sim {_library_version()}')
            self._channels: dict[str, int] = {}
            schema_ids: dict[str, int] = {}
            topics = dict(TOPICS)
            for name, kind in sensors:
                topics.update(sensor_topics(name, kind))
            for topic, type_name in topics.items():
                if type_name not in schema_ids:
                    schema_ids[type_name] = self._writer.register_schema(
                        name=type_name, encoding='ros2msg',
                        data=msgdefs.definition(type_name).encode('utf-8'))
                self._channels[topic] = self._writer.register_channel(
                    topic=topic, message_encoding='cdr', schema_id=schema_ids[type_name])
            if metadata is not None:
                self._writer.add_metadata('feeder_sim', _check_metadata(metadata))
            self._file.flush()
        except BaseException as exc:
            self._file.close()
            if isinstance(exc, OSError):
                raise _io_error('cannot write', self._path, exc) from exc
            raise
        self._sequence = dict.fromkeys(self._channels.values(), 0)
        self._ch_clock = self._channels[TOPIC_CLOCK]
        self._ch_poses = self._channels[TOPIC_PART_POSES]
        self._ch_contacts = self._channels[TOPIC_CONTACTS]
        self._ch_track = self._channels[TOPIC_TRACK_STATE]
        self._ch_vibration = self._channels[TOPIC_VIBRATION_CMD]
        self._state = _OPEN

    # -- properties --------------------------------------------------------------------------

    @property
    def path(self) -> str:
        return self._path

    @property
    def closed(self) -> bool:
        return self._state != _OPEN

    @property
    def bytes_written(self) -> int:
        """Bytes written to the file so far (the open chunk is not counted until it is done)."""
        return self._file.tell()

    @property
    def messages_written(self) -> int:
        """Messages accepted by the recorder (including those in the open chunk)."""
        return self._messages

    # -- message writers ---------------------------------------------------------------------

    def write_clock(self, t_ns: int) -> None:
        """rosgraph_msgs/Clock on /clock."""
        self._emit(self._ch_clock, t_ns, _ENCAPSULATION + _stamp(t_ns))

    def write_part_poses(self, t_ns: int, positions, angles, frame_id: str = 'world') -> None:
        """geometry_msgs/PoseArray: planar poses (positions (n, 2) m, angles (n,) rad)."""
        stamp = _stamp(t_ns)
        positions = _as_float_array('positions', positions, (2,))
        angles = _as_float_array('angles', angles, ())
        count = angles.shape[0]
        if positions.shape[0] != count:
            raise ValueError(
                f'positions has {positions.shape[0]} rows but angles has {count} entries')
        frame = self._frame(frame_id)
        parts = [_ENCAPSULATION, stamp, frame.padded, _U32.pack(count)]
        if count:
            poses = np.zeros((count, 7), dtype='<f8')
            poses[:, 0:2] = positions
            half = 0.5 * angles
            poses[:, 5] = np.sin(half)
            poses[:, 6] = np.cos(half)
            parts.append(_pad(frame.offset + 4, 8))
            parts.append(poses.tobytes())
        self._emit(self._ch_poses, t_ns, b''.join(parts))

    def write_contacts(self, t_ns: int, points, normals, normal_impulse, tangent_impulse,
                       body_a, body_b, frame_id: str = 'world') -> None:
        """sensor_msgs/PointCloud2 with one point per contact (see :data:`CONTACT_FIELDS`)."""
        stamp = _stamp(t_ns)
        normal_impulse = _as_float_array('normal_impulse', normal_impulse, ())
        count = normal_impulse.shape[0]
        points = _as_float_array('points', points, (2,))
        normals = _as_float_array('normals', normals, (2,))
        tangent_impulse = _as_float_array('tangent_impulse', tangent_impulse, ())
        for name, array in (('points', points), ('normals', normals),
                            ('tangent_impulse', tangent_impulse)):
            if array.shape[0] != count:
                raise ValueError(
                    f'{name} has {array.shape[0]} rows but normal_impulse has {count} entries')
        body_a = _as_index_array('body_a', body_a, count)
        body_b = _as_index_array('body_b', body_b, count)
        frame = self._frame(frame_id)
        cloud = np.empty((count, 9), dtype='<f4')
        cloud[:, 0:2] = points
        cloud[:, 2] = 0.0
        cloud[:, 3:5] = normals
        cloud[:, 5] = normal_impulse
        cloud[:, 6] = tangent_impulse
        ids = cloud.view('<u4')
        ids[:, 7] = body_a
        ids[:, 8] = body_b
        size = count * CONTACT_POINT_STEP
        payload = b''.join((
            _ENCAPSULATION, stamp, frame.padded, _CLOUD_SIZE.pack(1, count), _POINTFIELDS,
            _CLOUD_TAIL.pack(False, CONTACT_POINT_STEP, size, size), cloud.tobytes(), _DENSE,
        ))
        self._emit(self._ch_contacts, t_ns, payload)

    def write_part_impulses(self, t_ns: int, centre_of_mass, impulse, angular_impulse,
                            normal_impulse, contacts, frame_id: str = 'world') -> None:
        """sensor_msgs/PointCloud2 with one point per part (see :data:`PART_IMPULSE_FIELDS`;
        arrays in the frame's part order)."""
        stamp = _stamp(t_ns)
        com = _as_float_array('centre_of_mass', centre_of_mass, (2,))
        count = com.shape[0]
        impulse = _as_float_array('impulse', impulse, (2,))
        angular = _as_float_array('angular_impulse', angular_impulse, ())
        normal = _as_float_array('normal_impulse', normal_impulse, ())
        if not impulse.shape[0] == angular.shape[0] == normal.shape[0] == count:
            raise ValueError(f'impulse arrays have {impulse.shape[0]}, {angular.shape[0]}, '
                             f'{normal.shape[0]} rows for {count} parts')
        contacts = _as_index_array('contacts', contacts, count)
        cloud = np.zeros((count, 9), dtype='<f4')
        cloud[:, 0:2] = com
        cloud[:, 3:5] = impulse
        cloud[:, 5] = angular
        cloud[:, 6] = normal
        ids = cloud.view('<u4')
        ids[:, 7] = contacts
        ids[:, 8] = np.arange(count)
        size = count * PART_IMPULSE_STEP
        payload = b''.join((
            _ENCAPSULATION, stamp, self._frame(frame_id).padded, _CLOUD_SIZE.pack(1, count),
            _PART_POINTFIELDS, _CLOUD_TAIL.pack(False, PART_IMPULSE_STEP, size, size),
            cloud.tobytes(), _DENSE,
        ))
        self._emit(self._channels[TOPIC_PART_IMPULSES], t_ns, payload)

    def write_diagnostics(self, t_ns: int, name: str, level: int, message: str,
                          values: Sequence[tuple[str, str]], hardware_id: str = 'feeder_sim'
                          ) -> None:
        """diagnostic_msgs/DiagnosticArray with one status (``level`` 0 OK, 1 WARN, 2 ERROR)."""
        body = _Cdr()
        body.stamp(t_ns, '')
        body.put(_U32, 1, align=4)
        body.put(struct.Struct('<B'), int(level), align=1)
        body.string(name)
        body.string(message)
        body.string(hardware_id)
        body.put(_U32, len(values), align=4)
        for key, value in values:
            body.string(key)
            body.string(value)
        self._emit(self._channels[TOPIC_DIAGNOSTICS], t_ns, body.payload())

    def write_track_state(self, t_ns: int, names: Sequence[str], position,
                          velocity=None) -> None:
        """sensor_msgs/JointState: names, position along the track [m], speed [m/s]."""
        stamp = _stamp(t_ns)
        count, names_block = self._names(names)
        position = _as_float_array('position', position, ())
        if position.shape[0] != count:
            raise ValueError(f'position has {position.shape[0]} entries for {count} names')
        if velocity is None:
            velocity = position[:0]
        velocity = _as_float_array('velocity', velocity, ())
        if velocity.shape[0] not in (0, count):
            raise ValueError(f'velocity has {velocity.shape[0]} entries for {count} names')
        frame = self._frame('')
        parts = [_ENCAPSULATION, stamp, frame.padded, names_block]
        offset = frame.offset + len(names_block)
        for values in (position, velocity):
            parts.append(_U32.pack(values.shape[0]))
            offset += 4
            if values.shape[0]:
                padding = _pad(offset, 8)
                parts.append(padding)
                parts.append(values.astype('<f8', copy=False).tobytes())
                offset += len(padding) + 8 * values.shape[0]
        parts.append(b'\x00\x00\x00\x00')  # effort: empty
        self._emit(self._ch_track, t_ns, b''.join(parts))

    def write_vibration_cmd(self, t_ns: int, amplitude_m: float, frequency_hz: float) -> None:
        """std_msgs/Float64MultiArray with data = [amplitude_m, frequency_hz]."""
        _stamp(t_ns)
        payload = _ENCAPSULATION + _MULTIARRAY_2.pack(
            0, 0, 2, float(amplitude_m), float(frequency_hz))
        self._emit(self._ch_vibration, t_ns, payload)

    def write_sensor(self, t_ns: int, name: str, kind: str, blocked: bool, count: int,
                     passed: Sequence[tuple[str, str]] = ()) -> None:
        """One frame of a sensor: std_msgs/Bool ``blocked`` (beam), std_msgs/UInt32 ``count``
        and a diagnostic_msgs/KeyValue (key: part, value: orientation) per part in
        ``passed`` (inspection)."""
        _stamp(t_ns)
        channel = self._channels.get(f'{SENSOR_PREFIX}{name}/count')
        if channel is None:
            raise ValueError(f'no sensor {name!r} was declared when the recorder was opened')
        if kind == 'beam':
            self._emit(self._channels[f'{SENSOR_PREFIX}{name}/blocked'], t_ns,
                       _ENCAPSULATION + bytes([bool(blocked)]))
        self._emit(channel, t_ns, _ENCAPSULATION + _U32.pack(int(count)))
        if kind == 'inspection':
            topic = self._channels[f'{SENSOR_PREFIX}{name}/passed']
            for part, orientation in passed:
                key = _cdr_string(part)
                self._emit(topic, t_ns, b''.join((_ENCAPSULATION, key, _pad(len(key), 4),
                                                  _cdr_string(orientation))))

    def write_transforms(self, t_ns: int, names: Sequence[str], origin, angle,
                         parent: str = 'world') -> None:
        """tf2_msgs/TFMessage: the frame of each body ``names`` (its scene-file body frame:
        ``origin`` (n, 2) m and ``angle`` (n,) rad in ``parent``)."""
        origin = _as_float_array('origin', origin, (2,))
        angle = _as_float_array('angle', angle, ())
        if not origin.shape[0] == angle.shape[0] == len(names):
            raise ValueError(f'{len(names)} names, {origin.shape[0]} origins and '
                             f'{angle.shape[0]} angles')
        body = _Cdr()
        body.put(_U32, len(names), align=4)
        for name, (x, y), a in zip(names, origin.tolist(), angle.tolist(), strict=True):
            body.stamp(t_ns, parent)
            body.string(name)
            body.put(_F64_3, x, y, 0.0, align=8)
            body.put(_F64_4, 0.0, 0.0, np.sin(0.5 * a), np.cos(0.5 * a), align=8)
        self._emit(self._channels[TOPIC_TF], t_ns, body.payload())

    def write_outlines(self, t_ns: int, outlines: Mapping[str, Sequence[np.ndarray]],
                       colors: Mapping[str, tuple[float, float, float, float]],
                       line_width_m: float, deleted: Mapping[str, int] | None = None) -> None:
        """visualization_msgs/MarkerArray: each body's outlines (body frame, m) as closed
        LINE_STRIP markers in the body's own frame (``frame_locked``: they move with the
        frames of :meth:`write_transforms`), namespace = body, id = outline index; and a
        DELETE for each of the ``deleted`` bodies' outlines (name -> how many it had)."""
        markers = []
        for name, polygons in outlines.items():
            for k, polygon in enumerate(polygons):
                markers.append((name, k, _ADD, np.asarray(polygon, dtype=float), colors[name]))
        for name, count in (deleted or {}).items():
            markers += [(name, k, _DELETE, np.zeros((0, 2)), (0.0, 0.0, 0.0, 0.0))
                        for k in range(count)]
        body = _Cdr()
        body.put(_U32, len(markers), align=4)
        for name, k, action, polygon, rgba in markers:
            body.stamp(t_ns, name)
            body.string(name)                                  # ns
            body.put(_I32, k, align=4)
            body.put(_I32, _LINE_STRIP, align=4)
            body.put(_I32, action, align=4)
            body.put(_F64_3, 0.0, 0.0, 0.0, align=8)           # pose: the body frame itself
            body.put(_F64_4, 0.0, 0.0, 0.0, 1.0, align=8)
            body.put(_F64_3, float(line_width_m), 0.0, 0.0, align=8)   # scale.x: line width
            body.put(_F32_4, *rgba, align=4)
            body.put(_STAMP, 0, 0, align=4)                    # lifetime: forever
            body.put(_BOOL, True, align=1)                     # frame_locked
            closed = np.vstack([polygon, polygon[:1]]) if len(polygon) else polygon
            body.put(_U32, len(closed), align=4)
            for x, y in closed.tolist():
                body.put(_F64_3, x, y, 0.0, align=8)
            body.put(_U32, 0, align=4)                         # colors
            body.string('')                                    # texture_resource
            body.stamp(0, '')                                  # texture: header, format, data
            body.string('')
            body.put(_U32, 0, align=4)
            body.put(_U32, 0, align=4)                         # uv_coordinates
            body.string('')                                    # text
            body.string('')                                    # mesh_resource
            body.string('')                                    # mesh_file: filename, data
            body.put(_U32, 0, align=4)
            body.put(_BOOL, False, align=1)                    # mesh_use_embedded_materials
        self._emit(self._channels[TOPIC_GEOMETRY], t_ns, body.payload())

    def write_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """MCAP metadata record (e.g. the scene YAML text or the solver settings)."""
        if not isinstance(name, str):
            raise TypeError('metadata name must be a str')
        data = _check_metadata(data)
        with self._writing():
            self._writer.add_metadata(name, data)
            self._file.flush()

    def begin_episode(self, gap_ns: int) -> int:
        """A new episode (the simulation was reset: its time starts again at 0); returns its
        index (the first is 0).

        Log times stay monotonic across episodes: from now on a message of simulated time t
        is logged at ``t + offset``, the offset putting t = 0 ``gap_ns`` after the last
        message so far; header stamps keep the simulated time. A metadata record
        ``episode_<index>`` holds the index and the log time at which the episode starts."""
        with self._writing():
            self._episode += 1
            self._log_offset_ns = self._last_log_ns + int(gap_ns)
            self._writer.add_metadata(f'episode_{self._episode}', {
                'index': str(self._episode), 'log_time_ns': str(self._log_offset_ns),
                'reason': 'reset'})
            self._writer.flush()
            self._file.flush()
        return self._episode

    def flush(self) -> None:
        """End the open chunk (if it holds messages) and hand everything to the OS."""
        with self._writing():
            self._writer.flush()
            self._last_flush = time.monotonic()

    # -- closing -----------------------------------------------------------------------------

    def close(self) -> None:
        """Finalize the file (last chunk, summary, footer), fsync and close it. Idempotent."""
        with self._lock:
            if self._busy:
                # Called from a signal handler that interrupted a write of this thread:
                # finishing the file now would corrupt it; the write closes it when done.
                self._close_requested = True
                return
            self._close_locked()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def __del__(self):
        # Finalize a recorder that was never closed; a finalizer cannot report errors.
        with contextlib.suppress(Exception):
            if getattr(self, '_state', None) == _OPEN:
                self.close()

    # -- internals ---------------------------------------------------------------------------

    def _frame(self, frame_id: str) -> _Frame:
        frame = self._frames.get(frame_id)
        if frame is None:
            frame = _Frame(frame_id)
            self._frames[frame_id] = frame
        return frame

    def _names(self, names: Sequence[str]) -> tuple[int, bytes]:
        """Count and encoded ``string[]`` of the joint names (cached: they rarely change)."""
        key = names if isinstance(names, tuple) else tuple(names)
        cached_key, block = self._names_cache
        if key != cached_key:
            parts = [_U32.pack(len(key))]
            for name in key:
                encoded = _cdr_string(name)
                parts.append(encoded)
                parts.append(_pad(len(encoded), 4))
            block = b''.join(parts)
            self._names_cache = (key, block)
        return len(key), block

    def _check_open(self) -> None:
        if self._state == _OPEN:
            return
        if self._state == _FAILED and self._error is not None:
            raise RecordingError(
                self._error.errno or 0,
                f'MCAP recording {self._path!r} stopped after an earlier write error: '
                f'{self._error.strerror or self._error}')
        raise RecordingError(f'MCAP recording {self._path!r} is closed')

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        """One write under the lock. An OS error marks the recording failed (what was flushed
        stays readable); a close requested meanwhile (a signal handler) runs right after."""
        with self._lock:
            self._check_open()
            self._busy = True
            try:
                yield
            except OSError as exc:
                raise self._fail(exc) from exc
            finally:
                self._busy = False
            if self._close_requested:
                self._close_locked()

    def _emit(self, channel_id: int, t_ns: int, payload: bytes) -> None:
        with self._writing():
            sequence = (self._sequence[channel_id] + 1) & 0xFFFFFFFF
            self._sequence[channel_id] = sequence
            log_ns = t_ns + self._log_offset_ns
            self._last_log_ns = max(self._last_log_ns, log_ns)
            self._writer.add_message(
                channel_id, log_time=log_ns, data=payload, publish_time=log_ns,
                sequence=sequence)
            self._messages += 1
            if self._file.pending:
                # The writer just finished a chunk and its message indexes.
                self._file.flush()
                self._last_flush = time.monotonic()
            elif self._flush_interval is not None and (
                    time.monotonic() - self._last_flush >= self._flush_interval):
                self._writer.flush()
                self._last_flush = time.monotonic()

    def _fail(self, exc: OSError) -> RecordingError:
        error = exc if isinstance(exc, RecordingError) else _io_error(
            'cannot write to', self._path, exc)
        self._state = _FAILED
        self._error = error
        try:
            self._file.close()
        except OSError:
            pass
        return error

    def _close_locked(self) -> None:
        self._close_requested = False
        if self._state == _FAILED:
            self._state = _CLOSED
            return
        if self._state != _OPEN:
            return  # closed, or being closed further up this thread's stack
        self._state = _CLOSING
        try:
            self._writer.finish()
            self._file.flush()
            self._file.sync()
        except OSError as exc:
            self._error = _io_error('cannot finalize', self._path, exc)
            raise self._error from exc
        finally:
            self._state = _CLOSED
            try:
                self._file.close()
            except OSError:
                pass


def _check_metadata(data: Mapping[str, str]) -> dict[str, str]:
    result = dict(data)
    for key, value in result.items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise TypeError('metadata keys and values must be str')
    return result


# --------------------------------------------------------------------------------------------
# Reading back


def read_messages(path: str | os.PathLike,
                  topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
    """Yield ``(topic, log_time_ns, cdr_payload)`` of every message, in file order.

    Works on finalized files and on files whose writer was killed: reading stops quietly at the
    first record that is incomplete (or at a chunk that fails its CRC), after yielding every
    message of the complete chunks before it.  A file that does not start like an MCAP file
    raises ``ValueError``; an empty file yields nothing.
    """
    wanted = None if topics is None else {topics} if isinstance(topics, str) else set(topics)
    with open(path, 'rb') as stream:
        size = os.fstat(stream.fileno()).st_size
        magic = stream.read(len(_MCAP_MAGIC))
        if magic != _MCAP_MAGIC:
            if _MCAP_MAGIC.startswith(magic):
                return  # cut off before (or inside) the leading magic
            raise ValueError(f'{os.fspath(path)!r} is not an MCAP file')
        channels: dict[int, str] = {}
        for opcode, body, offset in top_level_records(stream, size, _MESSAGE_OPCODES):
            try:
                records = _parse_record(opcode, body)
            except Exception as exc:  # noqa: BLE001 - a damaged record ends the readable part
                warnings.warn(f'{os.fspath(path)!r}: stopped reading at a damaged record '
                              f'at offset {offset - _RECORD_HEADER.size}: {exc}', stacklevel=2)
                return
            for record in records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    topic = channels.get(record.channel_id)
                    if topic is not None and (wanted is None or topic in wanted):
                        yield topic, record.log_time, record.data


_MESSAGE_OPCODES = frozenset((Opcode.CHANNEL, Opcode.MESSAGE, Opcode.CHUNK))


def top_level_records(stream, size: int, opcodes: Container[int]
                      ) -> Iterator[tuple[int, bytes, int]]:
    """``(opcode, body, offset)`` of the top-level records from the stream's position (just past
    the magic) on, for the opcodes asked for; other records are skipped unread.

    Needs neither the summary nor the footer (a killed writer leaves neither): stops at the
    footer, at the data end, or quietly at the first record the file holds only part of.
    ``offset`` is the body's position in the file, ``size`` the file's length.
    """
    position = stream.tell()
    while True:
        head = stream.read(_RECORD_HEADER.size)
        if len(head) < _RECORD_HEADER.size:
            return
        opcode, length = _RECORD_HEADER.unpack(head)
        position += _RECORD_HEADER.size
        if length > size - position or opcode in (Opcode.FOOTER, Opcode.DATA_END):
            return
        if opcode in opcodes:
            body = stream.read(length)
            if len(body) < length:
                return
            yield opcode, body, position
        else:
            stream.seek(length, io.SEEK_CUR)
        position += length


def _parse_record(opcode: int, body: bytes) -> list:
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.CHANNEL:
        return [Channel.read(stream)]
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, len(body))]
    chunk = Chunk.read(stream)
    if chunk.compression == '' and len(chunk.data) != chunk.uncompressed_size:
        raise ValueError('chunk data is shorter than its declared size')
    records = breakup_chunk(chunk, validate_crc=True)
    return [record for record in records if isinstance(record, (Channel, Message))]

