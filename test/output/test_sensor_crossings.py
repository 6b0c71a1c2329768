"""A beam counts a part once per passage, whatever the beam's geometry: laid along the track
under vibrating parts, across it, under a part that hops in place across it, and at any angle
to a part moving in a straight line (against the analytic crossing of the segment)."""

from __future__ import annotations

import math

from hypothesis import assume, given, settings
from hypothesis import strategies as st
import numpy as np
from paths import CONFIG
import yaml

from feeder_sim.model.scene import SensorSpec
from feeder_sim.output.frames import read_sensors, sensor_bank
from feeder_sim.output.sensors import SensorBank
from feeder_sim.run import run
from feeder_sim.simulator import Simulator

QUEUE_CELL = CONFIG / 'queue_cell.yaml'
HALF = np.array([0.01, 0.005])                       # the box's half sides, m
BOX = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * HALF


def _cell(xs: list[float], sensors: list[dict], vibration_angle: float | None = None) -> dict:
    """queue_cell without its source: boxes lying on the track at ``xs``."""
    data = yaml.safe_load(QUEUE_CELL.read_text())
    data.pop('sources')
    box = next(b for b in data['bodies'] if b['name'] == 'box')
    data['bodies'] = [b for b in data['bodies'] if b['name'] != 'box']
    data['bodies'] += [dict(box, name=f'box{k}', pose=[x, 0.005, 0.0]) for k, x in enumerate(xs)]
    if vibration_angle is not None:
        data['bodies'][0]['vibration']['angle'] = vibration_angle
    data['sensors'] = sensors
    return data


def _run(data: dict, duration_s: float) -> tuple[SensorBank, dict, list]:
    """Runs ``data``, reading a bank of its sensors each frame beside the run's own; returns
    the bank, the run's summary and the frames (names, centres of mass, outlines' vertices)."""
    sim = Simulator(data)
    bank, frames = sensor_bank(sim), []

    def on_frame(s: Simulator) -> None:
        read_sensors(s, bank)
        parts = s.part_indices
        origin, angle = s.world.body_frame_pose(s.state)
        names = [s.world.names[i] for i in parts]
        verts = []
        for i in parts:
            c, sn = math.cos(angle[i]), math.sin(angle[i])
            verts.append(BOX @ np.array([[c, sn], [-sn, c]]) + origin[i])
        frames.append((names, s.state.position[parts].copy(), verts))

    summary = run(sim, duration_s, publish_rate_hz=100.0, on_frame=on_frame).summary
    return bank, summary, frames


def _reference(frames: list, a: tuple, b: tuple) -> tuple[int, int]:
    """Crossings of segment ab (left to right, right to left) by the centres of mass, a part
    counting again only after its outline has been seen wholly on one side of the line."""
    a, b = np.array(a, dtype=float), np.array(b, dtype=float)
    normal = np.array([-(b - a)[1], (b - a)[0]])       # points to the left
    armed: dict[str, bool] = {}
    last: dict[str, np.ndarray] = {}
    forth = back = 0
    for names, com, verts in frames:
        for n, p, v in zip(names, com, verts, strict=True):
            if n in last and armed[n]:
                q = last[n]
                # solve q + t (p - q) = a + u (b - a)
                m = np.column_stack([p - q, a - b])
                if abs(np.linalg.det(m)) > 0.0:
                    t, u = np.linalg.solve(m, a - q)
                    before, after = normal @ (q - a), normal @ (p - a)
                    if 0.0 <= u <= 1.0 and before * after <= 0.0 and before != after:
                        forth += before > 0.0
                        back += before <= 0.0
                        armed[n] = False
            dist = (v - a) @ normal
            armed[n] = armed.get(n, False) or bool(np.all(dist >= 0) or np.all(dist <= 0))
            last[n] = p
    return forth, back


