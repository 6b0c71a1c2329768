"""Compiled port of Baraff-Dantzig pivoting (:mod:`feeder_sim.contact.lcp` holds the Python
reference it is tested against), the boxed-LCP residual both the port and the island
solvers check their answers with, and the contact LCP of :func:`.dynamics.assemble` built
from the full 2k-row problem, with the row states of a solution and a solve on given row
states (the event-driven method re-solves its modes that way).

The port keeps the reference's sets, events and tolerances; it is flat on purpose (three
functions): numba optimizes and compiles every callee again inside each kernel that Python
calls, so deep call trees multiply the compile time (``benchmarks/compile.py``). Its
scratch comes from an arena (``ar``, :mod:`feeder_sim.compiled.arena`); each pivot's is given
back before the next.
"""

from __future__ import annotations

import numpy as np

from feeder_sim.compiled.arena import (
    arange_i,
    copy_f,
    copy_f2,
    empty_f,
    empty_f2,
    empty_i,
    full_b,
    full_i,
    local_arena,
    mark,
    release,
    zeros_f,
)
from feeder_sim.compiled.jit import inner, jit

# ---------------------------------------------------------------------------------------------
# A x + b and the residual, shared with the island solvers (``_island_kernels``)


@inner
def _affine(ar, A, x, b):
    """``A @ x + b`` (a loop: cheaper to compile than the BLAS binding, as fast at this size)."""
    m, n = A.shape
    out = empty_f(ar, m)
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += A[i, j] * x[j]
        out[i] = s + b[i]
    return out


@inner(machine_inline=True)
def _largest(A, b):
    """The largest ``|A[i, j]|`` and ``|b[i]|``: the scales of an LCP's tolerances."""
    amax = 0.0
    bmax = 0.0
    for i in range(b.shape[0]):
        bmax = max(bmax, abs(b[i]))
        for j in range(b.shape[0]):
            amax = max(amax, abs(A[i, j]))
    return amax, bmax


@inner
def _dense_residual(A, b, x, w, nof, lo, hi):
    """``lcp.residual`` of ``w = A x + b`` (w given)."""
    m = b.shape[0]
    amax, bmax = _largest(A, b)
    xmax = 0.0
    for i in range(m):
        xmax = max(xmax, abs(x[i]))
    if not np.isfinite(xmax):
        return np.inf
    s_w = max(1e-300, max(bmax, amax * xmax))
    s_x = s_w / amax if amax > 0.0 else max(1e-300, xmax)
    r = 0.0
    for k in range(m):
        xk, wk = x[k], w[k]
        j = nof[k]
        if j < 0:
            r = max(r, max(-xk / s_x, max(-wk / s_w, abs(xk * wk) / (s_x * s_w))))
        else:
            xj = max(x[j], 0.0)
            dl = xk + lo[k] * xj
            dh = hi[k] * xj - xk
            away = wk * max(dl, 0.0) if wk > 0.0 else -wk * max(dh, 0.0)
            r = max(r, max(-dl / s_x, max(-dh / s_x, away / (s_x * s_w))))
    return max(r, 0.0)


@inner
def lcp_residual(A, b, x, normal_of, lo, hi):
    """:func:`feeder_sim.contact.lcp.residual` of ``x``: inf when ``A x + b`` is not finite."""
    if b.shape[0] == 0:
        return 0.0
    w = A @ x + b
    if not np.isfinite(w.sum()):
        return np.inf
    return _dense_residual(A, b, x, w, normal_of, lo, hi)


# ---------------------------------------------------------------------------------------------
# Baraff-Dantzig pivoting: a port of ``lcp._Dantzig`` to numba with the same sets, events,
# tie-breaking, tolerances, cycling and fold handling, normals-first retry and polish. One
# difference: a (nearly) singular clamped system gets a basic solution by complete pivoting
# (dependent unknowns 0) where ``lcp`` takes the minimum-norm least-squares one; both are
# exact for a consistent system. The code is flat on purpose (three functions): numba
# re-generates every callee inside each caller, so deep call trees multiply compile time.

