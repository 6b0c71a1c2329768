"""Bit-level fingerprint of every shipped scene on every stepping method.

Each case runs a shipped scene for a short, fixed simulated time in frames of 10 ms, taking the
contact report after every frame as the node and the CLI do. Its fingerprint is the solver
counters (steps, events, LCP solves, pivots, ...), the exact bits of the final state, and a hash
of every frame's state and contact report. Two code versions that give the same fingerprints
step, collide and solve identically on these scenes.

    python test/fingerprint.py --write test/data/fingerprint.json   # record
    python test/fingerprint.py --check test/data/fingerprint.json   # compare, exit 1 on change
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
import sys
import time

import numpy as np

from feeder_sim.simulator import Simulator

FRAME_S = 0.01
METHODS = ('event_driven', 'time_stepping', 'impulse_based')
# Simulated seconds per scene: long enough to reach the scene's contact modes (landings, sticking,
# sliding, stacking), short enough for the suite.
DURATIONS = {
    'track_one_box': 0.3,
    'track_ten_boxes': 0.1,
    'incline_stick': 0.2,
    'incline_slide': 0.2,
    'bowl_track_0deg': 0.3,
    'bowl_track_0deg_no_friction_impulse': 0.3,
    'bowl_track_3deg': 0.3,
    'bowl_track_3deg_no_friction_impulse': 0.3,
    'orienter_hook': 0.05,
    'orienter_hook_short': 0.05,
    'orienter_partition': 0.2,
}
# event_driven integrates the partition orienter's stack of six cups in the magazine with its
# general path from the first frame: a shorter run there.
DURATION_OVERRIDES = {('orienter_partition', 'event_driven'): 0.02}


def _state_bytes(sim: Simulator) -> bytes:
    s = sim.state
    return b''.join([np.float64(s.t).tobytes(), s.position.tobytes(), s.angle.tobytes(),
                     s.velocity.tobytes(), s.omega.tobytes()])


def _report_bytes(sim: Simulator) -> bytes:
    r = sim.take_contacts()
    return b''.join(np.ascontiguousarray(a).tobytes() for a in (
        r.point, r.normal, r.normal_impulse, r.tangent_impulse, r.body_a, r.body_b))


def fingerprint(scene: str, method: str) -> dict:
    sim = Simulator(scene, method=method)
    frames = hashlib.sha256()
    n = round(DURATION_OVERRIDES.get((scene, method), DURATIONS[scene]) / FRAME_S)
    for k in range(1, n + 1):
        sim.advance(k * FRAME_S)
        frames.update(_state_bytes(sim))
        frames.update(_report_bytes(sim))
    stats = sim.stats.as_dict()
    stats['messages'] = len(stats['messages'])
    for key, value in stats.items():
        if isinstance(value, float):
            stats[key] = value.hex()
    s = sim.state
    return {
        'stats': stats,
        'final_t': float(s.t).hex(),
        'final_state_sha256': hashlib.sha256(_state_bytes(sim)).hexdigest(),
        'final_position': [float(v).hex() for v in s.position.ravel()[:6]],
        'frames_sha256': frames.hexdigest(),
    }


# impulse_based resolves the orienters' touching queues of cups one micro-collision at a time and
# advances microseconds per minute of wall time there: left out.
SLOW = {('orienter_hook', 'impulse_based'), ('orienter_hook_short', 'impulse_based'),
        ('orienter_partition', 'impulse_based')}


def cases() -> list[tuple[str, str]]:
    return [(scene, method) for scene in DURATIONS for method in METHODS
            if (scene, method) not in SLOW]


def run_all(selected: list[tuple[str, str]] | None = None, verbose: bool = True) -> dict:
    out = {}
    for scene, method in selected or cases():
        t0 = time.perf_counter()
        out[f'{scene}/{method}'] = fingerprint(scene, method)
        if verbose:
            print(f'{scene:40s} {method:14s} {time.perf_counter() - t0:7.2f} s', flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument('--write', type=Path)
    group.add_argument('--check', type=Path)
    args = ap.parse_args(argv)
    got = run_all()
    if args.write:
        args.write.write_text(json.dumps(got, indent=1, sort_keys=True) + '\n')
        return 0
    want = json.loads(args.check.read_text())
    bad = [k for k in want if want[k] != got.get(k)]
    for k in bad:
        print(f'CHANGED {k}:')
        for field in want[k]:
            if want[k][field] != got[k][field]:
                print(f'  {field}: {want[k][field]} -> {got[k][field]}')
    print(f'{len(want) - len(bad)} of {len(want)} cases identical to the bit')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
