"""Turn a feeder_sim MCAP log into a rerun recording (``.rrd``) and optionally show it.

>>> replay('run.mcap')                  # writes run.rrd; opens the viewer if there is a display
>>> replay('run.mcap', 'out.rrd', spawn=False)

Everything is logged on the duration timeline ``sim_time`` (simulated time; each message's
log time) and nothing on the wall-clock ``log_time`` / ``log_tick`` timelines. A log of a node
that was reset holds several episodes: ``sim_time`` goes on across them (each starts one frame
after the previous ended), the ``episode`` timeline holds each message's episode index and
``episode_time`` its simulated time within the episode, and ``/episodes`` marks each reset:

``/world`` (2D view, metres, world frame; the view flips it so that y points up)
    ``/world/track``            static and kinematic bodies: closed outlines, logged once
                                (static) at their nominal pose. The vibrating track is not
                                animated: its motion (amplitude below a millimetre) is the
                                scene's prescribed drive, not recorded data.
    ``/world/parts``            dynamic bodies: outline of every piece at every pose message,
                                one colour per part, labelled with the part names. Parts that
                                come and go (sources and sinks) are told apart by the names
                                track_state gives at the same time, a source's parts drawn
                                with their template's shape. Without a scene in the log (older
                                or foreign logs), the part origins as points instead.
    ``/world/parts/origins``    body-frame origins (the recorded poses) as points.
    ``/world/contacts/points``  contact points of each contacts message.
    ``/world/contacts/impulses`` impulse that body_b gave body_a (the body owning the contact
                                vertex) over the interval since the previous message,
                                ``normal_impulse * n + tangent_impulse * t`` with
                                ``t = (-n_y, n_x)``, drawn at :func:`impulse_scale` metres per
                                N s from the contact point.
``/plots``
    ``/plots/position/<part>``  position along the track [mm] (from ``track_state``).
    ``/plots/speed/<part>``     speed along the track [mm/s].
    ``/plots/vibration/amplitude``, ``/plots/vibration/frequency``  the vibration commands
                                [µm 0-peak, Hz], drawn as steps; the last command is repeated
                                at the end of the log so that the line spans it.
``/notes``                      a text document with the units and the arrow scale.

The recording also carries the property ``replay`` (log name, scene, method, arrow scale) and a
blueprint: the 2D view above three time-series views, time panel on ``sim_time``.

Logs are read with :func:`feeder_sim.output.recording.read_messages`, so logs of a killed writer
(no footer) convert up to their last complete chunk. Topics other than the feeder_sim ones are
ignored. Conversion time (2-core machine): a 10-part, 100 Hz, 10 s log (4 000 messages) about 0.2
s, plus about 1 s of imports from the command line; a synthetic 50-part, 100 Hz, 60 s log (24 000
messages, 15 MB) about 1.7 s.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
import functools
import hashlib
import io
import json
import logging
import math
import os
from pathlib import Path
import struct
import subprocess
import sys
from typing import NamedTuple
import uuid
import warnings

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Metadata
import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from feeder_sim.model.scene import parse_scene, Scene
from feeder_sim.output import msgdefs
from feeder_sim.output.recording import (
    CONTACT_FIELDS,
    CONTACT_POINT_DTYPE,
    read_messages,
    SENSOR_PREFIX,
    top_level_records,
    TOPIC_CONTACTS,
    TOPIC_PART_POSES,
    TOPIC_TRACK_STATE,
    TOPIC_VIBRATION_CMD,
    TOPICS,
)

__all__ = ['APPLICATION_ID', 'TIMELINE', 'impulse_scale', 'part_size', 'replay']

log = logging.getLogger('feeder_sim')

APPLICATION_ID = 'feeder_sim'
TIMELINE = 'sim_time'
EPISODE_TIMELINE = 'episode'
EPISODE_TIME_TIMELINE = 'episode_time'

#: The reference impulse (a percentile of all contact impulse magnitudes in the log) is drawn
#: as this fraction of the characteristic part size.
ARROW_FRACTION = 0.3
ARROW_PERCENTILE = 95.0
#: Part size assumed when the log carries no scene (m).
DEFAULT_PART_SIZE_M = 0.01

_MCAP_MAGIC = b'\x89MCAP0\r\n'
_U32 = struct.Struct('<I')
_CDR_LE = b'\x00\x01'  # encapsulation kind: plain CDR, little endian (what ROS 2 writes)

# Part colours (RGB), assigned by part index so that a part keeps its colour across views.
_PALETTE = np.array([
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
], dtype=np.uint8)
_TRACK_COLOUR = (90, 90, 90)
_CONTACT_COLOUR = (230, 30, 30)
_IMPULSE_COLOUR = (255, 150, 0)
_LINE_WIDTH = rr.components.Radius.ui_points(1.0)
_POINT_RADIUS = rr.components.Radius.ui_points(2.0)


# --------------------------------------------------------------------------------------------
# Reading the log


class _Series(NamedTuple):
    """Samples of one part from track_state: times (ns), position (m), speed (m/s)."""

    t: np.ndarray
    position: np.ndarray
    speed: np.ndarray


@dataclass
class _Log:
    """What the replay needs from a log, as flat arrays (times in ns, lengths in m)."""

    path: Path
    metadata: dict[str, str]
    scene: Scene | None
    pose_t: np.ndarray          # (n,) int64
    pose_count: np.ndarray      # (n,) poses per message
    origin: np.ndarray          # (sum(pose_count), 2)
    angle: np.ndarray           # (sum(pose_count),) rad
    contact_t: np.ndarray       # (m,) int64
    contact_count: np.ndarray   # (m,)
    contacts: np.ndarray        # (sum(contact_count),) CONTACT_POINT_DTYPE
    series: dict[str, _Series]  # part name -> track_state samples, in order of appearance
    vibration_t: np.ndarray     # (v,) int64
    vibration: np.ndarray       # (v, 2) amplitude m, frequency Hz
    end_t: int                  # largest message time seen
    # log times (ns) at which episodes 1, 2, ... start (the simulation was reset); empty: one
    episode_starts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # the parts track_state named at each time (ns): which pose is which part
    frame_names: dict = field(default_factory=dict)
    # the scene's sensors: topic suffix ('<name>/count', ...) -> [(t ns, value), ...]
    sensors: dict = field(default_factory=dict)


def _check_mcap(path: Path) -> None:
    """Raise OSError / ValueError (naming ``path``) unless it is a readable MCAP file."""
    if not path.exists():
        raise FileNotFoundError(f'{path}: no such file')
    if path.is_dir():
        raise IsADirectoryError(f'{path}: is a directory, not an MCAP log')
    with open(path, 'rb') as stream:
        magic = stream.read(len(_MCAP_MAGIC))
    if magic != _MCAP_MAGIC:
        what = 'is empty' if not magic else 'is not an MCAP file'
        if magic and _MCAP_MAGIC.startswith(magic):
            what = 'ends inside the MCAP magic (no data)'
        raise ValueError(f'{path}: {what}')


def _read_metadata(path: Path) -> dict[str, dict[str, str]]:
    """Metadata records by name, from a walk over the top-level records.

    The walk needs neither the summary nor the footer (a killed writer leaves neither) and
    skips chunk bodies without reading them; it stops at the first incomplete record.
    """
    found: dict[str, dict[str, str]] = {}
    with open(path, 'rb') as stream:
        size = os.fstat(stream.fileno()).st_size
        stream.seek(len(_MCAP_MAGIC))
        for _, body, _ in top_level_records(stream, size, (Opcode.METADATA,)):
            try:
                record = Metadata.read(ReadDataStream(io.BytesIO(body)))
            except Exception:  # noqa: BLE001 - a damaged record ends the readable part
                break
            found[record.name] = record.metadata
    return found


def _scene_from(metadata: dict[str, str], path: Path) -> Scene | None:
    text = metadata.get('scene_json')
    if not text:
        return None
    try:
        return parse_scene(json.loads(text), source=f'{path}:scene_json')
    except ValueError as err:  # json errors and SceneError are ValueErrors
        log.warning('%s: ignoring the scene stored in the log: %s', path, err)
        return None


class _Cdr:
    """Sequential reader of a little-endian CDR payload (XCDR1 alignment), for the fast paths.

    Raises ValueError (or struct.error) on anything unexpected; the caller then falls back to
    the generic decoder.
    """

    def __init__(self, data: bytes):
        if data[:2] != _CDR_LE:
            raise ValueError('not little-endian CDR')
        self.buf = memoryview(data)[4:]  # alignment counts from the end of the encapsulation
        self.pos = 0

    def take(self, size: int, align: int) -> int:
        """Start offset of the next ``size`` bytes aligned to ``align``; moves past them."""
        self.pos += -self.pos % align
        start = self.pos
        self.pos += size
        if self.pos > len(self.buf):
            raise ValueError('payload too short')
        return start

    def u8(self) -> int:
        return self.buf[self.take(1, 1)]

    def u32(self) -> int:
        return _U32.unpack_from(self.buf, self.take(4, 4))[0]

    def string(self) -> str:
        size = self.u32()
        start = self.take(size, 1)
        return bytes(self.buf[start:start + max(size - 1, 0)]).decode('utf-8')

    def header(self) -> None:
        """Skip a std_msgs/Header (stamp and frame_id)."""
        self.take(8, 4)
        self.take(self.u32(), 1)

    def float64s(self) -> np.ndarray:
        count = self.u32()
        # An empty sequence has no elements and hence no padding before them.
        start = self.take(8 * count, 8) if count else self.pos
        return np.frombuffer(self.buf, '<f8', count, start)

    def cached(self, cache: list, parse: Callable[[], object]) -> object:
        """``parse()`` the next block, or skip it when it repeats the previous message's bytes
        at the same offset (names and point fields rarely change between messages)."""
        start, block, value = cache
        here = self.pos
        if start == here and block and self.buf[here:here + len(block)] == block:
            self.pos += len(block)
            return value
        value = parse()
        cache[:] = [here, bytes(self.buf[here:self.pos]), value]
        return value


def _cloud_points(fields: dict[str, tuple[int, int]], big_endian: bool, point_step: int,
                  count: int, data) -> np.ndarray:
    """The points of a contacts PointCloud2 as CONTACT_POINT_DTYPE records (fields found by
    name, so another field order or point step reads too)."""
    if big_endian or any(fields.get(name, (0, None))[1] != code
                         for name, _, code in CONTACT_FIELDS):
        raise ValueError('not a feeder_sim contact cloud')
    dtype = _cloud_dtype(tuple(fields[name][0] for name in CONTACT_POINT_DTYPE.names),
                         point_step)
    points = np.frombuffer(data, dtype, count)
    return points if dtype == CONTACT_POINT_DTYPE else points.astype(CONTACT_POINT_DTYPE)


@functools.lru_cache(maxsize=8)
def _cloud_dtype(offsets: tuple[int, ...], point_step: int) -> np.dtype:
    names = list(CONTACT_POINT_DTYPE.names)
    return np.dtype({'names': names, 'formats': [CONTACT_POINT_DTYPE.fields[n][0] for n in names],
                     'offsets': list(offsets), 'itemsize': point_step})


def _yaw(q: np.ndarray) -> np.ndarray:
    """Rotation about z (rad) of quaternions (k, 4) xyzw."""
    x, y, z, w = np.asarray(q, float).reshape(-1, 4).T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class _Decoder:
    """Decodes the payloads of the topics the replay uses into plain arrays:

    * poses: (origins (k, 2) m, orientation quaternions (k, 4) xyzw)
    * track_state: (names, position (k,) m, velocity m/s: (k,) or empty)
    * contacts: CONTACT_POINT_DTYPE records
    * vibration_cmd: data (float64 array)

    :meth:`fast` reads the plain little-endian CDR with numpy (the generic decoder builds a
    Python object per pose and string: seconds for long logs); :meth:`generic` uses
    mcap_ros2's decoder on the ROS 2 definitions; ``__call__`` tries the first, then the
    second.
    """

    TOPICS = (TOPIC_PART_POSES, TOPIC_CONTACTS, TOPIC_TRACK_STATE, TOPIC_VIBRATION_CMD)

    def __init__(self) -> None:
        from mcap_ros2._dynamic import generate_dynamic

        self._generic = {}
        for topic in self.TOPICS:
            name = TOPICS[topic]
            self._generic[topic] = generate_dynamic(name, msgdefs.definition(name))[name]
        self._names: list = [-1, b'', ()]
        self._fields: list = [-1, b'', {}]

    def __call__(self, topic: str, data: bytes):
        try:
            return self.fast(topic, data)
        except (ValueError, IndexError, struct.error):
            return self.generic(topic, data)

    def fast(self, topic: str, data: bytes):
        r = _Cdr(data)
        if topic == TOPIC_VIBRATION_CMD:
            for _ in range(r.u32()):  # layout.dim
                r.string(), r.u32(), r.u32()
            r.u32()  # layout.data_offset
            return r.float64s()
        r.header()
        if topic == TOPIC_PART_POSES:
            count = r.u32()
            start = r.take(56 * count, 8) if count else r.pos
            poses = np.frombuffer(r.buf, '<f8', 7 * count, start).reshape(count, 7)
            return poses[:, 0:2], poses[:, 3:7]
        if topic == TOPIC_TRACK_STATE:
            names = r.cached(self._names, lambda: tuple(r.string() for _ in range(r.u32())))
            return names, r.float64s(), r.float64s()
        if topic == TOPIC_CONTACTS:
            count = r.u32() * r.u32()  # height * width
            fields = r.cached(self._fields, lambda: self._point_fields(r))
            big_endian, point_step = bool(r.u8()), r.u32()
            r.u32()  # row_step
            size = r.u32()
            start = r.take(size, 1)
            return _cloud_points(fields, big_endian, point_step, count,
                                 r.buf[start:start + size])
        raise ValueError(f'no decoder for {topic}')

    @staticmethod
    def _point_fields(r: _Cdr) -> dict[str, tuple[int, int]]:
        fields = {}
        for _ in range(r.u32()):
            name = r.string()
            offset, datatype = r.u32(), r.u8()
            r.u32()  # count
            fields[name] = (offset, datatype)
        return fields

    def generic(self, topic: str, data: bytes):
        m = self._generic[topic](data)
        if topic == TOPIC_PART_POSES:
            origins = [(p.position.x, p.position.y) for p in m.poses]
            q = [(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
                 for p in m.poses]
            return np.array(origins, float).reshape(-1, 2), np.array(q, float).reshape(-1, 4)
        if topic == TOPIC_TRACK_STATE:
            return tuple(m.name), np.asarray(m.position, float), np.asarray(m.velocity, float)
        if topic == TOPIC_CONTACTS:
            fields = {f.name: (f.offset, f.datatype) for f in m.fields}
            return _cloud_points(fields, m.is_bigendian, m.point_step, m.width * m.height,
                                 bytes(m.data))
        return np.asarray(m.data, float)


def _messages(path: Path) -> Iterator[tuple[str, int, object]]:
    """(topic, time ns, decoded message) of the topics the replay uses (the sensors': see
    :func:`_sensor_value`); undecodable messages are skipped with one warning per topic
    (foreign logs may use other layouts)."""
    decode = _Decoder()
    failed: set[str] = set()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        for topic, t_ns, data in read_messages(path):
            sensor = topic.startswith(SENSOR_PREFIX)
            if not sensor and topic not in _Decoder.TOPICS:
                continue
            try:
                message = _sensor_value(topic, data) if sensor else decode(topic, data)
            except Exception as err:  # noqa: BLE001 - skip what this replay cannot read
                if topic not in failed:
                    failed.add(topic)
                    log.warning('%s: skipping %s messages that cannot be decoded (%s)',
                                path, topic, err)
                continue
            yield topic, t_ns, message
    for warning in caught:  # e.g. "stopped reading at a damaged record"
        log.warning('%s', warning.message)


def _finalized(path: Path) -> bool:
    """Whether the log ends in the MCAP magic after its footer (its writer finished it)."""
    with open(path, 'rb') as stream:
        size = os.fstat(stream.fileno()).st_size
        if size < 2 * len(_MCAP_MAGIC):
            return False
        stream.seek(size - len(_MCAP_MAGIC))
        return stream.read() == _MCAP_MAGIC


def _read_log(path: Path) -> _Log:
    _check_mcap(path)
    finished = _finalized(path)
    records = _read_metadata(path)
    metadata = records.get('feeder_sim', {})
    # log times count simulated time from this wall-clock instant (0: from the epoch)
    origin = int(metadata.get('log_time_origin_ns', 0))
    episode_starts = np.sort(np.array(
        [int(m.get('log_time_ns', 0)) - origin for name, m in records.items()
         if name.startswith('episode_')], np.int64))
    poses, contacts, track, vibration = [], [], [], []
    sensors: dict[str, list] = {}
    end_t = 0
    for topic, t_ns, message in _messages(path):
        t_ns -= origin
        if topic.startswith(SENSOR_PREFIX):
            if message is not None:
                sensors.setdefault(topic[len(SENSOR_PREFIX):], []).append((t_ns, message))
            continue
        end_t = max(end_t, t_ns)
        if topic == TOPIC_PART_POSES:
            poses.append((t_ns, *message))
        elif topic == TOPIC_CONTACTS:
            contacts.append((t_ns, message))
        elif topic == TOPIC_TRACK_STATE:
            track.append((t_ns, *message))
        elif len(message) >= 2:
            vibration.append((t_ns, message[:2]))
    if not finished:
        log.warning('%s: the log ends without its footer (its writer stopped before finishing '
                    'it); replaying the %d frames up to its last whole record', path, len(poses))
    # Stable sorts by time: files are in time order unless chunks were written out of order.
    poses.sort(key=lambda m: m[0])
    contacts.sort(key=lambda m: m[0])
    vibration.sort(key=lambda m: m[0])
    for samples in sensors.values():
        samples.sort(key=lambda m: m[0])
    return _Log(
        path=path, metadata=metadata, scene=_scene_from(metadata, path),
        pose_t=np.array([m[0] for m in poses], np.int64),
        pose_count=np.array([len(m[1]) for m in poses], np.int64),
        origin=_concat([m[1] for m in poses], (0, 2)),
        angle=_yaw(_concat([m[2] for m in poses], (0, 4))),
        contact_t=np.array([m[0] for m in contacts], np.int64),
        contact_count=np.array([len(m[1]) for m in contacts], np.int64),
        contacts=(np.concatenate([m[1] for m in contacts]) if contacts
                  else np.zeros(0, CONTACT_POINT_DTYPE)),
        series=_track_series(track),
        vibration_t=np.array([m[0] for m in vibration], np.int64),
        vibration=np.array([m[1] for m in vibration], float).reshape(-1, 2),
        end_t=end_t, episode_starts=episode_starts,
        frame_names={m[0]: tuple(m[1][:len(m[2])]) for m in track},
        sensors=sensors,
    )


def _sensor_value(topic: str, data: bytes):
    """A sensor's message (``recording.SENSOR_TOPICS``): blocked as 0/1, a count, a (part,
    orientation) pair; None for a topic of another kind."""
    r = _Cdr(data)
    if topic.endswith('/blocked'):
        return r.u8()
    if topic.endswith('/count'):
        return r.u32()
    if topic.endswith('/passed'):
        return r.string(), r.string()
    return None


def _concat(arrays: list[np.ndarray], empty_shape: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(arrays) if arrays else np.zeros(empty_shape)


def _track_series(samples: list[tuple]) -> dict[str, _Series]:
    """Per part name, in order of first appearance: the (time, position, speed) samples of
    the track_state messages (t ns, names, position, velocity) that name it. Messages with
    the same names are stacked together, so the usual log costs a few array operations."""
    groups: dict[tuple[str, ...], list] = {}
    for t_ns, names, position, velocity in samples:
        names = names[:len(position)]
        if len(velocity) != len(names):  # velocity is optional in JointState
            velocity = np.full(len(names), math.nan)
        groups.setdefault(names, []).append((t_ns, position[:len(names)], velocity))
    pieces: dict[str, list] = {}
    for names, rows in groups.items():
        t = np.array([row[0] for row in rows], np.int64)
        position = np.stack([row[1] for row in rows]) if names else None
        velocity = np.stack([row[2] for row in rows]) if names else None
        for j, name in enumerate(names):
            pieces.setdefault(name, []).append((t, position[:, j], velocity[:, j]))
    series = {}
    for name, parts in pieces.items():
        t = np.concatenate([p[0] for p in parts])
        order = np.argsort(t, kind='stable')
        series[name] = _Series(t[order], np.concatenate([p[1] for p in parts])[order],
                               np.concatenate([p[2] for p in parts])[order])
    return series


# --------------------------------------------------------------------------------------------
# Geometry and scales


def _closed(polygon: np.ndarray) -> np.ndarray:
    return np.concatenate([polygon, polygon[:1]])


def _transform(points: np.ndarray, pose) -> np.ndarray:
    """``R(theta) p + (x, y)`` of points (k, 2) for a pose (x, y, theta)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return points @ np.array([[c, s], [-s, c]]) + np.asarray(pose[:2])


