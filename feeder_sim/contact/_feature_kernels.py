"""Contact rows of many steps summed per vertex-edge feature, compiled.

What the simulator's impulse log (``simulator.impulse_log.ImpulseLog``) does between two
reports: a pile gives thousands of rows per step, and the numpy version of this reduction
(a stable sort, ``np.add.at`` and a dozen whole-array passes) cost more than the step of a
single part.
"""

from __future__ import annotations

import numpy as np

from feeder_sim.compiled.jit import jit

# Fibonacci hashing: the key times 2^64 / golden ratio, its top bits the slot.
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@jit
def sum_by_feature(key, point, normal, p_n, p_t, body_a, body_b):
    """One row per distinct ``key`` (rows in step order): features in order of first
    appearance, the latest row's point, normal and bodies, and the impulses ``p_n`` / ``p_t``
    (N s) summed in row order from -0.0, so that the bits and the sign of a zero are those of
    a running ``+=``. Returns (key, point, normal, p_n, p_t, body_a, body_b).

    One pass over the rows with an open-addressing table of the keys (no sort: a feature's
    rows are summed as they come)."""
    n = key.shape[0]
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    mask = (1 << bits) - 1
    shift = np.uint64(64 - bits)
    slot_feature = np.full(1 << bits, -1, np.int64)
    first = np.empty(n, np.int64)
    last = np.empty(n, np.int64)
    sum_n = np.empty(n)
    sum_t = np.empty(n)
    n_f = 0
    for row in range(n):
        k = key[row]
        h = np.int64((np.uint64(k) * _GOLDEN) >> shift)
        while slot_feature[h] >= 0 and key[first[slot_feature[h]]] != k:
            h = (h + 1) & mask
        f = slot_feature[h]
        if f < 0:
            f = n_f
            n_f += 1
            slot_feature[h] = f
            first[f] = row
            sum_n[f] = -0.0
            sum_t[f] = -0.0
        last[f] = row
        sum_n[f] += p_n[row]
        sum_t[f] += p_t[row]
    out_key = np.empty(n_f, key.dtype)
    out_point = np.empty((n_f, 2))
    out_normal = np.empty((n_f, 2))
    out_a = np.empty(n_f, body_a.dtype)
    out_b = np.empty(n_f, body_b.dtype)
    for f in range(n_f):
        row = last[f]
        out_key[f] = key[first[f]]
        out_point[f, 0], out_point[f, 1] = point[row, 0], point[row, 1]
        out_normal[f, 0], out_normal[f, 1] = normal[row, 0], normal[row, 1]
        out_a[f], out_b[f] = body_a[row], body_b[row]
    return out_key, out_point, out_normal, sum_n[:n_f].copy(), sum_t[:n_f].copy(), out_a, out_b