_U, _C, _NC, _L, _H, _DEAD, _Z = 0, 1, 2, 3, 4, 5, 6
(_DONE_C, _DONE_L, _DONE_H, _BAD, _C_NC, _NC_C, _C_L, _C_H, _SL_C,
 _Z_C) = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
_ENTERS = (_C, _L, _H, _U, _NC, _C, _L, _H, _C, _C)     # ``lcp._ENTERS``
_EPS_W = 1e-12
_EPS_ROW = 1e-13      # ``lcp._Dantzig.EPS_ROW``: a normal row's own round-off scale
_EPS_RATE = 1e-11
# abort codes (0 = success); ``time_stepping._ABORTS`` spells them out
_OK, _PIVOT_CAP, _NO_STEP, _NONFINITE, _BAD_END, _CYCLING, _BUDGET, _NUMERIC = range(8)


@inner
def _dz_solve(ar, M, r, amax, cnt):
    """``lcp._Dantzig._solve``: closed forms for n <= 2, else LU with partial pivoting; a
    (nearly) singular system (counted in cnt[1]) gets the basic solution of complete
    pivoting with two steps of iterative refinement. M and r are not modified."""
    n = r.shape[0]
    y = zeros_f(ar, n)
    if n == 0:
        return y
    level = mark(ar)
    if n == 1:
        if abs(M[0, 0]) > 1e-13 * amax:
            y[0] = r[0] / M[0, 0]
            return y
    elif n == 2:
        a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
        det = a * d - b * c
        if abs(det) > 1e-12 * (abs(a * d) + abs(b * c)):
            y[0] = (d * r[0] - b * r[1]) / det
            y[1] = (a * r[1] - c * r[0]) / det
            return y
    else:
        LU = copy_f2(ar, M)
        z = copy_f(ar, r)
        ok = True
        for k in range(n):
            p = k
            best = abs(LU[k, k])
            for i in range(k + 1, n):
                if abs(LU[i, k]) > best:
                    best, p = abs(LU[i, k]), i
            if best == 0.0:
                ok = False
                break
            if p != k:
                for j in range(n):
                    LU[k, j], LU[p, j] = LU[p, j], LU[k, j]
                z[k], z[p] = z[p], z[k]
            for i in range(k + 1, n):
                f = LU[i, k] / LU[k, k]
                if f != 0.0:
                    for j in range(k + 1, n):
                        LU[i, j] -= f * LU[k, j]
                    z[i] -= f * z[k]
        if ok:
            umin, umax = np.inf, 0.0
            for k in range(n):
                umin = min(umin, abs(LU[k, k]))
                umax = max(umax, abs(LU[k, k]))
            if umin > 1e-12 * umax:
                finite = True
                for k in range(n - 1, -1, -1):
                    s = z[k]
                    for j in range(k + 1, n):
                        s -= LU[k, j] * y[j]
                    y[k] = s / LU[k, k]
                    finite = finite and (y[k] - y[k] == 0.0)
                if finite:
                    release(ar, level)
                    return y
    # Redundant clamped rows (a tiny pivot): keep the consistent part exact instead of
    # sending the null-space component to 1e16.
    cnt[1] += 1
    for k in range(n):
        y[k] = 0.0
    LU = copy_f2(ar, M)
    rowp = arange_i(ar, n)
    colp = arange_i(ar, n)
    rank = n
    pmax = 0.0
    for k in range(n):
        best, bi, bj = 0.0, k, k
        for i in range(k, n):
            for j in range(k, n):
                if abs(LU[i, j]) > best:
                    best, bi, bj = abs(LU[i, j]), i, j
        if k == 0:
            pmax = best
        if not (best > 1e-12 * pmax):
            rank = k
            break
        for j in range(n):
            LU[k, j], LU[bi, j] = LU[bi, j], LU[k, j]
        rowp[k], rowp[bi] = rowp[bi], rowp[k]
        for i in range(n):
            LU[i, k], LU[i, bj] = LU[i, bj], LU[i, k]
        colp[k], colp[bj] = colp[bj], colp[k]
        for i in range(k + 1, n):
            f = LU[i, k] / LU[k, k]
            LU[i, k] = f
            for j in range(k + 1, n):
                LU[i, j] -= f * LU[k, j]
    res = copy_f(ar, r)
    z = empty_f(ar, n)
    u = empty_f(ar, n)
    for _ in range(3):            # solve, then two refinement steps on the residual
        for i in range(n):
            s = res[rowp[i]]
            for k in range(min(i, rank)):
                s -= LU[i, k] * z[k]
            z[i] = s
        for k in range(n):
            u[k] = 0.0
        for k in range(rank - 1, -1, -1):
            s = z[k]
            for j in range(k + 1, rank):
                s -= LU[k, j] * u[j]
            u[k] = s / LU[k, k]
        for k in range(n):
            y[colp[k]] += u[k]
        for i in range(n):
            s = r[i]
            for j in range(n):
                s -= M[i, j] * y[j]
            res[i] = s
    release(ar, level)
    return y


