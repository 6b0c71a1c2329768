"""Compiled narrow phase and contact clean-up of ``collision.find_contacts``.

The tests are those the module docstring of ``collision`` states. Library sorts,
``searchsorted`` and sets are avoided: each pulls generic code into the compile and
lengthens it (``benchmarks/compile.py``).
The kernels take a scratch arena first (``ar``, :mod:`feeder_sim.compiled.arena`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.arena import arange_i, empty_f, empty_i, full_b, full_i, gather
from feeder_sim.compiled.jit import for_python, inner

_RUN = 16      # _argsort's insertion-sorted runs
_RADIX_BITS = 8     # _argsort_int's digit
_RADIX_MIN = 100    # keys below which _argsort_int leaves them to _argsort (as fast there)
# bodies x vertices below which (bodies x vertices)^2 fits in int64 (2^63 ~ 9.2e18)
_ONE_KEY_LIMIT = 3_000_000_000


@inner
def _argsort(ar, keys):
    """Stable argsort: insertion-sorted runs of ``_RUN``, then bottom-up merges, a merge of two
    runs already in order being a copy (keys here are mostly in order already: pieces by x
    from one step to the next). Hand-written because ``np.argsort`` with a ``kind`` compiles
    numba's generic sorts and string handling, which lengthen the compile. Keys must not be
    NaN."""
    n = keys.shape[0]
    idx = arange_i(ar, n)
    for lo in range(0, n, _RUN):
        hi = min(lo + _RUN, n)
        for i in range(lo + 1, hi):
            v = idx[i]
            kv = keys[v]
            j = i - 1
            while j >= lo and kv < keys[idx[j]]:
                idx[j + 1] = idx[j]
                j -= 1
            idx[j + 1] = v
    if n <= _RUN:
        return idx
    tmp = empty_i(ar, n)
    width = _RUN
    while width < n:
        lo = 0
        while lo < n:
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            if mid == hi or not (keys[idx[mid]] < keys[idx[mid - 1]]):
                for k in range(lo, hi):
                    tmp[k] = idx[k]
                lo += 2 * width
                continue
            i, j, k = lo, mid, lo
            while i < mid and j < hi:
                if keys[idx[j]] < keys[idx[i]]:
                    tmp[k] = idx[j]
                    j += 1
                else:
                    tmp[k] = idx[i]
                    i += 1
                k += 1
            while i < mid:
                tmp[k] = idx[i]
                i += 1
                k += 1
            while j < hi:
                tmp[k] = idx[j]
                j += 1
                k += 1
            lo += 2 * width
        idx, tmp = tmp, idx
        width *= 2
    return idx


@inner
def _argsort_int(ar, keys):
    """:func:`_argsort` of integer keys (the same permutation: both are stable). Non-negative
    keys, from ``_RADIX_MIN`` of them on, are sorted by their digits of ``_RADIX_BITS`` bits,
    least significant first, each pass a stable counting sort (a pass whose digit every key
    shares is skipped): some 3 n steps a pass instead of n log n comparisons that a branch
    predictor cannot guess (the contact and warm-start keys of a step are not in order)."""
    n = keys.shape[0]
    if n < _RADIX_MIN:
        return _argsort(ar, keys)
    bits = 0
    for i in range(n):
        if keys[i] < 0:
            return _argsort(ar, keys)
        bits |= keys[i]
    idx = arange_i(ar, n)
    tmp = empty_i(ar, n)
    start = empty_i(ar, 1 << _RADIX_BITS)
    mask = (1 << _RADIX_BITS) - 1
    shift = 0
    while shift < 63 and bits >> shift:      # (a shift by 64 bits would be undefined)
        for d in range(1 << _RADIX_BITS):
            start[d] = 0
        for i in range(n):
            start[(keys[i] >> shift) & mask] += 1
        if start[(keys[0] >> shift) & mask] < n:
            total = 0
            for d in range(1 << _RADIX_BITS):
                c = start[d]
                start[d] = total
                total += c
            for i in range(n):
                v = idx[i]
                d = (keys[v] >> shift) & mask
                tmp[start[d]] = v
                start[d] += 1
            idx, tmp = tmp, idx
        shift += _RADIX_BITS
    return idx


@inner
def sorted_unique(ar, x):
    """``np.unique`` of an integer array (its sorted distinct values), at a fraction of the
    compile time: numba's version brings its generic sort along."""
    n = x.shape[0]
    out = empty_i(ar, n)
    m = 0
    for i in _argsort_int(ar, x):
        if m == 0 or x[i] != out[m - 1]:
            out[m] = x[i]
            m += 1
    return out[:m]


