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

Every chunk of the log is checked against its CRC (through the summary's chunk index when
the log has an intact summary, else record by record from the start). A chunk or metadata
record that cannot be read is damage: :class:`DamagedLogError` names each, with the simulated
time range of the frames it held, unless ``allow_damaged`` (``--allow-damaged``) replays the
rest with each as a warning. A log of a killed writer (no footer) is not damaged: it converts
up to its last complete chunk, with one warning. A log with neither feeder_sim metadata nor
any topic the replay draws (another program's) is refused in one line naming its topics;
topics other than the feeder_sim ones are otherwise ignored. Metadata values are checked
(a bad one is a ValueError naming it); ``scene_json`` is held to the scene files' limits
(:data:`~feeder_sim.model.scene.MAX_FILE_BYTES`, nesting) and to a budget for the scene
parser's checks before it is parsed, and a scene beyond them is ignored with a warning (parts
drawn as origins). An output that exists and is not a regular file is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterator
from dataclasses import dataclass, field
import functools
import hashlib
import io
import json
import logging
import math
import os
from pathlib import Path
import re
import stat
import struct
import subprocess
import sys
from typing import NamedTuple
import uuid
import zlib

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Message, Metadata, MetadataIndex, Schema
import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.distance import pdist

from feeder_sim.model.scene import (
    MAX_FILE_BYTES,
    MAX_NESTING,
    MAX_POLYGON_VERTICES,
    parse_scene,
    Scene,
    SceneError,
)
from feeder_sim.output import msgdefs
from feeder_sim.output.recording import (
    CONTACT_FIELDS,
    CONTACT_POINT_DTYPE,
    SENSOR_PREFIX,
    TOPIC_CONTACTS,
    TOPIC_PART_POSES,
    TOPIC_TRACK_STATE,
    TOPIC_VIBRATION_CMD,
    TOPICS,
)

__all__ = ['APPLICATION_ID', 'DamagedLogError', 'TIMELINE', 'impulse_scale', 'part_size',
           'replay']

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


class DamagedLogError(ValueError):
    """The log holds damaged records: ``lines`` says, one line each, which frames (time
    range) or metadata were lost and where. ``replay(..., allow_damaged=True)`` replays the
    rest instead."""

    def __init__(self, lines: list[str]):
        self.lines = list(lines)
        super().__init__('\n'.join(self.lines))


@dataclass
class _Damage:
    """A record the log holds but that cannot be read: its byte offset, the log times (ns)
    of the messages it held where known, and why."""

    offset: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    what: str = 'chunk'


class _Bad(Exception):
    """A record that cannot be read; the message says why, for the damage report."""


_RECORD_HEADER = struct.Struct('<BQ')
_MESSAGE = struct.Struct('<HIQQ')     # channel id, sequence, log time, publish time


class _Msg(NamedTuple):
    channel_id: int
    log_time: int
    data: bytes
_FOOTER = struct.Struct('<BQQQI')    # opcode, length, summary start, summary offset start, crc
# Opcodes 0x01-0x0F are the specification's, 0x80 and up are for other programs' own records;
# anything else where a record should start means the walk has left the record boundaries.
_KNOWN_OPCODE = frozenset(range(0x01, 0x10)) | frozenset(range(0x80, 0x100))
# A chunk's declared uncompressed size is allocated before it is checked; a damaged size field
# must not ask for gigabytes. mcap writers chunk by a few MiB at most (feeder_sim: 256 KiB).
_MAX_CHUNK_BYTES = 1 << 28
# Looking for the next chunk after a damaged record header: the file is read in blocks, and
# only byte positions that could start a chunk (opcode, a length that fits) are tried.
_CHUNK_OPCODE = bytes([Opcode.CHUNK])
_MIN_CHUNK_BODY = 8 + 8 + 8 + 4 + 4 + 8   # times, sizes, CRC, compression length, records length
_RESYNC_BLOCK = 1 << 20
_RESYNC_TRIES = 64


