"""Frames: what is published and recorded at one simulated time, and the MCAP recorder set-up.

``feeder-sim run`` and the ROS node take the same :class:`Frame` from a simulator and write it
with :func:`record_frame`, so a log is the same whichever wrote it.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import json
import os
import time

import numpy as np

from feeder_sim import __version__
from feeder_sim.model.scene import BodySpec, scene_to_dict
from feeder_sim.output.impulses import part_impulses, PartImpulses
from feeder_sim.output.sensors import SensorBank, SensorReading
from feeder_sim.simulator import ContactReport, Simulator


@dataclass
class Frame:
    """What is published and recorded at one simulated time: one pass over the state. What
    only some frames need (outlines, impulse totals) is worked out on first use."""

    t_ns: int                    # simulated time, ns
    names: tuple[str, ...]       # parts, scene order
    origin: np.ndarray           # (n, 2) body-frame origins, m
    angle: np.ndarray            # (n,) rad
    s: np.ndarray                # (n,) position along the track, m
    speed: np.ndarray            # (n,) speed along the track, m/s
    contacts: ContactReport      # contacts and impulses since the previous frame
    bodies: tuple[str, ...]      # every body, world order (for transforms)
    body_origin: np.ndarray      # (N, 2) their body-frame origins, m
    body_angle: np.ndarray       # (N,) rad
    parts: np.ndarray            # (n,) the parts' indices among the bodies
    centre_of_mass: np.ndarray   # (N, 2) every body's, m
    scene_bodies: tuple[BodySpec, ...]        # the bodies as the scene has them now
    sensors: tuple[SensorReading, ...] = ()   # the scene's sensors, in scene order

    @classmethod
    def take(cls, sim: Simulator, sensors: SensorBank | None = None) -> Frame:
        """The current frame of ``sim``; takes (and so resets) its contact report, and reads
        ``sensors`` (which follow the parts from frame to frame)."""
        parts, names, body_origin, body_angle = _poses(sim)
        s, v = sim.track_coordinates()
        frame = cls(round(sim.t * 1e9), names, body_origin[parts], body_angle[parts], s, v,
                    sim.take_contacts(), tuple(sim.world.names), body_origin, body_angle,
                    parts, sim.state.position.copy(), sim.world.scene.bodies)
        if sensors is not None and sensors.specs:
            frame.sensors = sensors.update(names, frame.centre_of_mass[parts], frame.origin,
                                           frame.angle, frame.outlines)
        return frame

    @functools.cached_property
    def outlines(self) -> dict[str, tuple[np.ndarray, ...]]:
        """Each body's outlines (body frame, as the scene gives them), by name."""
        return {b.name: b.outlines for b in self.scene_bodies}

    @functools.cached_property
    def impulses(self) -> PartImpulses:
        """The contacts' impulses totalled per part."""
        return part_impulses(self.contacts, self.parts, self.centre_of_mass)


def _poses(sim: Simulator) -> tuple[np.ndarray, tuple[str, ...], np.ndarray, np.ndarray]:
    """The parts' indices and names, and every body's frame (origins m, angles rad)."""
    parts = sim.part_indices
    body_origin, body_angle = sim.world.body_frame_pose(sim.state)
    return parts, tuple(sim.world.names[i] for i in parts), body_origin, body_angle


def read_sensors(sim: Simulator, sensors: SensorBank) -> tuple[SensorReading, ...]:
    """``sensors`` read at ``sim``'s current state (without taking a frame)."""
    if not sensors.specs:
        return ()
    parts, names, body_origin, body_angle = _poses(sim)
    return sensors.update(names, sim.state.position[parts], body_origin[parts],
                          body_angle[parts], {b.name: b.outlines for b in sim.world.scene.bodies})


def sensor_bank(sim: Simulator) -> SensorBank:
    """The sensors of ``sim``'s scene, orientations read relative to its track."""
    return SensorBank(sim.scene.sensors, sim.scene.outcomes, sim.world.track_angle)