def test_a_beam_along_the_track_counts_no_part_that_vibrates_along_it():
    # 6 boxes conveyed along a beam at the height of their centres: before, each period of
    # the drive counted (600 in 2 s one way, 594 the other)
    along = [[-0.2, 0.005], [0.2, 0.005]]
    data = _cell([-0.18 + 0.04 * k for k in range(6)],
                 [{'name': 'along', 'type': 'beam', 'line': along},
                  {'name': 'along_back', 'type': 'beam', 'line': along[::-1]},
                  {'name': 'across', 'type': 'beam', 'line': [[0.0, 0.0005], [0.0, 0.02]]}])
    bank, summary, frames = _run(data, 2.0)
    assert summary['sensors'] == dict(zip(['along', 'along_back', 'across'], bank.counts))
    for s, line in ((0, along), (1, along[::-1])):
        assert bank.counts[s] <= 6 and bank.counts_back[s] <= 6
        assert (bank.counts[s], bank.counts_back[s]) == _reference(frames, *line)
    # the boxes that reached x = 0 went through the beam across the track once, forwards
    reached = sum(x0 < 0.0 < x for x0, x in zip(frames[0][1][:, 0], frames[-1][1][:, 0]))
    assert reached >= 1
    assert bank.counts[2] == reached and bank.counts_back[2] == 0
    assert (bank.counts[2], 0) == _reference(frames, (0.0, 0.0005), (0.0, 0.02))


def test_a_part_hopping_in_place_across_beams_counts_at_most_once():
    # the drive straight up hops the box in place: its centre wanders about each line
    lines = {'upright': [[0.0, 0.0005], [0.0, 0.02]], 'level': [[-0.05, 0.005], [0.05, 0.005]],
             'slanted': [[-0.01, -0.005], [0.01, 0.015]]}
    data = _cell([0.0], [{'name': k, 'type': 'beam', 'line': v} for k, v in lines.items()],
                 vibration_angle=math.pi / 2)
    bank, _, frames = _run(data, 1.0)
    for s, line in enumerate(lines.values()):
        assert bank.counts[s] <= 1 and bank.counts_back[s] <= 1
        assert (bank.counts[s], bank.counts_back[s]) == _reference(frames, *line)


@settings(max_examples=200, deadline=None, database=None)
@given(beam_angle=st.floats(0.0, 2 * math.pi), beam_length=st.floats(0.005, 0.1),
       beam_x=st.floats(-0.05, 0.05), beam_y=st.floats(-0.05, 0.05),
       heading=st.floats(0.0, 2 * math.pi), part_angle=st.floats(0.0, 2 * math.pi),
       start=st.floats(0.0, 0.1), travel=st.floats(0.0, 0.2),
       frames=st.integers(2, 60))
def test_a_part_moving_straight_crosses_a_segment_at_most_once_each_way(
        beam_angle, beam_length, beam_x, beam_y, heading, part_angle, start, travel, frames):
    a = np.array([beam_x, beam_y])
    d = beam_length * np.array([math.cos(beam_angle), math.sin(beam_angle)])
    m = np.array([math.cos(heading), math.sin(heading)])
    p0 = -start * m                                  # the path runs through the origin
    ts = np.linspace(0.0, 1.0, frames)
    path = p0 + np.outer(ts * travel, m)
    bank = SensorBank([_beam(a, a + d)], None)
    for p in path:
        bank.update(['box'], p[None], p[None], np.array([part_angle]), {'box': (BOX,)})

    # analytic: the centre's distance to the line is linear along the path, so it changes
    # side at most once; the part is armed iff its outline starts clear of the line
    def side(p):
        return d[0] * (p[..., 1] - a[1]) - d[1] * (p[..., 0] - a[0])

    c, s = math.cos(part_angle), math.sin(part_angle)
    outline0 = BOX @ np.array([[c, s], [-s, c]]) + path[0]
    f0, f1, margins = side(path[0]), side(path[-1]), side(outline0)
    scale = beam_length * 1e-9
    assume(min(abs(f0), abs(f1)) > scale and np.min(np.abs(margins)) > scale)
    armed = bool(np.all(margins > 0) or np.all(margins < 0))
    forth = back = 0
    if f0 * f1 < 0.0 and armed:
        cross = path[0] + f0 / (f0 - f1) * (path[-1] - path[0])
        u = float((cross - a) @ d / (d @ d))
        assume(min(abs(u), abs(u - 1.0)) > 1e-9)
        forth, back = int(0.0 < u < 1.0 and f0 > 0.0), int(0.0 < u < 1.0 and f0 < 0.0)
    assert (bank.counts[0], bank.counts_back[0]) == (forth, back)


def _beam(start: np.ndarray, end: np.ndarray) -> SensorSpec:
    return SensorSpec('beam', 'beam', tuple(map(float, start)), tuple(map(float, end)))