def _parts(scene: Scene | None) -> list:
    return [b for b in scene.bodies if b.type == 'dynamic'] if scene is not None else []


def part_size(scene: Scene | None) -> float:
    """Characteristic part size (m): the median over the dynamic bodies of their largest
    vertex-to-vertex distance; :data:`DEFAULT_PART_SIZE_M` without a scene."""
    sizes = []
    for body in _parts(scene):
        v = np.concatenate(body.outlines)
        sizes.append(float(np.max(np.linalg.norm(v[:, None] - v[None], axis=-1))))
    return float(np.median(sizes)) if sizes else DEFAULT_PART_SIZE_M


def impulse_scale(contacts: np.ndarray, size_m: float) -> tuple[float, float]:
    """(arrow length per impulse in m/(N s), reference impulse in N s) for the contact arrows.

    The reference impulse is the :data:`ARROW_PERCENTILE` percentile of the non-zero impulse
    magnitudes ``|(normal_impulse, tangent_impulse)|`` over the whole log (a percentile, so
    that a few collisions do not shrink every other arrow); it is drawn
    :data:`ARROW_FRACTION` x ``size_m`` long. Without any impulse the reference is 1 N s.
    """
    magnitude = np.hypot(contacts['normal_impulse'].astype(float),
                         contacts['tangent_impulse'].astype(float))
    magnitude = magnitude[np.isfinite(magnitude) & (magnitude > 0)]
    reference = float(np.percentile(magnitude, ARROW_PERCENTILE)) if magnitude.size else 1.0
    return ARROW_FRACTION * size_m / reference, reference