def record_frame(recorder, frame: Frame) -> None:
    """Write one frame of the interfaces' MCAP topics."""
    t_ns, c = frame.t_ns, frame.contacts
    recorder.write_clock(t_ns)
    recorder.write_part_poses(t_ns, frame.origin, frame.angle)
    recorder.write_contacts(t_ns, c.point, c.normal, c.normal_impulse, c.tangent_impulse,
                            c.body_a, c.body_b)
    recorder.write_track_state(t_ns, frame.names, frame.s, frame.speed)
    _record_geometry(recorder, frame)
    recorder.write_transforms(t_ns, frame.bodies, frame.body_origin, frame.body_angle)
    p = frame.impulses
    recorder.write_part_impulses(t_ns, frame.centre_of_mass[frame.parts], p.impulse,
                                 p.angular_impulse, p.normal_impulse, p.contacts)
    for reading in frame.sensors:
        recorder.write_sensor(t_ns, reading.name, reading.kind, reading.blocked, reading.count,
                              reading.passed)


PART_COLOR = (0.12, 0.47, 0.71, 1.0)      # RGBA
FIXED_COLOR = (0.5, 0.5, 0.5, 1.0)


def _record_geometry(recorder, frame: Frame) -> None:
    """The outlines of the bodies that are new in this frame; a delete for those gone."""
    drawn = recorder.outlines_drawn
    now = set(frame.bodies)
    new = {n: frame.outlines[n] for n in frame.bodies if n not in drawn}
    gone = {n: k for n, k in drawn.items() if n not in now}
    if not new and not gone:
        return
    parts = set(frame.names)
    colors = {n: PART_COLOR if n in parts else FIXED_COLOR for n in new}
    sizes = [np.ptp(np.vstack(frame.outlines[n]), axis=0).max() for n in frame.names]
    # as the node draws them: a fortieth of the typical part
    width = 0.025 * float(np.median(sizes)) if sizes else 1e-3
    recorder.write_outlines(frame.t_ns, new, colors, width, gone)
    for n in gone:
        del drawn[n]
    drawn.update({n: len(frame.outlines[n]) for n in new})


LOG_TIMES = ('wall', 'sim')


def recording_metadata(sim: Simulator, log_time_origin_ns: int = 0) -> dict[str, str]:
    """What a log needs besides its messages: the scene (as JSON), how it was solved, and
    the wall-clock time its log times count simulated time from."""
    return {'scene': sim.scene.name, 'method': sim.method, 'feeder_sim': __version__,
            'scene_json': json.dumps(scene_to_dict(sim.scene), separators=(',', ':')),
            'log_time_origin_ns': str(log_time_origin_ns)}


def open_recorder(sim: Simulator, path: str | os.PathLike, log_time: str = 'wall', **options):
    """An MCAP recorder for ``sim`` holding the scene metadata and the vibration in force.

    ``log_time`` 'wall': log times are the wall-clock time at which the recording started plus
    the simulated time, so that viewers show dates and times of day (not 1970); 'sim': log
    times are simulated time alone (two runs of the same commands give the same file).
    Header stamps are simulated time either way."""
    from feeder_sim.output.recording import McapRecorder
    if log_time not in LOG_TIMES:
        raise ValueError(f"log_time must be 'wall' or 'sim', got {log_time!r}")
    # whole seconds: the simulated times stay readable in the log times' digits
    origin = (time.time_ns() // 1_000_000_000) * 1_000_000_000 if log_time == 'wall' else 0
    origin -= round(sim.t * 1e9) if origin else 0
    recorder = McapRecorder(path, metadata=recording_metadata(sim, origin),
                            sensors=[(x.name, x.kind) for x in sim.scene.sensors],
                            log_time_origin_ns=origin, **options)
    for i in sim.world.driven:
        d = sim.world.drives[i]
        recorder.write_vibration_cmd(int(round(sim.t * 1e9)), d.amplitude_m, d.frequency_hz)
        break
    return recorder