def _decompressed(chunk: Chunk) -> bytes:
    """A chunk's records, decompressed with its declared size as the bound."""
    size = chunk.uncompressed_size
    if size > _MAX_CHUNK_BYTES:
        raise _Bad(f'declared size {size} bytes is beyond {_MAX_CHUNK_BYTES}')
    if chunk.compression == '':
        data = chunk.data
    elif chunk.compression == 'zstd':
        import zstandard
        # a stream reads at most what is asked for, whatever the frame header claims
        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as reader:
            data = reader.read(size + 1)
    elif chunk.compression == 'lz4':
        import lz4.frame
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    else:
        raise _Bad(f'unknown compression {chunk.compression[:20]!r}')
    if len(data) != size:
        raise _Bad(f'{len(data)} bytes where {size} were declared')
    return data


def _chunk_records(body: bytes) -> tuple[Chunk, list]:
    """The chunk in a Chunk record's body and its Schema, Channel and Message records;
    raises _Bad when it fails its CRC or does not parse."""
    try:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
    except Exception as err:  # noqa: BLE001 - any parse failure is damage
        raise _Bad(f'unreadable chunk header ({type(err).__name__})') from None
    try:
        data = _decompressed(chunk)
    except _Bad:
        raise
    except Exception as err:  # noqa: BLE001 - the codecs raise their own types
        raise _Bad(f'cannot be decompressed ({err})') from None
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise _Bad('CRC mismatch')
    records, pos = [], 0
    try:
        while pos < len(data):
            opcode, length = _RECORD_HEADER.unpack_from(data, pos)
            pos += _RECORD_HEADER.size
            if length > len(data) - pos:
                raise _Bad('a record runs past the chunk')
            if opcode == Opcode.MESSAGE:
                # read in place: a record object per message doubles the reading time
                channel, _, log_time, _ = _MESSAGE.unpack_from(data, pos)
                records.append(_Msg(channel, log_time,
                                    data[pos + _MESSAGE.size:pos + length]))
            elif opcode in (Opcode.CHANNEL, Opcode.SCHEMA):
                stream = ReadDataStream(io.BytesIO(data[pos:pos + length]))
                records.append((Channel if opcode == Opcode.CHANNEL else Schema).read(stream))
            pos += length
    except _Bad:
        raise
    except Exception as err:  # noqa: BLE001 - without a CRC, parsing is the only check
        raise _Bad(f'unreadable records ({type(err).__name__})') from None
    return chunk, records