def _impulse_vectors(contacts: np.ndarray, scale: float) -> np.ndarray:
    """Arrow vectors (k, 2) m: ``scale * (p_n n + p_t t)`` with ``t = perp(n) = (-n_y, n_x)``,
    the tangent the solvers use (dynamics.contact_set), so this is the impulse on body_a."""
    n = np.stack([contacts['normal_x'], contacts['normal_y']], 1).astype(float)
    t = np.stack([-n[:, 1], n[:, 0]], 1)
    p_n = contacts['normal_impulse'].astype(float)[:, None]
    p_t = contacts['tangent_impulse'].astype(float)[:, None]
    return scale * (p_n * n + p_t * t)


def _colour(index: int) -> np.ndarray:
    return _PALETTE[index % len(_PALETTE)]


def _part_names(log_: _Log) -> list[str]:
    """Names of the parts in pose order: the scene's dynamic bodies, else track_state's."""
    parts = _parts(log_.scene)
    if parts:
        return [b.name for b in parts]
    names = list(log_.series)
    count = int(log_.pose_count.max()) if log_.pose_count.size else 0
    return names[:count] + [f'part_{i}' for i in range(len(names), count)]


# --------------------------------------------------------------------------------------------
# Logging to rerun


def _time_columns(log_: _Log, t_ns: np.ndarray) -> list[rr.TimeColumn]:
    """``sim_time`` (the log time) and, in a log with resets, ``episode`` (its index) and
    ``episode_time`` (simulated time since the reset)."""
    t = np.asarray(t_ns, np.int64)
    columns = [rr.TimeColumn(TIMELINE, duration=t.astype('timedelta64[ns]'))]
    if log_.episode_starts.size:
        episode = np.searchsorted(log_.episode_starts, t, side='right')
        start = np.concatenate([[0], log_.episode_starts])[episode]
        columns += [rr.TimeColumn(EPISODE_TIMELINE, sequence=episode),
                    rr.TimeColumn(EPISODE_TIME_TIMELINE,
                                  duration=(t - start).astype('timedelta64[ns]'))]
    return columns