@inner
def _where(ar, mask):
    n = 0
    for v in mask:
        n += v
    out = empty_i(ar, n)
    q = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            out[q] = i
            q += 1
    return out


# ---------------------------------------------------------------------------------------------
# collision detection: broad and narrow phase of ``collision.find_contacts``


@inner
def _vertex_edge(pv_lo, pv_hi, qe_lo, qe_hi, w, nw, active, internal, nxt, prv, elen, margin,
                 depth, tie, param_tol, angle_tol, out_v, out_e, out_g, out_t, n_out):
    """Vertices pv_lo..pv_hi-1 of one piece against edges qe_lo..qe_hi-1 of another: each
    active vertex takes the least-penetrated face it can touch (``collision``'s step 3)."""
    for v in range(pv_lo, pv_hi):
        if not active[v]:
            continue
        px, py = w[v, 0], w[v, 1]
        dmax = -np.inf
        for e in range(qe_lo, qe_hi):
            if not internal[e]:
                d = nw[e, 0] * (px - w[e, 0]) + nw[e, 1] * (py - w[e, 1])
                if d > dmax:
                    dmax = d
        if not (dmax - tie <= margin and dmax >= -depth):
            continue
        ip, ix = prv[v], nxt[v]
        ux, uy = w[ip, 0] - px, w[ip, 1] - py
        xx, xy = w[ix, 0] - px, w[ix, 1] - py
        slack_u = max(margin, angle_tol * elen[ip])
        slack_x = max(margin, angle_tol * elen[v])
        best = -np.inf
        best_e = -1
        best_t = 0.0
        for e in range(qe_lo, qe_hi):
            if internal[e]:
                continue
            nx, ny = nw[e, 0], nw[e, 1]
            dx, dy = px - w[e, 0], py - w[e, 1]
            d = nx * dx + ny * dy
            q1 = nxt[e]
            ex, ey = w[q1, 0] - w[e, 0], w[q1, 1] - w[e, 1]
            t = (dx * ex + dy * ey) / (ex * ex + ey * ey)
            if not (t >= -param_tol and t <= 1.0 + param_tol):
                continue
            if not (ux * nx + uy * ny >= -slack_u and xx * nx + xy * ny >= -slack_x):
                continue
            if d > best:
                best, best_e, best_t = d, e, t
        if best_e >= 0 and best <= margin and best >= -depth:
            out_v[n_out] = v
            out_e[n_out] = best_e
            out_g[n_out] = best
            out_t[n_out] = best_t
            n_out += 1
    return n_out


class NarrowPhaseTolerances(NamedTuple):
    """The scalars of ``narrow_phase`` (``collision.find_contacts``' arguments and defaults)."""

    bp_margin_m: float       # broad phase: AABBs within this distance pair up
    margin_m: float          # contacts up to this gap
    depth_m: float           # and down to minus this gap; < 0: depth_fraction per pair
    depth_fraction: float    # default depth, share of the smaller piece width
    tie_rel: float           # face ties, relative to the pair's coordinate scale
    param_tol: float         # edge-parameter slack at the edge's ends
    angle_tol: float         # supporting-vertex slack per unit edge length