@inner
def _dz_direction(ar, A, b, st, nof, lo, hi, d, sigma, amax, cnt):
    """``lcp._Dantzig._direction`` (d >= 0): the unit move (dx, dw) of x_d by sigma keeping
    clamped rows' w fixed, slaved friction columns substituted into their normals' (the
    free unknowns are the clamped rows and d). With d < 0 the ``_polish`` solve instead:
    the clamped rows alone with w = 0, returned as (x, w)."""
    m = A.shape[0]
    dx = zeros_f(ar, m)
    dw = zeros_f(ar, m)
    level = mark(ar)
    nc = 0
    for i in range(m):
        if st[i] == _C:
            nc += 1
    nv = nc + 1 if d >= 0 else nc
    V = empty_i(ar, nv)
    pos = full_i(ar, m, -1)
    q = 0
    for i in range(m):
        if st[i] == _C:
            V[q] = i
            pos[i] = q
            q += 1
    if d >= 0:
        V[nc] = d
        pos[d] = nc
    cols = empty_f2(ar, m, nv)
    for p in range(nv):
        for i in range(m):
            cols[i, p] = A[i, V[p]]
    coef = zeros_f(ar, m)       # slaved rows: x_k = coef[k] x_nof[k]
    slaved = full_b(ar, m, False)
    for k in range(m):
        s = st[k]
        if s == _L or s == _H:
            p = pos[nof[k]]
            if p >= 0:
                c = -lo[k] if s == _L else hi[k]
                if c != 0.0:
                    for i in range(m):
                        cols[i, p] += c * A[i, k]
                coef[k] = c
                slaved[k] = True
    xv = empty_f(ar, nv)
    if d >= 0:
        xv[nc] = sigma
    if nc:
        M = empty_f2(ar, nc, nc)
        r = empty_f(ar, nc)
        for p in range(nc):
            for s in range(nc):
                M[p, s] = cols[V[p], s]
            r[p] = -sigma * cols[V[p], nc] if d >= 0 else -b[V[p]]
        y = _dz_solve(ar, M, r, amax, cnt)
        for p in range(nc):
            xv[p] = y[p]
    for i in range(m):
        s = 0.0 if d >= 0 else b[i]
        for p in range(nv):
            s += cols[i, p] * xv[p]
        dw[i] = s
    for p in range(nv):
        dx[V[p]] = xv[p]
    for k in range(m):
        if slaved[k]:
            dx[k] = coef[k] * dx[nof[k]]
    release(ar, level)
    return dx, dw