def _strips_array(vertices: np.ndarray, lengths: np.ndarray) -> pa.Array:
    """LineStrip2D arrow array of strips stored back to back in ``vertices`` (n, 2)."""
    datatype = rr.components.LineStrip2DBatch([]).as_arrow_array().type
    flat = pa.array(np.ascontiguousarray(vertices, np.float32).reshape(-1), pa.float32())
    points = pa.FixedSizeListArray.from_arrays(flat, type=datatype.value_type)
    offsets = np.zeros(len(lengths) + 1, np.int32)
    np.cumsum(lengths, out=offsets[1:])
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), points, type=datatype)


def _log_fixed_bodies(rec: rr.RecordingStream, scene: Scene) -> None:
    """Static and kinematic bodies at their nominal pose, once (static)."""
    strips, labels = [], []
    for body in scene.bodies:
        if body.type != 'dynamic':
            for outline in body.outlines:
                strips.append(_transform(_closed(outline), body.pose))
                labels.append(body.name)
    if strips:
        rec.log('/world/track', rr.LineStrips2D(strips, labels=labels, colors=_TRACK_COLOUR,
                                                radii=_LINE_WIDTH), static=True)


def _log_parts(rec: rr.RecordingStream, log_: _Log, names: list[str]) -> None:
    parts = _parts(log_.scene)
    time = _time_columns(log_, log_.pose_t)
    outlines = bool(parts) and bool(np.all(log_.pose_count == len(parts)))
    changing = None
    if parts and not outlines:
        changing = _shapes_by_frame(log_)      # parts that came and went (sources and sinks)
        if changing is not None:
            outlines = True
        else:
            log.warning('%s: pose counts differ from the scene\'s %d parts; drawing origins '
                        'only', log_.path, len(parts))
    colours = np.array([_colour(i) for i in range(len(names))], np.uint8).reshape(-1, 3)
    origin_path = '/world/parts/origins' if outlines else '/world/parts'
    rec.log(origin_path, rr.Points2D.from_fields(
        colors=colours, radii=_POINT_RADIUS, labels=None if outlines else names), static=True)
    rec.send_columns(origin_path, indexes=time,
                     columns=rr.Points2D.columns(positions=log_.origin).partition(
                         log_.pose_count))
    if changing is not None:
        _log_changing_outlines(rec, log_, changing, time)
    elif outlines:
        _log_outlines(rec, log_, parts, time)