@inner(machine_inline=True)
def narrow_phase_inline(ar, w, nw, lo, hi, piece_start, piece_body, take, dyn, piece_width,
                        coord, radius, active, internal, nxt, prv, elen, tol):
    """Vertex-edge contacts of all piece pairs whose AABBs are within ``tol.bp_margin_m``
    (``tol`` a :class:`NarrowPhaseTolerances`).

    The pair set is that of ``collision.candidate_pairs`` (closed AABB overlap on both axes,
    pieces of different bodies, both taking part, at least one dynamic), found by a sweep
    along x; the per-pair test is ``_vertex_edge`` in both directions.
    ``depth < 0`` means the default per pair (``depth_fraction`` x the smaller piece width).
    Returns unordered (vertex, edge, gap, edge_param) and the number of candidate pairs."""
    bp_margin, margin, depth = tol.bp_margin_m, tol.margin_m, tol.depth_m
    depth_fraction, tie_rel = tol.depth_fraction, tol.tie_rel
    param_tol, angle_tol = tol.param_tol, tol.angle_tol
    n_p = piece_body.shape[0]
    ids = empty_i(ar, n_p)
    n_t = 0
    for p in range(n_p):
        if take[p]:
            ids[n_t] = p
            n_t += 1
    ids = ids[:n_t]
    key = empty_f(ar, n_t)
    for q in range(n_t):
        key[q] = lo[ids[q], 0]
    order = gather(ar, ids, _argsort(ar, key))
    cap = 64
    out_v = empty_i(ar, cap)
    out_e = empty_i(ar, cap)
    out_g = empty_f(ar, cap)
    out_t = empty_f(ar, cap)
    n_out = np.int64(0)      # never a literal: typing would compile _vertex_edge for it
    n_pairs = 0
    for ii in range(n_t):
        p = order[ii]
        reach = hi[p, 0] + bp_margin
        for jj in range(ii + 1, n_t):
            q = order[jj]
            if lo[q, 0] > reach:
                break
            if piece_body[p] == piece_body[q] or not (dyn[p] or dyn[q]):
                continue
            if not (lo[p, 1] <= hi[q, 1] + bp_margin and lo[q, 1] <= hi[p, 1] + bp_margin):
                continue
            if not (lo[q, 0] <= hi[p, 0] + bp_margin and lo[p, 0] <= hi[q, 0] + bp_margin):
                continue
            n_pairs += 1
            a, b = min(p, q), max(p, q)
            a0, a1 = piece_start[a], piece_start[a + 1]
            b0, b1 = piece_start[b], piece_start[b + 1]
            need = n_out + (a1 - a0) + (b1 - b0)
            if need > cap:
                while need > cap:
                    cap *= 2
                nv = empty_i(ar, cap)
                ne = empty_i(ar, cap)
                ng = empty_f(ar, cap)
                nt = empty_f(ar, cap)
                for q in range(n_out):
                    nv[q], ne[q], ng[q], nt[q] = out_v[q], out_e[q], out_g[q], out_t[q]
                out_v, out_e, out_g, out_t = nv, ne, ng, nt
            if depth < 0.0:
                dp = depth_fraction * min(piece_width[a], piece_width[b])
            else:
                dp = depth
            tie = tie_rel * (coord[piece_body[a]] + coord[piece_body[b]] + radius[a]
                             + radius[b])
            n_out = _vertex_edge(a0, a1, b0, b1, w, nw, active, internal, nxt, prv, elen,
                                 margin, dp, tie, param_tol, angle_tol, out_v, out_e, out_g,
                                 out_t, n_out)
            n_out = _vertex_edge(b0, b1, a0, a1, w, nw, active, internal, nxt, prv, elen,
                                 margin, dp, tie, param_tol, angle_tol, out_v, out_e, out_g,
                                 out_t, n_out)
    return out_v[:n_out], out_e[:n_out], out_g[:n_out], out_t[:n_out], n_pairs


narrow_phase = for_python(narrow_phase_inline)


