"""Bit-level fingerprint of every shipped scene on every stepping method.

Each case runs a shipped scene for a short, fixed simulated time in frames of 10 ms, taking the
contact report after every frame as the node and the CLI do. Its fingerprint is the solver
counters (steps, events, LCP solves, pivots, ...), the exact bits of the final state, and a hash
of every frame's state and contact report. Two code versions that give the same fingerprints
step, collide and solve identically on these scenes.

Bits are a property of the machine too: the LAPACK builds pick kernels for the CPU (the
event-driven method's least squares go through them) and round differently on another one.
The file records a signature of those results (:func:`platform_signature`); on a machine
with another signature, the cases are compared to round-off instead
(:func:`beyond_round_off`): the same counters and final time, the final positions within
``POSITION_TOL_M``.

    python test/fingerprint.py --write test/data/fingerprint.json   # record
    python test/fingerprint.py --check test/data/fingerprint.json   # compare, exit 1 on change

``--method M`` (repeatable) takes that method's cases only: ``--check`` compares those,
``--write`` replaces those in the file and keeps the others.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from pathlib import Path
import sys
import time

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

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


PLATFORM_KEY = '_platform'
# Final positions of a case on another machine: round-off (1e-16 m) grown over a short run;
# a change to the physics moves a part by micrometres at least.
POSITION_TOL_M = 1e-9
# Counters that depend on rounding: pivots resolve ties between rows in a rounding-dependent
# order.
ROUNDING_COUNTERS = frozenset({'pivots'})


def platform_signature() -> str:
    """A hash of floating-point results that depend on the machine rather than on this code:
    least squares and LU factors of nearly rank-deficient systems (like contact Jacobians)
    from numpy's and scipy's LAPACK, and the math library's functions."""
    rng = np.random.default_rng(2026)
    h = hashlib.sha256()
    for n in (3, 6, 12, 40):
        a = rng.standard_normal((n, n))
        a[:, -1] = a[:, 0] + 1e-9 * a[:, 1]
        b = rng.standard_normal((n, 2))
        h.update(np.linalg.lstsq(a, b, rcond=1e-12)[0].tobytes())
        h.update(scipy.linalg.lstsq(a, b, cond=1e-12, lapack_driver='gelsd')[0].tobytes())
        h.update(scipy.linalg.lapack.dgetrf(a)[0].tobytes())
        h.update((a @ b).tobytes())
    x = np.linspace(-20.0, 20.0, 4001)
    for y in (np.sin(x), np.cos(x), np.exp(x / 4), np.log1p(np.abs(x)), np.arctan2(x, 1 + x * x),
              np.sqrt(np.abs(x)), [math.sin(v) + math.cos(v) + math.atan2(v, 3.0) for v in x]):
        h.update(np.asarray(y).tobytes())
    return h.hexdigest()[:16]


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-9 + 1e-6 * max(abs(a), abs(b))


def beyond_round_off(got: dict, want: dict) -> list[str]:
    """The differences between two fingerprints of a case that round-off does not explain:
    counters other than :data:`ROUNDING_COUNTERS`, the final time, float statistics beyond
    1e-9 + 1e-6 relative, final positions beyond :data:`POSITION_TOL_M`."""
    bad = []
    for key, w in want['stats'].items():
        g = got['stats'].get(key)
        if isinstance(w, str):
            if g is None or not _close(float.fromhex(g), float.fromhex(w)):
                bad.append(f'stats.{key}: {w} -> {g}')
        elif key not in ROUNDING_COUNTERS and g != w:
            bad.append(f'stats.{key}: {w} -> {g}')
    if got['final_t'] != want['final_t']:
        bad.append(f'final_t: {want["final_t"]} -> {got["final_t"]}')
    for i, (g, w) in enumerate(zip(got['final_position'], want['final_position'], strict=True)):
        if not abs(float.fromhex(g) - float.fromhex(w)) <= POSITION_TOL_M:
            bad.append(f'final_position[{i}]: {w} -> {g}')
    return bad


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


def cases(methods: tuple[str, ...] | list[str] = METHODS) -> list[tuple[str, str]]:
    """(scene, method) of every case of ``methods``."""
    return [(scene, method) for scene in DURATIONS for method in METHODS
            if method in methods and (scene, method) not in SLOW]


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
    ap.add_argument('--method', action='append', choices=METHODS,
                    help="this method's cases only (repeatable; default: all)")
    args = ap.parse_args(argv)
    got = run_all(cases(args.method or METHODS))
    if args.write:
        if args.method and args.write.exists():
            kept = json.loads(args.write.read_text())
            if kept.get(PLATFORM_KEY) != platform_signature():
                print('the file was recorded on a machine that rounds differently: write all '
                      'of it (no --method)', file=sys.stderr)
                return 2
            got = {**kept, **got}
        got[PLATFORM_KEY] = platform_signature()
        args.write.write_text(json.dumps(got, indent=1, sort_keys=True) + '\n')
        return 0
    want = json.loads(args.check.read_text())
    exact = want.pop(PLATFORM_KEY, None) == platform_signature()
    if args.method:
        want = {k: v for k, v in want.items() if k.rpartition('/')[2] in args.method}
    if not exact:
        print('recorded on a machine that rounds differently: comparing to round-off')
    bad = 0
    for k in want:
        if exact and want[k] != got.get(k):
            bad += 1
            print(f'CHANGED {k}:')
            for field in want[k]:
                if want[k][field] != got[k][field]:
                    print(f'  {field}: {want[k][field]} -> {got[k][field]}')
        elif not exact and (lines := beyond_round_off(got[k], want[k])):
            bad += 1
            print(f'CHANGED {k}:', *lines, sep='\n  ')
    print(f'{len(want) - bad} of {len(want)} cases identical '
          f'{"to the bit" if exact else "to round-off"}')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