def _shapes_by_frame(log_: _Log) -> list[list] | None:
    """Per pose message, the body of each pose (the part's own, or for a part a source added,
    ``<template>_<k>``, its template's), from the names track_state gave at the same time;
    None when a frame cannot be told apart."""
    bodies = {b.name: b for b in _parts(log_.scene)}
    out = []
    for t, count in zip(log_.pose_t.tolist(), log_.pose_count.tolist()):
        names = log_.frame_names.get(t)
        if names is None or len(names) != count:
            return None
        frame = []
        for name in names:
            body = bodies.get(name) or bodies.get(name.rpartition('_')[0])
            if body is None:
                return None
            frame.append((name, body))
        out.append(frame)
    return out


def _log_changing_outlines(rec: rr.RecordingStream, log_: _Log, shapes: list[list],
                           time: list) -> None:
    """The outlines of parts that come and go: each frame's parts with their own shapes,
    coloured by name (in order of first appearance)."""
    order: dict[str, int] = {}
    strips, lengths, colours, labels = [], [], [], []
    offset = 0
    for frame in shapes:
        count = 0
        for k, (name, body) in enumerate(frame):
            pose = (*log_.origin[offset + k], log_.angle[offset + k])
            colour = _colour(order.setdefault(name, len(order)))
            for outline in body.outlines:
                strips.append(_transform(_closed(outline), pose))
                colours.append(colour)
                labels.append(name)
                count += 1
        offset += len(frame)
        lengths.append(count)
    rec.log('/world/parts', rr.LineStrips2D.from_fields(radii=_LINE_WIDTH), static=True)
    rec.send_columns('/world/parts', indexes=time, columns=rr.LineStrips2D.columns(
        strips=strips, colors=np.array(colours, np.uint8).reshape(-1, 3),
        labels=labels).partition(lengths))