@inner(machine_inline=True)
def clean_contacts_inline(ar, vert, edge, gap, t, cover_start, cover_lo, cover_hi, nxt, canon,
                          vbody, nw, n_vertices, n_bodies, param_tol, angle_tol):
    """The clean-up of ``collision.find_contacts`` after the narrow phase: contacts on
    internal edge portions and one of each vertex-on-vertex pair dropped from the raw
    contacts, duplicates of one canonical vertex against parallel edges of one body merged
    among the survivors, then the order by (min body, max body, piece_a, vertex, piece_b, edge)
    (pieces are numbered in vertex order, so vertex and edge imply the pieces). Returns the
    indices of the kept contacts in that order."""
    k = vert.shape[0]
    keep = full_b(ar, k, True)
    # contacts on internal portions of compound-body edges
    for i in range(k):
        e = edge[i]
        tc = min(max(t[i], 0.0), 1.0)
        for q in range(cover_start[e], cover_start[e + 1]):
            lo, hi = cover_lo[q], cover_hi[q]
            if (((tc > lo + param_tol) or (lo <= param_tol))
                    and ((tc < hi - param_tol) or (hi >= 1.0 - param_tol))):
                keep[i] = False
    # vertex on vertex: keep the contact whose edge belongs to the lower-numbered body
    end = full_i(ar, k, -1)
    n_cand = 0
    for i in range(k):
        if abs(t[i]) <= param_tol:
            end[i] = edge[i]
        elif abs(t[i] - 1.0) <= param_tol:
            end[i] = nxt[edge[i]]
        if end[i] >= 0:
            n_cand += 1
    if n_cand >= 2:
        rev = empty_i(ar, n_cand)
        q = 0
        for i in range(k):
            if end[i] >= 0:
                rev[q] = canon[vert[i]] * n_vertices + canon[end[i]]
                q += 1
        rev = gather(ar, rev, _argsort_int(ar, rev))
        for i in range(k):
            if end[i] >= 0 and vbody[edge[i]] > vbody[vert[i]]:
                key = canon[end[i]] * n_vertices + canon[vert[i]]
                lo_, hi_ = 0, n_cand          # binary search: first rev >= key
                while lo_ < hi_:
                    mid = (lo_ + hi_) // 2
                    if rev[mid] < key:
                        lo_ = mid + 1
                    else:
                        hi_ = mid
                if lo_ < n_cand and rev[lo_] == key:
                    keep[i] = False
    idx = _where(ar, keep)
    n = idx.shape[0]
    # duplicates: one canonical vertex against parallel edges of one body
    if n >= 2:
        gkey = empty_i(ar, n)
        for q in range(n):
            i = idx[q]
            gkey[q] = ((vbody[vert[i]] * n_vertices + canon[vert[i]]) * n_bodies
                       + vbody[edge[i]])
        o = _argsort_int(ar, gkey)
        s0 = 0
        while s0 < n:
            s1 = s0 + 1
            while s1 < n and gkey[o[s1]] == gkey[o[s0]]:
                s1 += 1
            if s1 - s0 >= 2:
                # members by (gap, vertex, edge), then keep greedily
                mem = gather(ar, idx, o[s0:s1])
                for u in range(1, mem.shape[0]):
                    v = mem[u]
                    p = u - 1
                    while p >= 0 and (gap[mem[p]] > gap[v] or (gap[mem[p]] == gap[v] and (
                            vert[mem[p]] > vert[v] or (vert[mem[p]] == vert[v]
                                                       and edge[mem[p]] > edge[v])))):
                        mem[p + 1] = mem[p]
                        p -= 1
                    mem[p + 1] = v
                kept = empty_i(ar, mem.shape[0])
                nk = 0
                for u in range(mem.shape[0]):
                    ci = mem[u]
                    nx, ny = nw[edge[ci], 0], nw[edge[ci], 1]
                    dup = False
                    for z in range(nk):
                        mx, my = nw[edge[kept[z]], 0], nw[edge[kept[z]], 1]
                        if nx * mx + ny * my > 0 and abs(nx * my - ny * mx) <= angle_tol:
                            dup = True
                            break
                    if dup:
                        keep[ci] = False
                    else:
                        kept[nk] = ci
                        nk += 1
            s0 = s1
        idx = _where(ar, keep)
        n = idx.shape[0]
    # final order: by k1 (the body pair), then k2 (vertex, edge), then found order; one sort
    # of k1 x n_vertices^2 + k2 where that fits in int64, else by k2 then stably by k1
    one_key = n_bodies * n_vertices < _ONE_KEY_LIMIT
    span = n_vertices * n_vertices if one_key else 1
    k1 = empty_i(ar, n)
    k2 = empty_i(ar, n)
    for q in range(n):
        i = idx[q]
        ba, bb = vbody[vert[i]], vbody[edge[i]]
        k2[q] = vert[i] * n_vertices + edge[i]
        k1[q] = min(ba, bb) * n_bodies + max(ba, bb)
        if one_key:
            k1[q] = k1[q] * span + k2[q]
    if one_key:
        return gather(ar, idx, _argsort_int(ar, k1))
    o2 = _argsort_int(ar, k2)
    o1 = _argsort_int(ar, gather(ar, k1, o2))
    return gather(ar, idx, gather(ar, o2, o1))


clean_contacts = for_python(clean_contacts_inline)
