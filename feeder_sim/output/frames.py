"""Frames: what is published and recorded at one simulated time, and the MCAP recorder set-up.

``feeder-sim run`` and the ROS node take the same :class:`Frame` from a simulator and write it
with :func:`record_frame`, so a log is the same whichever wrote it.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import os

import numpy as np

from feeder_sim import __version__
from feeder_sim.model.scene import scene_to_dict
from feeder_sim.simulator import ContactReport, Simulator


@dataclass
class Frame:
    """What is published and recorded at one simulated time: one pass over the state."""

    t_ns: int                    # simulated time, ns
    names: tuple[str, ...]       # parts, scene order
    origin: np.ndarray           # (n, 2) body-frame origins, m
    angle: np.ndarray            # (n,) rad
    s: np.ndarray                # (n,) position along the track, m
    speed: np.ndarray            # (n,) speed along the track, m/s
    contacts: ContactReport      # contacts and impulses since the previous frame

    @classmethod
    def take(cls, sim: Simulator) -> Frame:
        """The current frame of ``sim``; takes (and so resets) its contact report."""
        names, origin, angle = sim.part_poses()
        s, v = sim.track_coordinates()
        return cls(round(sim.t * 1e9), names, origin, angle, s, v, sim.take_contacts())


def record_frame(recorder, frame: Frame) -> None:
    """Write one frame of the interfaces' MCAP topics."""
    t_ns, c = frame.t_ns, frame.contacts
    recorder.write_clock(t_ns)
    recorder.write_part_poses(t_ns, frame.origin, frame.angle)
    recorder.write_contacts(t_ns, c.point, c.normal, c.normal_impulse, c.tangent_impulse,
                            c.body_a, c.body_b)
    recorder.write_track_state(t_ns, frame.names, frame.s, frame.speed)


def recording_metadata(sim: Simulator) -> dict[str, str]:
    """What a log needs besides its messages: the scene (as JSON) and how it was solved."""
    return {'scene': sim.scene.name, 'method': sim.method, 'feeder_sim': __version__,
            'scene_json': json.dumps(scene_to_dict(sim.scene), separators=(',', ':'))}


def open_recorder(sim: Simulator, path: str | os.PathLike, **options):
    """An MCAP recorder for ``sim`` holding the scene metadata and the vibration in force."""
    from feeder_sim.output.recording import McapRecorder
    recorder = McapRecorder(path, metadata=recording_metadata(sim), **options)
    for i in sim.world.driven:
        d = sim.world.drives[i]
        recorder.write_vibration_cmd(int(round(sim.t * 1e9)), d.amplitude_m, d.frequency_hz)
        break
    return recorder