def _log_outlines(rec: rr.RecordingStream, log_: _Log, parts: list,
                  time: rr.TimeColumn) -> None:
    """Every piece of every part, transformed by each recorded pose, closed."""
    loops = [(i, _closed(outline)) for i, body in enumerate(parts) for outline in body.outlines]
    vertex = np.concatenate([loop for _, loop in loops])            # (V, 2) body frames
    vertex_part = np.concatenate([np.full(len(loop), i) for i, loop in loops])
    lengths = np.array([len(loop) for _, loop in loops])
    n = len(log_.pose_t)
    origin = log_.origin.reshape(n, len(parts), 2)[:, vertex_part]  # (n, V, 2)
    angle = log_.angle.reshape(n, len(parts))[:, vertex_part]       # (n, V)
    c, s = np.cos(angle), np.sin(angle)
    world = np.stack([c * vertex[:, 0] - s * vertex[:, 1],
                      s * vertex[:, 0] + c * vertex[:, 1]], -1) + origin
    strips = _strips_array(world.reshape(-1, 2), np.tile(lengths, n))
    rec.log('/world/parts', rr.LineStrips2D.from_fields(
        colors=[_colour(i) for i, _ in loops], labels=[parts[i].name for i, _ in loops],
        radii=_LINE_WIDTH), static=True)
    rec.send_columns('/world/parts', indexes=time,
                     columns=rr.LineStrips2D.columns(strips=strips).partition(
                         np.full(n, len(loops))))


def _log_contacts(rec: rr.RecordingStream, log_: _Log, scale: float) -> None:
    if not log_.contact_t.size:
        return
    c = log_.contacts
    points = np.stack([c['x'], c['y']], 1).astype(np.float32)
    time = _time_columns(log_, log_.contact_t)
    rec.log('/world/contacts/points', rr.Points2D.from_fields(
        colors=_CONTACT_COLOUR, radii=_POINT_RADIUS), static=True)
    rec.send_columns('/world/contacts/points', indexes=time,
                     columns=rr.Points2D.columns(positions=points).partition(
                         log_.contact_count))
    rec.log('/world/contacts/impulses', rr.Arrows2D.from_fields(
        colors=_IMPULSE_COLOUR, radii=_LINE_WIDTH), static=True)
    rec.send_columns('/world/contacts/impulses', indexes=time,
                     columns=rr.Arrows2D.columns(
                         origins=points,
                         vectors=_impulse_vectors(c, scale).astype(np.float32),
                     ).partition(log_.contact_count))