@inner
def dantzig(ar, A, b, nof, lo, hi, max_pivots):
    """``lcp._dantzig``: a Baraff-Dantzig pass from x = 0 and, with friction, when it
    aborts, one retry treating every normal before any friction row. Returns (x, pivots,
    abort code of the pass, abort code of the retry, row states); codes are 0 on success,
    and the row states (``_U`` .. ``_Z``) are those x ends with when the pass succeeded:
    :func:`solve_with_states` solves them again in one piece."""
    m = b.shape[0]
    amax, bmax = _largest(A, b)
    nfr = 0
    for i in range(m):
        nfr += nof[i] >= 0
    if amax == 0.0:
        amax = 1.0
    st = empty_i(ar, m)
    x = zeros_f(ar, m)
    w = empty_f(ar, m)
    nodefer = full_b(ar, m, False)
    cnt = full_i(ar, 2, 0)                # pivots, singular solves
    best_x = zeros_f(ar, m)
    best_r = np.inf
    codes = full_i(ar, 2, 0)
    ct = empty_f(ar, 2 * m + 4)           # ratio-test candidates: step, priority, row, event
    cp = empty_i(ar, 2 * m + 4)
    ci = empty_i(ar, 2 * m + 4)
    cc = empty_i(ar, 2 * m + 4)
    seen = empty_i(ar, 4 * m + 16)
    level = mark(ar)        # each direction's scratch is given back before the next
    total = 0
    for attempt in range(2):
        normals_first = attempt == 1
        cap = max_pivots - total
        for k in range(m):
            st[k] = _DEAD if nof[k] >= 0 and lo[k] == 0.0 and hi[k] == 0.0 else _U
            x[k] = 0.0
            w[k] = b[k]
            nodefer[k] = False
        cnt[0] = 0
        cnt[1] = 0
        code = _OK
        budget = 20 * (cap + m) + 100
        while True:
            budget -= 1
            if budget < 0:
                code = _BUDGET
                break
            xmax = 0.0
            for v in x:
                xmax = max(xmax, abs(v))
            eps = _EPS_W * max(max(bmax, amax * xmax), 1e-300)
            nr0 = -1
            jmin = -1
            for i in range(m):
                if st[i] == _U and nof[i] < 0:
                    if nr0 < 0:
                        nr0 = i
                    if jmin < 0 or w[i] < w[jmin]:
                        jmin = i
            fr0 = -1
            for k in range(m):
                if st[k] == _U and nof[k] >= 0 and st[nof[k]] == _C:
                    fr0 = k
                    break
            d = -1
            sigma = 1.0
            if fr0 >= 0 and not (normals_first and nr0 >= 0):
                k = fr0
                if abs(w[k]) <= eps:
                    dependent = False
                    if not nodefer[k]:
                        release(ar, level)
                        dx, dw = _dz_direction(ar, A, b, st, nof, lo, hi, k, 1.0, amax, cnt)
                        dxmax = 1.0
                        for v in dx:
                            dxmax = max(dxmax, abs(v))
                        dependent = abs(dw[k]) <= _EPS_RATE * amax * dxmax
                    st[k] = _Z if dependent else _C
                elif w[k] > 0.0:
                    if lo[k] == 0.0:
                        st[k] = _L
                    else:
                        d, sigma = k, -1.0
                elif hi[k] == 0.0:
                    st[k] = _H
                else:
                    d, sigma = k, 1.0
            elif nr0 >= 0:
                if w[jmin] >= -eps:
                    # zero on the problem's scale; some row may still approach on its own
                    # (``lcp._Dantzig._approaching``)
                    floor = _EPS_W * max(bmax, 1e-300)
                    late = -1
                    for i in range(m):
                        if st[i] == _U and nof[i] < 0 and w[i] < 0.0:
                            s_i = 0.0
                            for j in range(m):
                                s_i += abs(A[i, j]) * abs(x[j])
                            if w[i] < -max(floor, _EPS_ROW * s_i) and (
                                    late < 0 or w[i] < w[late]):
                                late = i
                    if late >= 0:
                        d, sigma = late, 1.0
                    else:
                        for i in range(m):
                            if st[i] == _U and nof[i] < 0:
                                st[i] = _NC
                else:
                    d, sigma = jmin, 1.0
            else:
                # deferred (dependent) friction rows are fine at x = 0 while their w stays 0
                bad = -1
                for k in range(m):
                    if st[k] == _Z and st[nof[k]] == _C and abs(w[k]) > eps:
                        bad = k
                        break
                if bad < 0:
                    break
                st[bad] = _U
                nodefer[bad] = True
            if d < 0:
                continue
            # ---- drive row d (``lcp._Dantzig._drive``) --------------------------------------
            isn_d = nof[d] < 0
            n_seen = 0
            prev_i, prev_code = -1, -1
            while True:
                if cnt[0] >= cap:
                    code = _PIVOT_CAP
                    break
                release(ar, level)
                dx, dw = _dz_direction(ar, A, b, st, nof, lo, hi, d, sigma, amax, cnt)
                finite = True
                dxmax = 1.0
                for r_ in range(m):
                    finite = finite and (dx[r_] - dx[r_] == 0.0) and (dw[r_] - dw[r_] == 0.0)
                    dxmax = max(dxmax, abs(dx[r_]))
                if not finite:
                    code = _NUMERIC
                    break
                dtol = _EPS_RATE * amax * dxmax
                xr = 1e-13 * dxmax
                n = 0
                if isn_d:
                    if dw[d] > dtol:
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[d] / dw[d]), 0, d, _DONE_C
                        n += 1
                    if sigma < 0.0:
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, x[d]), 2, d, _BAD
                        n += 1
                else:
                    if (w[d] > 0.0 and dw[d] < -dtol) or (w[d] < 0.0 and dw[d] > dtol):
                        ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[d] / dw[d]), 0, d, _DONE_C
                        n += 1
                    j = nof[d]
                    rate = -dx[d] - lo[d] * dx[j]
                    if rate > xr:
                        good = w[d] > 0.0
                        ct[n] = max(0.0, (x[d] + lo[d] * x[j]) / rate)
                        cp[n], ci[n], cc[n] = (0 if good else 2), d, (_DONE_L if good else _BAD)
                        n += 1
                    rate = dx[d] - hi[d] * dx[j]
                    if rate > xr:
                        good = w[d] < 0.0
                        ct[n] = max(0.0, (hi[d] * x[j] - x[d]) / rate)
                        cp[n], ci[n], cc[n] = (0 if good else 2), d, (_DONE_H if good else _BAD)
                        n += 1
                for i in range(m):
                    s = st[i]
                    if i == d or s == _U or s == _DEAD:
                        continue
                    j = nof[i]
                    if j < 0:
                        if s == _C:
                            if dx[i] < -xr:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, x[i] / -dx[i]), 1, i, _C_NC
                                n += 1
                        elif dw[i] < -dtol:
                            ct[n], cp[n], ci[n], cc[n] = max(0.0, w[i] / -dw[i]), 1, i, _NC_C
                            n += 1
                        continue
                    if s == _C:
                        # the bounds move with the normal: x_i + t dx_i = mu (x_j + t dx_j)
                        rate = -dx[i] - lo[i] * dx[j]
                        if rate > xr:
                            ct[n] = max(0.0, (x[i] + lo[i] * x[j]) / rate)
                            cp[n], ci[n], cc[n] = 1, i, _C_L
                            n += 1
                        rate = dx[i] - hi[i] * dx[j]
                        if rate > xr:
                            ct[n] = max(0.0, (hi[i] * x[j] - x[i]) / rate)
                            cp[n], ci[n], cc[n] = 1, i, _C_H
                            n += 1
                    elif st[j] == _C or j == d:
                        if s == _L:
                            if dw[i] < -dtol:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, w[i] / -dw[i]), 1, i, _SL_C
                                n += 1
                        elif s == _H:
                            if dw[i] > dtol:
                                ct[n], cp[n], ci[n], cc[n] = max(0.0, -w[i] / dw[i]), 1, i, _SL_C
                                n += 1
                        elif abs(dw[i]) > dtol:
                            # a clamped row it depended on has left C: clamp it now
                            ct[n], cp[n], ci[n], cc[n] = 0.0, 1, i, _Z_C
                            n += 1
                if n == 0:
                    code = _NO_STEP
                    break
                smin = ct[0]
                for q in range(1, n):
                    smin = min(smin, ct[q])
                if not (smin - smin == 0.0):
                    code = _NONFINITE
                    break
                lim = smin * (1.0 + 1e-12)
                sel = -1
                for q in range(n):
                    if ct[q] <= lim and (sel < 0 or cp[q] < cp[sel]
                                         or (cp[q] == cp[sel] and ci[q] < ci[sel])):
                        sel = q
                prio, i, ev = cp[sel], ci[sel], cc[sel]
                if ev == _BAD:
                    code = _BAD_END
                    break
                cnt[0] += 1
                xscale = max(bmax / amax, 1e-300)
                for v in x:
                    xscale = max(xscale, abs(v))
                if smin * dxmax > 1e-13 * xscale:
                    n_seen = 0
                else:
                    key = np.int64(1469598103934665603)
                    for v in st:
                        key = (key ^ np.int64(v)) * np.int64(1099511628211)
                    key = (key ^ np.int64(i + 1000)) * np.int64(1099511628211)
                    key = (key ^ np.int64(ev + 100)) * np.int64(1099511628211)
                    key = (key ^ np.int64(1 if sigma > 0 else 2)) * np.int64(1099511628211)
                    repeated = False
                    for q in range(n_seen):
                        if seen[q] == key:
                            repeated = True
                            break
                    if repeated:
                        # rescue: clamp waiting friction rows of active normals with w = 0
                        xmax = 0.0
                        for v in x:
                            xmax = max(xmax, abs(v))
                        eps2 = _EPS_W * max(max(bmax, amax * xmax), 1e-300)
                        rescued = False
                        for k in range(m):
                            jk = nof[k]
                            if (st[k] == _U and jk >= 0 and (st[jk] == _C or jk == d)
                                    and abs(w[k]) <= eps2):
                                st[k] = _C
                                rescued = True
                        if not rescued:
                            code = _CYCLING
                            break
                        n_seen = 0
                        prev_i = -1
                        continue
                    if n_seen == seen.shape[0]:
                        # from the heap: the arena's level is reset at every direction
                        grown = np.empty(2 * n_seen, np.int64)
                        for q in range(n_seen):
                            grown[q] = seen[q]
                        seen = grown
                    seen[n_seen] = key
                    n_seen += 1
                    if prev_i >= 0 and prev_i == i and (
                            ((prev_code == _C_L or prev_code == _C_H) and ev == _SL_C)
                            or (prev_code == _SL_C and (ev == _C_L or ev == _C_H))
                            or (prev_code == _C_NC and ev == _NC_C)
                            or (prev_code == _NC_C and ev == _C_NC)):
                        # a fold of the solution path: follow it backwards in x_d
                        sigma = -sigma
                        prev_i = -1
                        continue
                prev_i, prev_code = i, ev
                for r_ in range(m):
                    x[r_] += smin * dx[r_]
                st[d if ev <= _DONE_H else i] = _ENTERS[ev]
                if ev == _C_NC:
                    x[i] = 0.0
                    for k in range(m):
                        if nof[k] == i and st[k] != _DEAD:
                            st[k] = _U
                            x[k] = 0.0
                # sync: re-impose the x fixed by each row's set, then refresh w
                for r_ in range(m):
                    s = st[r_]
                    if r_ == d or s == _C:
                        continue
                    if s == _L or s == _H:
                        j = nof[r_]
                        if st[j] == _C or j == d:
                            x[r_] = (-lo[r_] if s == _L else hi[r_]) * x[j]
                        else:
                            x[r_] = 0.0
                    else:
                        x[r_] = 0.0
                for r_ in range(m):
                    s = b[r_]
                    for q in range(m):
                        s += A[r_, q] * x[q]
                    w[r_] = s
                if prio == 0:
                    break
            if code != _OK:
                break
        total += cnt[0]
        codes[attempt] = code
        if code == _OK:
            # polish: the final sets solved in one piece (skipped after a few
            # well-conditioned pivots)
            nc = 0
            for i in range(m):
                nc += st[i] == _C
            if nc and (cnt[0] > 4 or cnt[1] > 0):
                no_row = m - m - 1      # -1, typed like d (a literal would compile anew)
                release(ar, level)
                xp, wp = _dz_direction(ar, A, b, st, nof, lo, hi, no_row, 0.0, amax, cnt)
                finite = True
                for v in xp:
                    finite = finite and (v - v == 0.0)
                if finite and (_dense_residual(A, b, xp, wp, nof, lo, hi)
                               <= _dense_residual(A, b, x, w, nof, lo, hi)):
                    for k in range(m):
                        x[k] = xp[k]
            release(ar, level)
            return x, total, _OK, _OK, st
        r = _dense_residual(A, b, x, w, nof, lo, hi)
        if r < best_r:
            best_r = r
            for k in range(m):
                best_x[k] = x[k]
        if nfr == 0 or total >= max_pivots:
            break
    release(ar, level)
    return best_x, total, codes[0], codes[1], st