class _LogReader:
    """Reads a log record by record, noting every record that cannot be read.

    A finished log whose summary passes its CRC is read chunk by chunk through the summary's
    chunk index (a damaged record then costs only itself, and the index says which log times
    it held); otherwise the records are walked from the start, which needs neither summary
    nor footer (a killed writer leaves neither). Each chunk is checked against its CRC before
    its messages are used. A walk stopped by a record that reaches past the end of a log
    without a footer is the cut of a killed writer (``truncated``), not damage.
    """

    def __init__(self, path: Path):
        self.path = path
        self.damage: list[_Damage] = []
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.truncated = False
        self.summary_damaged = False
        self._good: list[tuple[int, int, int]] = []   # (offset, start, end) of good chunks
        self._lost_channels: dict[int, list[int]] = {}   # channel id -> [offset, t0, t1]
        with open(path, 'rb') as stream:
            self.size = os.fstat(stream.fileno()).st_size
            self.finished = self._ends_in_magic(stream)
            self._summary = self._read_summary(stream) if self.finished else None

    # -- summary -----------------------------------------------------------------------------

    def _ends_in_magic(self, stream) -> bool:
        if self.size < 2 * len(_MCAP_MAGIC) + _FOOTER.size:
            return False
        stream.seek(self.size - len(_MCAP_MAGIC))
        return stream.read() == _MCAP_MAGIC

    def _read_summary(self, stream) -> dict | None:
        """Chunk and metadata indexes, channels and schemas of the summary, when it is there
        and passes its CRC; None otherwise."""
        footer_at = self.size - len(_MCAP_MAGIC) - _FOOTER.size
        stream.seek(footer_at)
        opcode, length, start, offsets, crc = _FOOTER.unpack(stream.read(_FOOTER.size))
        if opcode != Opcode.FOOTER or length != _FOOTER.size - _RECORD_HEADER.size:
            self.summary_damaged = True
            return None
        if start == 0:
            return None
        if not len(_MCAP_MAGIC) <= start <= footer_at:
            self.summary_damaged = True
            return None
        stream.seek(start)
        data = stream.read(footer_at - start)
        if crc and zlib.crc32(_FOOTER.pack(opcode, length, start, offsets, 0)[:-4],
                              zlib.crc32(data)) != crc:
            self.summary_damaged = True
            return None
        summary: dict = {'chunks': [], 'metadata': [], 'channels': {}, 'schemas': {}}
        pos = 0
        try:
            while pos < len(data):
                opcode, length = _RECORD_HEADER.unpack_from(data, pos)
                pos += _RECORD_HEADER.size
                stream_ = ReadDataStream(io.BytesIO(data[pos:pos + length]))
                if opcode == Opcode.CHUNK_INDEX:
                    summary['chunks'].append(ChunkIndex.read(stream_))
                elif opcode == Opcode.METADATA_INDEX:
                    summary['metadata'].append(MetadataIndex.read(stream_))
                elif opcode == Opcode.CHANNEL:
                    channel = Channel.read(stream_)
                    summary['channels'][channel.id] = channel
                elif opcode == Opcode.SCHEMA:
                    schema = Schema.read(stream_)
                    summary['schemas'][schema.id] = schema
                pos += length
        except Exception:  # noqa: BLE001 - a summary that passed its CRC but does not parse
            self.summary_damaged = True
            return None
        if not all(len(_MCAP_MAGIC) <= c.chunk_start_offset
                   and c.chunk_start_offset + c.chunk_length <= start
                   for c in summary['chunks']):
            self.summary_damaged = True
            return None
        summary['chunks'].sort(key=lambda c: c.chunk_start_offset)
        self.channels.update(summary['channels'])
        self.schemas.update(summary['schemas'])
        return summary

    @property
    def indexed(self) -> bool:
        return self._summary is not None and bool(self._summary['chunks'])

    # -- walking -----------------------------------------------------------------------------

    def _walk(self, stream, wanted: Container[int], note: bool = True
              ) -> Iterator[tuple[int, int, bytes]]:
        """(opcode, offset, body) of the top-level records of the opcodes wanted, from the
        start to the data end; where the walk cannot go on, the rest is damage (a finished
        log) or the cut of a killed writer (``truncated``)."""
        pos = len(_MCAP_MAGIC)
        stream.seek(pos)
        while True:
            head = stream.read(_RECORD_HEADER.size)
            if len(head) < _RECORD_HEADER.size:
                if note:
                    self._stopped(pos, 'the log ends inside a record header', cut=True)
                return
            opcode, length = _RECORD_HEADER.unpack(head)
            if opcode in (Opcode.FOOTER, Opcode.DATA_END):
                return
            body_at = pos + _RECORD_HEADER.size
            known = opcode in _KNOWN_OPCODE
            if not known or length > self.size - body_at:
                reason = (f'a record of {length} bytes runs past the end of the file' if known
                          else f'no record starts there (opcode 0x{opcode:02x})')
                after = self._next_chunk(stream, pos)
                if after is None:
                    if note:
                        # a killed writer's last record: a valid opcode, cut short
                        self._stopped(pos, reason, cut=known)
                    return
                if note:
                    self.damage.append(_Damage(pos, reason, what='record'))
                pos = after
                stream.seek(pos)
                continue
            if opcode in wanted:
                yield opcode, pos, stream.read(length)
            else:
                stream.seek(length, io.SEEK_CUR)
            pos = body_at + length

    def _next_chunk(self, stream, start: int) -> int | None:
        """Offset of the first chunk record after ``start`` that passes its checks, or None:
        where a damaged record header stops the walk, the chunks after it still count (and
        a killed writer's cut leaves none)."""
        tries = 0
        block_at = start + 1
        while block_at < self.size and tries < _RESYNC_TRIES:
            stream.seek(block_at)
            block = stream.read(_RESYNC_BLOCK + _RECORD_HEADER.size)
            i = block.find(_CHUNK_OPCODE)
            while 0 <= i < min(_RESYNC_BLOCK, len(block) - _RECORD_HEADER.size + 1):
                at = block_at + i
                _, length = _RECORD_HEADER.unpack_from(block, i)
                if _MIN_CHUNK_BODY <= length <= min(_MAX_CHUNK_BYTES,
                                                    self.size - at - _RECORD_HEADER.size):
                    tries += 1
                    stream.seek(at + _RECORD_HEADER.size)
                    try:
                        _chunk_records(stream.read(length))
                        return at
                    except _Bad:
                        if tries >= _RESYNC_TRIES:
                            return None
                i = block.find(_CHUNK_OPCODE, i + 1)
            block_at += _RESYNC_BLOCK
        return None

    def _stopped(self, pos: int, reason: str, cut: bool = False) -> None:
        if cut and not self.finished:
            self.truncated = pos < self.size
        else:
            self.damage.append(_Damage(pos, reason, what='record'))

    # -- metadata ----------------------------------------------------------------------------

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (the first of each name)."""
        found: dict[str, dict[str, str]] = {}
        with open(self.path, 'rb') as stream:
            if self._summary is not None and self._summary['metadata']:
                places = []
                for index in self._summary['metadata']:
                    stream.seek(index.offset)
                    places.append((index.offset, stream.read(index.length)))
                records = ((o, b[_RECORD_HEADER.size:]) for o, b in places
                           if b[:1] == bytes([Opcode.METADATA]))
                if len(places) != sum(b[:1] == bytes([Opcode.METADATA]) for _, b in places):
                    self.damage.append(_Damage(places[0][0], 'a metadata index points at '
                                               'another record', what='metadata'))
            else:
                # where a walk stops is told once, by the walk over the messages
                records = [(o, b) for _, o, b in self._walk(stream, (Opcode.METADATA,), False)]
            for offset, body in records:
                try:
                    record = Metadata.read(ReadDataStream(io.BytesIO(body)))
                except Exception as err:  # noqa: BLE001 - no CRC covers metadata
                    self.damage.append(_Damage(offset, f'unreadable ({type(err).__name__})',
                                               what='metadata'))
                    continue
                found.setdefault(record.name, record.metadata)
        return found

    # -- messages ----------------------------------------------------------------------------

    def messages(self) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time ns, payload) of every message that can be read, in file order."""
        with open(self.path, 'rb') as stream:
            if self.indexed:
                for index in self._summary['chunks']:
                    stream.seek(index.chunk_start_offset)
                    record = stream.read(index.chunk_length)
                    opcode = record[0] if record else None
                    if opcode != Opcode.CHUNK:
                        self._chunk_lost(index.chunk_start_offset, 'no chunk where the index '
                                         'puts one', index.message_start_time,
                                         index.message_end_time)
                        continue
                    yield from self._chunk(index.chunk_start_offset,
                                           record[_RECORD_HEADER.size:],
                                           (index.message_start_time, index.message_end_time))
                return
            wanted = (Opcode.CHUNK, Opcode.CHANNEL, Opcode.SCHEMA, Opcode.MESSAGE)
            for opcode, offset, body in self._walk(stream, wanted):
                if opcode == Opcode.CHUNK:
                    yield from self._chunk(offset, body, None)
                    continue
                try:
                    stream_ = ReadDataStream(io.BytesIO(body))
                    if opcode == Opcode.MESSAGE:
                        message = Message.read(stream_, len(body))
                        records = [_Msg(message.channel_id, message.log_time, message.data)]
                    elif opcode == Opcode.CHANNEL:
                        records = [Channel.read(stream_)]
                    else:
                        records = [Schema.read(stream_)]
                except Exception as err:  # noqa: BLE001 - damage, reported with the rest
                    self.damage.append(_Damage(offset, f'unreadable ({type(err).__name__})',
                                               what='record'))
                    continue
                yield from self._records(offset, records)

    def _chunk(self, offset: int, body: bytes, times: tuple[int, int] | None
               ) -> Iterator[tuple[str, int, bytes]]:
        try:
            chunk, records = _chunk_records(body)
        except _Bad as err:
            if times is None:
                times = _chunk_times(body)
            self._chunk_lost(offset, str(err), *times)
            return
        # the index's times where there is one: a chunk's CRC does not cover its header
        self._good.append((offset, *(times or (chunk.message_start_time,
                                               chunk.message_end_time))))
        yield from self._records(offset, records)

    def _chunk_lost(self, offset: int, reason: str, start: int | None, end: int | None
                    ) -> None:
        self.damage.append(_Damage(offset, reason, start, end))

    def _records(self, offset: int, records: list) -> Iterator[tuple[str, int, bytes]]:
        for record in records:
            if isinstance(record, _Msg):
                channel = self.channels.get(record.channel_id)
                if channel is not None:
                    yield channel.topic, record.log_time, record.data
                else:
                    lost = self._lost_channels.setdefault(
                        record.channel_id, [offset, record.log_time, record.log_time])
                    lost[1] = min(lost[1], record.log_time)
                    lost[2] = max(lost[2], record.log_time)
            elif isinstance(record, Channel):
                self.channels.setdefault(record.id, record)
            else:
                self.schemas.setdefault(record.id, record)

    # -- after reading -----------------------------------------------------------------------

    def topics(self) -> list[tuple[str, str]]:
        """(topic, schema name) of each channel, in channel id order."""
        out = []
        for key in sorted(self.channels):
            channel = self.channels[key]
            schema = self.schemas.get(channel.schema_id)
            out.append((channel.topic, schema.name if schema is not None else '?'))
        return out

    def report(self, origin_ns: int) -> list[str]:
        """One line per damaged record: which frames (simulated time range) or what else was
        lost, and where."""
        lines = []
        for channel, (offset, t0, t1) in sorted(self._lost_channels.items()):
            self.damage.append(_Damage(offset, f'messages of channel {channel}, whose '
                                       'definition was lost', t0, t1))
        for d in sorted(self.damage, key=lambda d: d.offset):
            where = f'{d.what} at byte {d.offset}: {d.reason}'
            if d.what == 'metadata':
                lines.append(f'{self.path}: metadata lost ({where})')
                continue
            start, end = d.start_ns, d.end_ns
            if start is not None and end is not None and origin_ns <= start <= end:
                span = (f'frames from t={_seconds(start - origin_ns)} to '
                        f't={_seconds(end - origin_ns)} s')
            else:
                # times unknown (the chunk's header is damaged too): the good neighbours'
                before = [e for o, _, e in self._good if o < d.offset]
                after = [s for o, s, _ in self._good if o > d.offset]
                bounds = ([f'after t={_seconds(before[-1] - origin_ns)} s'] if before else []) + (
                    [f'before t={_seconds(after[0] - origin_ns)} s'] if after else [])
                span = 'frames ' + (' and '.join(bounds) or 'at unknown times')
            lines.append(f'{self.path}: {span} lost ({where})')
        return lines