def _log_series(rec: rr.RecordingStream, log_: _Log, names: list[str]) -> None:
    """Along-track position [mm] and speed [mm/s] per part, columnar."""
    index = {name: i for i, name in enumerate(names)}
    for k, (name, s) in enumerate(log_.series.items()):
        colour = _colour(index.get(name, k))
        part = rr.escape_entity_path_part(name)
        time = _time_columns(log_, s.t)
        for kind, values, unit in (('position', s.position, 'mm'),
                                   ('speed', s.speed, 'mm/s')):
            path = f'/plots/{kind}/{part}'
            rec.log(path, rr.SeriesLines(names=f'{name} [{unit}]', colors=colour),
                    static=True)
            rec.send_columns(path, indexes=time, columns=rr.Scalars.columns(
                scalars=1e3 * np.asarray(values, float)))


def _log_sensors(rec: rr.RecordingStream, log_: _Log) -> None:
    """Each sensor's count and beam state as plots, each passing part as a line of text."""
    for suffix, samples in sorted(log_.sensors.items()):
        name, kind = suffix.rsplit('/', 1)
        t = np.array([x[0] for x in samples], np.int64)
        if kind == 'passed':
            for ti, (part, orientation) in samples:
                rec.set_time(TIMELINE, duration=np.timedelta64(ti, 'ns'))
                rec.log(f'/sensors/{name}/passed', rr.TextLog(f'{part}: {orientation}'))
            rec.reset_time()
            continue
        path = f'/plots/sensors/{name}/{kind}'
        rec.log(path, rr.SeriesLines(names=f'{name} {kind}'), static=True)
        rec.send_columns(path, indexes=_time_columns(log_, t), columns=rr.Scalars.columns(
            scalars=np.array([x[1] for x in samples], float)))


def _log_episodes(rec: rr.RecordingStream, log_: _Log) -> None:
    """A line in ``/episodes`` where each reset starts a new episode."""
    for k, start in enumerate(log_.episode_starts.tolist(), 1):
        rec.set_time(TIMELINE, duration=np.timedelta64(start, 'ns'))
        rec.set_time(EPISODE_TIMELINE, sequence=k)
        rec.set_time(EPISODE_TIME_TIMELINE, duration=np.timedelta64(0, 'ns'))
        rec.log('/episodes', rr.TextLog(f'episode {k}: the simulation was reset, simulated '
                                        'time starts again at 0'))
    rec.reset_time()


def _log_vibration(rec: rr.RecordingStream, log_: _Log) -> None:
    """The commands as steps; the last one repeated at the end of the log."""
    if not log_.vibration_t.size:
        return
    t, values = log_.vibration_t, log_.vibration
    if log_.end_t > t[-1]:
        t = np.append(t, log_.end_t)
        values = np.concatenate([values, values[-1:]])
    time = _time_columns(log_, t)
    for name, column, factor, label in (('amplitude', 0, 1e6, 'amplitude [µm, 0-peak]'),
                                        ('frequency', 1, 1.0, 'frequency [Hz]')):
        path = f'/plots/vibration/{name}'
        rec.log(path, rr.SeriesLines(names=label, interpolation_mode='StepAfter'), static=True)
        rec.send_columns(path, indexes=time,
                         columns=rr.Scalars.columns(scalars=factor * values[:, column]))


def _notes(log_: _Log, scale: float, reference: float, size: float) -> str:
    m = log_.metadata
    scene = (f"scene `{m.get('scene', '?')}`, method `{m.get('method', '?')}`, "
             f"feeder_sim {m.get('feeder_sim', '?')}") if m else 'no feeder_sim metadata'
    shapes = ('part outlines from the scene stored in the log' if log_.scene is not None
              else 'no scene in the log: parts drawn as their origins, no track')
    return '\n'.join([
        f'# {log_.path.name}', '', scene + '.', '',
        f'* `/world`: metres, y up; {shapes}.',
        '* The track is drawn at its nominal pose; its vibration is not animated.',
        '* Impulse arrows: impulse on the body owning the contact vertex (body_a), summed '
        'since the previous contacts message.',
        f'* Arrow scale: {1e3 * scale:.4g} mm per N s ({1 / scale:.4g} N s per metre); the '
        f'{ARROW_PERCENTILE:g}th percentile impulse, {reference:.4g} N s, is drawn '
        f'{1e3 * ARROW_FRACTION * size:.3g} mm long ({100 * ARROW_FRACTION:g} % of the part '
        f'size {1e3 * size:.3g} mm).',
        '* Plots: position along the track [mm], speed along the track [mm/s], vibration '
        'amplitude [µm, 0-peak] and frequency [Hz].',
    ]) + '\n'