@inner
def solve_with_states(ar, A, b, nof, lo, hi, st):
    """The LCP's solution if its rows end in the states ``st`` (``dantzig``'s, e.g. those of
    the step before): the clamped rows solved in one piece with w = 0, friction rows at a
    bound slaved to their normals, the others at x = 0 (``dantzig``'s final polish). Returns
    (x, w, lcp residual); the residual is inf where the states do not fit the problem (a
    friction row at a bound of a normal that is not clamped) or the clamped rows are
    (nearly) dependent, which ``dantzig`` resolves its own way."""
    m = b.shape[0]
    amax = 0.0
    for i in range(m):
        s = st[i]
        if s < _U or s > _Z or ((s == _L or s == _H) and (nof[i] < 0 or st[nof[i]] != _C)):
            return zeros_f(ar, m), zeros_f(ar, m), np.inf
        for j in range(m):
            amax = max(amax, abs(A[i, j]))
    if amax == 0.0:
        amax = 1.0
    cnt = full_i(ar, 2, 0)
    no_row = m - m - 1      # -1, typed like dantzig's row index (a literal would compile anew)
    x, w = _dz_direction(ar, A, b, st, nof, lo, hi, no_row, 0.0, amax, cnt)
    if cnt[1]:
        return x, w, np.inf
    w = _affine(ar, A, x, b)
    return x, w, _dense_residual(A, b, x, w, nof, lo, hi)