def _chunk_times(body: bytes) -> tuple[int | None, int | None]:
    """The (start, end) log times a chunk record's header gives, None where unreadable."""
    if len(body) < 16:
        return None, None
    start, end = struct.unpack_from('<QQ', body)
    return (start, end) if start <= end else (None, None)


def _seconds(t_ns: int) -> str:
    return f'{t_ns / 1e9:.3f}'


# The scene parser checks each distinct outline in O(n^2) time and each body against the
# others; within MAX_FILE_BYTES a log's scene_json could ask for far more of that than a replay
# should spend before it draws anything. A replay takes a scene whose checks are no more than
# those of two outlines of MAX_POLYGON_VERTICES vertices and of a thousand bodies; beyond, it
# draws part origins.
_SCENE_VERTEX_PAIRS = 2 * MAX_POLYGON_VERTICES ** 2
_SCENE_BODIES = 1000


def _scene_cost(data) -> tuple[int, int]:
    """(bodies, vertex pairs of the distinct outlines) the scene parser would check."""
    bodies = data.get('bodies') if isinstance(data, dict) else None
    if not isinstance(bodies, list):
        return 0, 0
    seen: set[tuple] = set()
    pairs = 0
    for body in bodies:
        if not isinstance(body, dict):
            continue
        pieces = body.get('polygons')
        for shape in [body.get('polygon'), *(pieces if isinstance(pieces, list) else ())]:
            if isinstance(shape, list):
                try:
                    key = tuple(tuple(p) if isinstance(p, list) else p for p in shape)
                    fresh = key not in seen
                    seen.add(key)
                except TypeError:  # not [x, y] pairs: the parser refuses it, at no cost
                    fresh = True
                pairs += len(shape) ** 2 if fresh else 0
    return len(bodies), pairs


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def _json_depth(text: str) -> int:
    """How deep the brackets of a JSON text nest (strings skipped), in one vectorised pass:
    JSON has no aliases, so this and the size bound the scene files' nesting and value
    limits before anything is parsed."""
    b = np.frombuffer(_JSON_STRING.sub('', text).encode('utf-8', 'replace'), np.uint8)
    step = (np.isin(b, (ord('['), ord('{'))).astype(np.int32)
            - np.isin(b, (ord(']'), ord('}'))))
    return int(np.cumsum(step).max()) if step.size else 0