def _bounds(log_: _Log, size: float) -> rrb.VisualBounds2D | None:
    """What to show first: every body and every recorded part origin, with a margin. The
    ranges are in the view's (y-flipped) frame."""
    points = [log_.origin]
    if log_.scene is not None:
        points += [_transform(o, b.pose) for b in log_.scene.bodies for o in b.outlines]
    points = np.concatenate([p for p in points if len(p)]) if any(map(len, points)) else None
    if points is None:
        return None
    lo, hi = points.min(0) - size, points.max(0) + size
    return rrb.VisualBounds2D(x_range=(lo[0], hi[0]), y_range=(-hi[1], -lo[1]))


def _blueprint(log_: _Log, size: float) -> rrb.Blueprint:
    """The layout: the 2D world above the position, speed, vibration (and sensor) plots."""
    bounds = _bounds(log_, size)
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Spatial2DView(name='feeder', origin='/', contents=['/world/**'],
                              visual_bounds=bounds),
            rrb.Horizontal(
                rrb.TimeSeriesView(name='position along track [mm]', origin='/plots/position'),
                rrb.TimeSeriesView(name='speed along track [mm/s]', origin='/plots/speed'),
                rrb.Tabs(
                    rrb.TimeSeriesView(name='vibration command', origin='/plots/vibration'),
                    *([rrb.TimeSeriesView(name='sensors', origin='/plots/sensors'),
                       rrb.TextLogView(name='parts passing', origin='/sensors')]
                      if log_.sensors else []),
                    rrb.TextDocumentView(name='notes', origin='/notes'),
                ),
            ),
            row_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE),
        collapse_panels=False,
    )


def _recording_id(path: Path) -> str:
    """A UUID from the log's bytes: converting the same log twice gives the same recording."""
    digest = hashlib.sha256()
    with open(path, 'rb') as stream:
        while chunk := stream.read(1 << 20):
            digest.update(chunk)
    return str(uuid.UUID(bytes=digest.digest()[:16]))


def _write_rrd(log_: _Log, rrd: Path) -> None:
    size = part_size(log_.scene)
    scale, reference = impulse_scale(log_.contacts, size)
    names = _part_names(log_)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=_recording_id(log_.path),
                             send_properties=False)
    # Only simulated time matters; the wall clock of the conversion would be noise.
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    partial = rrd.with_name(rrd.name + '.part')
    try:
        rec.save(partial)
    except RuntimeError as err:  # rerun reports file errors as RuntimeError
        raise OSError(f'{rrd}: cannot write the recording ({err})') from None
    try:
        rec.send_recording_name(log_.path.name)
        rec.send_blueprint(_blueprint(log_, size), make_active=True, make_default=True)
        rec.send_property('replay', rr.AnyValues(
            source=log_.path.name, scene=log_.metadata.get('scene', ''),
            method=log_.metadata.get('method', ''),
            impulse_arrow_m_per_Ns=scale, impulse_arrow_Ns_per_m=1.0 / scale,
            impulse_reference_Ns=reference, part_size_m=size))
        # The view shows /world with y up (rerun's 2D views have y down).
        rec.log('/world', rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
        rec.log('/notes', rr.TextDocument(_notes(log_, scale, reference, size),
                                          media_type=rr.MediaType.MARKDOWN), static=True)
        if log_.scene is not None:
            _log_fixed_bodies(rec, log_.scene)
        _log_parts(rec, log_, names)
        _log_contacts(rec, log_, scale)
        _log_series(rec, log_, names)
        _log_vibration(rec, log_)
        _log_sensors(rec, log_)
        _log_episodes(rec, log_)
        rec.flush()
        rec.disconnect()
        # Written under a temporary name so that a failed conversion leaves no .rrd behind.
        os.replace(partial, rrd)
    except BaseException:
        rec.disconnect()
        partial.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------------
# Public API


def _display_available() -> bool:
    return bool(os.environ.get('DISPLAY') or os.environ.get('WAYLAND_DISPLAY'))


def _open_viewer(rrd: Path) -> None:
    """Start the rerun viewer on ``rrd`` in its own session (it outlives this process)."""
    subprocess.Popen([sys.executable, '-m', 'rerun', str(rrd)], stdin=subprocess.DEVNULL,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                     start_new_session=True)


def replay(mcap_path: str | os.PathLike, rrd_path: str | os.PathLike | None = None, *,
           spawn: bool | None = None) -> Path:
    """Convert the MCAP log ``mcap_path`` to a rerun recording and return the ``.rrd`` path.

    ``rrd_path`` defaults to the log's path with the suffix ``.rrd``; its directory is
    created. ``spawn``: True opens the viewer on the written file, False only writes, None
    opens it when a display is available ($DISPLAY or $WAYLAND_DISPLAY). The recording has
    application id ``feeder_sim`` and a recording id derived from the log's bytes. Raises
    ``OSError`` or ``ValueError`` (naming the file) for a missing or non-MCAP file.
    """
    source = Path(mcap_path)
    rrd = Path(rrd_path) if rrd_path is not None else source.with_suffix('.rrd')
    if rrd.exists() and rrd.resolve() == source.resolve():
        raise ValueError(f'{rrd}: the recording would overwrite the log')
    log_ = _read_log(source)
    rrd.parent.mkdir(parents=True, exist_ok=True)
    _write_rrd(log_, rrd)
    if spawn or (spawn is None and _display_available()):
        try:
            _open_viewer(rrd)
        except OSError as err:
            if spawn:
                raise
            log.warning('cannot start the rerun viewer: %s', err)
    return rrd