# ---------------------------------------------------------------------------------------------
# The contact LCP in ``dynamics.assemble``'s layout from the full 2k-row problem, the row
# states a solution ends with, and solves from scratch or on known row states.

BOX_ROW, SLAVED_ROW = 1, 2    # ``dynamics.BOX`` / ``dynamics.SLAVED`` (0: no friction row)

# Row states of a frictional LCP solution: x held at 0, clamped (w = 0), friction at its lower
# or upper bound (x slaved to its normal).
HELD, CLAMPED, AT_LO, AT_HI = 0, 1, 2, 3


@jit
def lcp_pattern(x, normal_of, lo, hi):
    """Row states of a solution x (the active set a pivoting solver ended with)."""
    m = x.shape[0]
    out = np.zeros(m, np.int64)
    for k in range(m):
        j = normal_of[k]
        if j < 0:
            out[k] = CLAMPED if x[k] > 0.0 else HELD
            continue
        xj = max(x[j], 0.0)
        band = 1e-9 * (lo[k] + hi[k]) * xj
        if xj > 0.0 and hi[k] > 0.0 and abs(x[k] - hi[k] * xj) <= band:
            out[k] = AT_HI
        elif xj > 0.0 and lo[k] > 0.0 and abs(x[k] + lo[k] * xj) <= band:
            out[k] = AT_LO
        elif x[k] == 0.0:
            out[k] = HELD
        else:
            out[k] = CLAMPED
    return out