def _parse_scene_json(text: str, source: str) -> Scene:
    """The scene a log stores, within the scene files' limits (size, nesting) and the
    replay's budget for checking it; SceneError otherwise."""
    if len(text) > MAX_FILE_BYTES or len(text.encode('utf-8', 'replace')) > MAX_FILE_BYTES:
        raise SceneError(f'{len(text.encode("utf-8", "replace")) / 2 ** 20:.1f} MiB; scenes are '
                         f'limited to {MAX_FILE_BYTES / 2 ** 20:.0f} MiB as scene files are',
                         source=source)
    if _json_depth(text) > MAX_NESTING:
        raise SceneError(f'nested deeper than {MAX_NESTING} levels; a scene needs about 6',
                         source=source)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise SceneError(f'not JSON ({err.msg} at character {err.pos})', source=source) from None
    bodies, pairs = _scene_cost(data)
    if bodies > _SCENE_BODIES or pairs > _SCENE_VERTEX_PAIRS:
        raise SceneError(f'{bodies} bodies with {pairs} vertex pairs in distinct outlines; a '
                         f'replay checks at most {_SCENE_BODIES} bodies and {_SCENE_VERTEX_PAIRS} '
                         'pairs (about two seconds): drawing part origins instead', source=source)
    return parse_scene(data, source=source)


