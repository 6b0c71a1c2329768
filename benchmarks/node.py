"""What the ROS node costs on top of the bare simulator, and what recording costs per frame.

Issue targets: with ``real_time_factor`` 0 and ``publish_rate`` 100 Hz on the default scene, the
node's real-time factor is at least 80 % of the bare simulator's (publishing and recording cost
at most 25 %); recording 50 parts at 100 Hz takes at most 1 ms of wall time per frame.

Runs, in one process and interleaved ``--repeats`` times so that machine noise hits all of them:

- ``bare``: ``Simulator.advance`` frame by frame (the contact report taken each frame);
- ``node``: the ``feeder_sim`` node in an executor, publishing every topic (markers included)
  and recording MCAP, with nobody subscribed;
- ``node+probe``: the same with a subscriber to poses, contacts, track state and markers in
  the same executor (its callbacks are charged to the node: a pessimistic figure).

Then the per-frame cost of ``record_frame`` with 50 parts resting on a track, and of the node's
whole frame (publish + record) for the same scene. Prints a table, writes
``out/bench/node.json`` (``--out`` elsewhere)::

    .venv/bin/python benchmarks/node.py [--duration 4] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import sys
import tempfile
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(11 + os.getpid() % 90))

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
import yaml  # noqa: E402

from feeder_sim.model.builders import build, conveyor  # noqa: E402
from feeder_sim.model.scene import scene_to_dict  # noqa: E402
from feeder_sim.output.frames import Frame, record_frame  # noqa: E402
from feeder_sim.output.recording import McapRecorder  # noqa: E402
from feeder_sim.ros.node import SimNode  # noqa: E402
from feeder_sim.simulator import Simulator  # noqa: E402

SCENE = 'track_one_box'
RATE_HZ = 100.0


def bare(duration_s: float) -> float:
    """Wall seconds per simulated second of the bare simulator, frame by frame."""
    sim = Simulator(SCENE)
    frames = round(duration_s * RATE_HZ)
    t0 = time.perf_counter()
    for k in range(1, frames + 1):
        sim.advance_to(k / RATE_HZ)
        sim.take_contacts()
    return (time.perf_counter() - t0) / duration_s


def node(duration_s: float, scene=SCENE, probe: bool = False) -> dict:
    """Wall seconds per simulated second of the node at real_time_factor 0."""
    context = Context()
    rclpy.init(context=context)
    tmp = tempfile.mkdtemp()
    try:
        params = [Parameter('scene', value=scene), Parameter('real_time_factor', value=0.0),
                  Parameter('publish_rate', value=RATE_HZ), Parameter('start_paused', value=True),
                  Parameter('record_path', value=os.path.join(tmp, 'bench.mcap'))]
        sim_node = SimNode(context=context, parameter_overrides=params,
                           use_global_arguments=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(sim_node)
        if probe:
            from geometry_msgs.msg import PoseArray
            from sensor_msgs.msg import JointState, PointCloud2
            from visualization_msgs.msg import MarkerArray
            listener = Node('probe', context=context)
            for msg_type, topic in ((PoseArray, '/feeder_sim/part_poses'),
                                    (PointCloud2, '/feeder_sim/contacts'),
                                    (JointState, '/feeder_sim/track_state'),
                                    (MarkerArray, '/feeder_sim/markers')):
                listener.create_subscription(msg_type, topic, lambda m: None, 10)
            executor.add_node(listener)
            end = time.monotonic() + 10
            while sim_node.pub_poses.get_subscription_count() == 0 and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
        sim_node.paused = False
        sim_node._anchor()
        t_start = sim_node.sim.t
        t0 = time.perf_counter()
        while sim_node.sim.t - t_start < duration_s:
            executor.spin_once(timeout_sec=0.01)
        wall = time.perf_counter() - t0
        simulated = sim_node.sim.t - t_start
        frames = sim_node.frames
        sim_node.close()
        executor.shutdown()
        return {'wall_per_sim_s': wall / simulated, 'frames': frames}
    finally:
        rclpy.shutdown(context=context)


def pile_scene(n_parts: int) -> dict:
    return build(conveyor(psi=0.35, mu=0.5, theta=0.0, gamma=1.2, n_parts=n_parts,
                          method='time_stepping', time_step=1e-3, track_length=2.0,
                          spacing=0.03, name=f'parts_{n_parts}'))


def recording_per_frame(n_parts: int, frames: int = 300) -> float:
    """Median wall seconds of record_frame for n_parts parts (contacts included)."""
    sim = Simulator(pile_scene(n_parts))
    sim.advance_to(0.05)
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        with McapRecorder(os.path.join(tmp, 'rec.mcap')) as recorder:
            for k in range(frames):
                sim.advance_to(0.05 + (k + 1) / RATE_HZ)
                frame = Frame.take(sim)
                t0 = time.perf_counter()
                record_frame(recorder, frame)
                times.append(time.perf_counter() - t0)
    return statistics.median(times)


def node_frame_cost(n_parts: int, frames: int = 200) -> float:
    """Median wall seconds the node spends per frame beyond the physics (publish + record)."""
    context = Context()
    rclpy.init(context=context)
    tmp = tempfile.mkdtemp()
    try:
        scene = os.path.join(tmp, 'parts.yaml')
        Path(scene).write_text(yaml.safe_dump(scene_to_dict(pile_scene(n_parts))))
        params = [Parameter('scene', value=scene), Parameter('real_time_factor', value=0.0),
                  Parameter('start_paused', value=True), Parameter('publish_rate', value=RATE_HZ),
                  Parameter('record_path', value=os.path.join(tmp, 'frames.mcap'))]
        sim_node = SimNode(context=context, parameter_overrides=params,
                           use_global_arguments=False)
        times = []
        for _ in range(frames):
            sim_node.sim.advance_to(sim_node.sim.t + 1 / RATE_HZ)
            frame = Frame.take(sim_node.sim)
            t0 = time.perf_counter()
            sim_node._publish_frame(frame)
            times.append(time.perf_counter() - t0)
        sim_node.close()
        return statistics.median(times)
    finally:
        rclpy.shutdown(context=context)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--duration', type=float, default=4.0, help='simulated s per run')
    parser.add_argument('--repeats', type=int, default=3)
    parser.add_argument('--out', default=str(ROOT / 'out' / 'bench' / 'node.json'),
                        help='JSON output (default out/bench/node.json)')
    args = parser.parse_args()

    bare(0.2), node(0.2)                     # load compiled kernels and DDS once
    runs: dict[str, list[float]] = {'bare': [], 'node': [], 'node+probe': []}
    for r in range(args.repeats):
        runs['bare'].append(bare(args.duration))
        runs['node'].append(node(args.duration)['wall_per_sim_s'])
        runs['node+probe'].append(node(args.duration, probe=True)['wall_per_sim_s'])
        print(f'[node bench] repeat {r + 1}/{args.repeats}: ' + ', '.join(
            f'{k} {v[-1] * 1e3:.0f} ms/s' for k, v in runs.items()), flush=True)
    median = {k: statistics.median(v) for k, v in runs.items()}
    rtf = {k: 1.0 / v for k, v in median.items()}
    record_50 = recording_per_frame(50)
    frame_50 = node_frame_cost(50)

    print(f'\n{SCENE}, publish_rate {RATE_HZ:g} Hz, real_time_factor 0, '
          f'{args.repeats} x {args.duration:g} s simulated (medians)')
    print(f"{'configuration':<14}{'wall s/sim s':>14}{'RTF':>8}{'vs bare':>9}")
    for k in runs:
        print(f'{k:<14}{median[k]:>14.4f}{rtf[k]:>8.1f}{rtf[k] / rtf["bare"]:>9.1%}')
    print('issue target: node RTF >= 80 % of bare')
    print(f'\nrecord_frame, 50 parts: {record_50 * 1e3:.3f} ms per frame (target <= 1 ms)')
    print(f'node publish + record, 50 parts: {frame_50 * 1e3:.3f} ms per frame')

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        'scene': SCENE, 'publish_rate_hz': RATE_HZ, 'duration_s': args.duration,
        'repeats': args.repeats, 'wall_per_sim_s': runs, 'median_wall_per_sim_s': median,
        'real_time_factor': rtf, 'node_rtf_fraction_of_bare': rtf['node'] / rtf['bare'],
        'node_probe_rtf_fraction_of_bare': rtf['node+probe'] / rtf['bare'],
        'record_frame_50_parts_s': record_50, 'node_frame_50_parts_s': frame_50,
    }, indent=2) + '\n')
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