@inner
def lcp_with_pattern(A, b, normal_of, lo, hi, pattern):
    """The solution with the given row states: clamped rows get w = 0 (least squares)."""
    m = b.shape[0]
    col = np.full(m, -1, np.int64)
    nc = 0
    for k in range(m):
        if pattern[k] == CLAMPED:
            col[k] = nc
            nc += 1
    S = np.zeros((m, nc))
    for k in range(m):
        if pattern[k] == CLAMPED:
            S[k, col[k]] = 1.0
        elif normal_of[k] >= 0 and col[normal_of[k]] >= 0:
            if pattern[k] == AT_LO:
                S[k, col[normal_of[k]]] = -lo[k]
            elif pattern[k] == AT_HI:
                S[k, col[normal_of[k]]] = hi[k]
    x = np.zeros(m)
    if nc == 0:
        return x
    AS = A @ S
    M = np.empty((nc, nc))
    rhs = np.empty(nc)
    for k in range(m):
        if col[k] >= 0:
            M[col[k]] = AS[k]
            rhs[col[k]] = -b[k]
    z = np.linalg.lstsq(M, rhs, 1e-13)[0]
    return S @ z


@jit
def reduce_lcp(W, friction, mu_lo, mu_hi, slave):
    """The boxed LCP of :func:`feeder_sim.contact.dynamics.assemble` from the full 2k problem:
    ``(A, P, rows, normal_of, lo, hi)`` with ``b = b_full[rows]`` and the stacked solution
    ``P @ x``. Friction NONE drops the row, BOX keeps it, SLAVED ties it to its normal."""
    c = friction.shape[0]
    nbox = 0
    for i in range(c):
        if friction[i] == BOX_ROW:
            nbox += 1
    m = c + nbox
    P = np.zeros((2 * c, m))
    rows = np.empty(m, np.int64)
    normal_of = np.full(m, -1, np.int64)
    lo = np.zeros(m)
    hi = np.zeros(m)
    for i in range(c):
        P[i, i] = 1.0
        rows[i] = i
    r = c
    for i in range(c):
        if friction[i] == BOX_ROW:
            P[c + i, r] = 1.0
            rows[r], normal_of[r], lo[r], hi[r] = c + i, i, mu_lo[i], mu_hi[i]
            r += 1
        elif friction[i] == SLAVED_ROW:
            P[c + i, i] = slave[i]
    A = np.empty((m, 2 * c))
    for i in range(m):
        A[i] = W[rows[i]]
    return A @ P, P, rows, normal_of, lo, hi