def _scene_from(metadata: dict[str, str], path: Path) -> Scene | None:
    text = metadata.get('scene_json')
    if not text:
        return None
    try:
        return _parse_scene_json(text, f'{path}:scene_json')
    except ValueError as err:  # SceneError is a ValueError
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


def _messages(reader: _LogReader) -> Iterator[tuple[str, int, object]]:
    """(topic, time ns, decoded message) of the topics the replay uses (the sensors': see
    :func:`_sensor_value`); undecodable messages are skipped with one warning per topic
    (foreign logs may use other layouts)."""
    decode = _Decoder()
    failed: set[str] = set()
    for topic, t_ns, data in reader.messages():
        sensor = topic.startswith(SENSOR_PREFIX)
        if not sensor and topic not in _Decoder.TOPICS:
            continue
        try:
            message = _sensor_value(topic, data) if sensor else decode(topic, data)
        except Exception as err:  # noqa: BLE001 - skip what this replay cannot read
            if topic not in failed:
                failed.add(topic)
                log.warning('%s: skipping %s messages that cannot be decoded (%s)',
                            reader.path, topic, err)
            continue
        yield topic, t_ns, message


# Metadata values longer than this are not names or numbers feeder_sim wrote.
_MAX_NAME_CHARS = 200
_MAX_TIME_NS = 2 ** 63 - 1


def _metadata_int(path: Path, field: str, value: str, lo: int, what: str) -> int:
    text = value.strip()
    digits = text.removeprefix('+').removeprefix('-')
    if not (digits.isascii() and digits.isdigit() and len(text) <= 20
            and lo <= int(text) <= _MAX_TIME_NS):
        raise ValueError(f"{path}: metadata '{field}': expected an integer ({what}) from {lo} "
                         f'to {_MAX_TIME_NS}, got {value[:40]!r}; feeder_sim writes it so: the '
                         'log is damaged or another program wrote it')
    return int(text)


def _checked_metadata(path: Path, records: dict[str, dict[str, str]]
                      ) -> tuple[dict[str, str], int, np.ndarray]:
    """The ``feeder_sim`` metadata record, the log time (ns) simulated time counts from, and
    the simulated times (ns) at which episodes 1, 2, ... start; every value the replay uses
    is checked, a bad one is a ValueError naming it."""
    metadata = dict(records.get('feeder_sim', {}))
    for key in ('scene', 'method', 'feeder_sim'):
        value = metadata.get(key, '')
        if len(value) > _MAX_NAME_CHARS or not value.isprintable():
            raise ValueError(f"{path}: metadata '{key}': expected a name of at most "
                             f'{_MAX_NAME_CHARS} printable characters, got {value[:40]!r}')
    # log times count simulated time from this wall-clock instant (0: from the epoch)
    origin = _metadata_int(path, 'log_time_origin_ns', metadata.get('log_time_origin_ns', '0'),
                           0, 'ns since the Unix epoch')
    starts = [_metadata_int(path, f'{name}.log_time_ns', m.get('log_time_ns', ''), origin,
                            'the log time in ns at which the episode starts')
              for name, m in records.items() if name.startswith('episode_')]
    return metadata, origin, np.sort(np.array(starts, np.int64)) - origin


def _feeder_sim_topic(topic: str) -> bool:
    return topic in _Decoder.TOPICS or topic.startswith(SENSOR_PREFIX)


def _not_feeder_sim(path: Path, topics: list[tuple[str, str]]) -> str:
    """The line saying that a log holds nothing the replay can draw, and what it holds."""
    shown = ', '.join(f'{topic} ({schema})' for topic, schema in topics[:4])
    more = f' and {len(topics) - 4} more' if len(topics) > 4 else ''
    held = f'its topics are {shown}{more}' if topics else 'it has no topics'
    return (f'{path}: not a feeder_sim log: no feeder_sim metadata and none of the topics '
            f'the replay draws ({", ".join(_Decoder.TOPICS)}, {SENSOR_PREFIX}*); {held}, so '
            f'a replay would show nothing: open it with `rerun {path}` instead')