@jit
def lcp_known_pattern(W, b_full, friction, mu_lo, mu_hi, slave, pattern):
    """Solve the contact LCP with given row states: ``(stacked solution, x, w, residual)``."""
    A, P, rows, normal_of, lo, hi = reduce_lcp(W, friction, mu_lo, mu_hi, slave)
    b = b_full[rows]
    if pattern.shape[0] != b.shape[0]:
        x = np.zeros(b.shape[0])
        return P @ x, x, b, np.inf
    x = lcp_with_pattern(A, b, normal_of, lo, hi, pattern)
    return P @ x, x, A @ x + b, lcp_residual(A, b, x, normal_of, lo, hi)


@jit
def lcp_dantzig(W, b_full, friction, mu_lo, mu_hi, slave):
    """Solve the contact LCP from scratch by the compiled Baraff-Dantzig pivoting
    (:func:`dantzig`, a port of ``lcp.solve``'s first method):
    ``(stacked solution, x, w, residual, pivots, abort codes)`` with the reduced problem
    ``(A, b, normal_of, lo, hi)`` for the caller's fallback when the residual misses."""
    A, P, rows, normal_of, lo, hi = reduce_lcp(W, friction, mu_lo, mu_hi, slave)
    b = b_full[rows]
    m = b.shape[0]
    # the pivots' scratch in one allocation (a direction's dense system and its LU, the
    # bookkeeping; each direction's is given back before the next) instead of some fifty
    buf = np.empty(8 * (4 * m * m + 48 * m) + 8192, np.uint8)
    scratch = local_arena(buf)
    x, pivots, code, retry, _ = dantzig(scratch, A, b, normal_of, lo, hi, 50 * m + 50)
    x = x.copy()
    release(scratch, 0)
    if buf.shape[0] == 0:    # (buf in use until x is out of it)
        x = x.copy()
    res = lcp_residual(A, b, x, normal_of, lo, hi)
    return P @ x, x, A @ x + b, res, pivots, (code, retry), (A, P, b, normal_of, lo, hi)