def _read_log(path: Path, allow_damaged: bool = False) -> _Log:
    """The log's frames as arrays. Raises DamagedLogError for records that cannot be read
    (unless ``allow_damaged``: then each is one warning), ValueError for a log that is not
    feeder_sim's or metadata that is not what feeder_sim writes."""
    _check_mcap(path)
    reader = _LogReader(path)
    records = reader.metadata()
    metadata, origin, episode_starts = _checked_metadata(path, records)
    # before the frames are read: a hostile scene is refused in a fraction of a second
    scene = _scene_from(metadata, path)
    poses, contacts, track, vibration = [], [], [], []
    sensors: dict[str, list] = {}
    end_t = 0
    for topic, t_ns, message in _messages(reader):
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
    damage = reader.report(origin)
    if damage and not allow_damaged:
        raise DamagedLogError(damage)
    for line in damage:
        log.warning('%s', line)
    if reader.summary_damaged:
        log.warning('%s: the summary at the end of the log is damaged; read the records '
                    'one by one instead', path)
    topics = reader.topics()
    # a log cut before its first channel is a killed writer's, not another program's
    if (not damage and (topics or reader.finished) and 'feeder_sim' not in records
            and not any(_feeder_sim_topic(topic) for topic, _ in topics)):
        raise ValueError(_not_feeder_sim(path, topics))
    if reader.truncated or not reader.finished:
        log.warning('%s: the log ends without its footer (its writer stopped before finishing '
                    'it); replaying the %d frames up to its last whole record', path, len(poses))
    # Stable sorts by time: files are in time order unless chunks were written out of order.
    poses.sort(key=lambda m: m[0])
    contacts.sort(key=lambda m: m[0])
    vibration.sort(key=lambda m: m[0])
    for samples in sensors.values():
        samples.sort(key=lambda m: m[0])
    return _Log(
        path=path, metadata=metadata, scene=scene,
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
    sizes = [_diameter(np.concatenate(body.outlines)) for body in _parts(scene)]
    return float(np.median(sizes)) if sizes else DEFAULT_PART_SIZE_M


# Up to this many vertices the diameter is the largest of all pairwise distances; beyond, the
# largest extent over this many directions (a relative error below 1e-6), so that a body of
# many large pieces costs time linear in its vertices and no quadratic memory.
_DIAMETER_PAIRS_UP_TO = 2000


def _diameter(v: np.ndarray) -> float:
    if len(v) <= _DIAMETER_PAIRS_UP_TO:
        return float(pdist(v).max()) if len(v) > 1 else 0.0
    angle = np.linspace(0.0, math.pi, _DIAMETER_PAIRS_UP_TO, endpoint=False)
    extent = 0.0
    for block in np.array_split(angle, 8):
        along = v @ np.stack([np.cos(block), np.sin(block)])
        extent = max(extent, float((along.max(0) - along.min(0)).max()))
    return extent


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
    partial = _partial(rrd)
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


def _check_output(rrd: Path) -> None:
    """Refuse an output that exists and is not a regular file (a FIFO would block the
    conversion or take the recording; a device or socket is not a place for it), and the
    temporary file beside it likewise."""
    for path in (rrd, _partial(rrd)):
        try:
            mode = path.stat().st_mode
        except FileNotFoundError:
            continue
        except OSError as err:
            raise ValueError(f'{path}: cannot check the output ({err.strerror})') from None
        if not stat.S_ISREG(mode):
            kind = ('a directory' if stat.S_ISDIR(mode) else 'a FIFO' if stat.S_ISFIFO(mode)
                    else 'a socket' if stat.S_ISSOCK(mode) else 'a device')
            raise ValueError(f'{path}: is {kind}, not a regular file; name a new file (or a '
                             'regular file to replace) for the recording')


def _partial(rrd: Path) -> Path:
    return rrd.with_name(rrd.name + '.part')


def replay(mcap_path: str | os.PathLike, rrd_path: str | os.PathLike | None = None, *,
           spawn: bool | None = None, allow_damaged: bool = False) -> Path:
    """Convert the MCAP log ``mcap_path`` to a rerun recording and return the ``.rrd`` path.

    ``rrd_path`` defaults to the log's path with the suffix ``.rrd``; its directory is
    created; an existing one that is not a regular file (a FIFO, a directory, a device) is
    refused. ``spawn``: True opens the viewer on the written file, False only writes, None
    opens it when a display is available ($DISPLAY or $WAYLAND_DISPLAY). The recording has
    application id ``feeder_sim`` and a recording id derived from the log's bytes.

    Raises ``OSError`` or ``ValueError`` (naming the file) for a missing or non-MCAP file, a
    log that holds nothing of feeder_sim's, or metadata feeder_sim does not write; and
    :class:`DamagedLogError` (a ValueError; one line per damaged record, with the simulated
    time range it held) when chunks fail their CRC or records cannot be read, unless
    ``allow_damaged``: then the rest is replayed and each line is a warning. A log cut short
    by a killed writer is not damaged: it is replayed up to its last whole record.
    """
    source = Path(mcap_path)
    rrd = Path(rrd_path) if rrd_path is not None else source.with_suffix('.rrd')
    if rrd.exists() and rrd.resolve() == source.resolve():
        raise ValueError(f'{rrd}: the recording would overwrite the log')
    _check_output(rrd)
    log_ = _read_log(source, allow_damaged)
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
