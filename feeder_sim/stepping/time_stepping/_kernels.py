"""``time_stepping``'s whole step, compiled: many steps per call, no Python per step.

:func:`advance` is ``TimeStepper.step`` (drift, drives, contact search, rows, islands, the
small islands' Baraff-Dantzig, the piles' PGS with Kawachi's second pass, impulses, drift, the
position projection) with the same operations in the same order, so a frame gives the bits of
the Python path, which stays the reference it is tested against (``test/test_fingerprint.py``
runs every shipped scene through this kernel against states recorded from the Python path).

A step the kernel does not take itself is handed back before anything of it is written:
``advance`` returns ``REFERENCE`` and ``TimeStepper`` takes that one step in Python, then
calls the kernel again. That is a step where the compiled Dantzig misses ``lcp_tol`` (the
reference's fallback ladder solves it, counted in ``stats.fallbacks`` there), or where a
step's contacts would overflow the report buffers (``GROW``: they are doubled). Contacts
with restitution are stepped here too: the velocities a speculative row held back
(:class:`Approach`) travel from step to step like the warm start.

The step, its contact search and its solve are compiled into ``advance`` itself (LLVM
inlining, ``machine_inline``) rather than called: a call between kernels hands over every
array of its arguments (the step's are some 80) and clears the callee's local array slots.
Called, the kernels would spend more than half of a free part's step on that, and a
sizeable share of one part's conveying at dt = 1e-4 (``benchmarks/throughput.py``).
The price is a longer first compile of ``time_stepping`` (``benchmarks/compile.py``); the
default run (``event_driven``) does not compile this module.

The kernels of the contact layer the step calls (``narrow_phase``, ``contact_rows``,
``solve_small``, ...) it calls through their ``_inline`` twins, the same code that LLVM
always inlines; Python callers keep the ``jit`` entry points. LLVM inlines the ``jit`` ones
only when they are compiled for this step: where the Python reference has compiled them
first (the test suite, a reference step), the step is linked against them as calls, and the
speed of the same source would depend on which process filled the cache.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.arena import (
    borrow,
    concat,
    copy_f,
    copy_f2,
    copy_i,
    empty_b,
    empty_f,
    empty_f2,
    empty_i,
    full_b,
    full_i,
    gather,
    gather_rows,
    release,
    zeros_f,
    zeros_f2,
)
from feeder_sim.compiled.jit import for_python, inner, jit
from feeder_sim.contact._collision_kernels import (
    _argsort,
    _argsort_int,
    _where,
    clean_contacts_inline,
    narrow_phase_inline,
    NarrowPhaseTolerances,
)
from feeder_sim.contact._island_kernels import (
    _contact_velocity,
    any_kept_inline,
    apply_impulses_inline,
    breakaway_within_step_inline,
    contact_rows_inline,
    drift_inline,
    feature_gaps_inline,
    island_groups_inline,
    IslandRows,
    PgsSettings,
    RowImpulses,
    RowProblem,
    RowSettings,
    solve_pgs,
    solve_small_inline,
    speed_bounds_inline,
    StepSlip,
    stop_within_step_inline,
)
from feeder_sim.model.arrays import BodyArrays, ShapeArrays
from feeder_sim.model.vibration import DriveSegments, segment_motion

# what advance returns
DONE, REFERENCE, GROW = 0, 1, 2

# integer counters (``ints``), in SolverStats' names
(I_STEPS, I_LCP_SOLVES, I_TRIVIAL, I_PIVOTS, I_UNCONVERGED, I_IMPACTS, I_ISLANDS, I_PGS,
 I_LCP_ROWS, I_MAX_LCP_ROWS, I_SUBSTEPS) = range(11)
INT_COUNTERS = ('steps', 'lcp_solves', 'trivial_solves', 'pivots', 'unconverged', 'impacts',
                'islands', 'pgs_solves', 'lcp_rows', 'max_lcp_rows', 'substeps')
# float maxima (``floats``)
F_MAX_RESIDUAL, F_MAX_PENETRATION, F_MAX_PGS_VRES = range(3)
FLOAT_MAXIMA = ('max_residual', 'max_penetration_m', 'max_pgs_velocity_residual_mps')


class StepSettings(NamedTuple):
    """``TimeStepSettings`` and the scene's solver options (SI units)."""

    time_step_s: float
    touch_m: float
    projection_slop_m: float
    projection_reach: float
    slop_m: float
    push_out: float
    push_max_mps: float
    spec_depth: float          # speculative_depth x collision.DEPTH_FRACTION
    substep_share: float       # substep_depth x collision.DEPTH_FRACTION
    slip_tol_mps: float
    lcp_tol: float
    reuse_row_states: bool
    direct_max_rows: int
    pgs_tol_mps: float
    pgs_max_sweeps: int
    pgs_check: int
    pgs_omega: float
    pgs_momentum: bool
    friction_impulse: bool
    narrow: NarrowPhaseTolerances   # find_contacts' defaults; bp_margin_m holds only the
    #                                 broad phase's widening (2 param_tol x longest edge), the
    #                                 step adds its margin


class Warm(NamedTuple):
    """Impulses of the previous step by feature key ``vertex * n_vertices + edge``, sorted,
    and the row states each contact's small-island solve ended in (``solve_small``): its
    velocity solve's and the last position projection's it took part in (-1: none)."""

    keys: np.ndarray
    p_n: np.ndarray
    p_t: np.ndarray
    state: np.ndarray
    projection_state: np.ndarray


class Approach(NamedTuple):
    """``TimeStepper._approach``: the body pairs ``lo[p] < hi[p]`` a speculative row with
    restitution held back, and their velocities before the first such step: (vx, vy, omega)
    of ``lo[p]`` in row ``2 p`` of ``vel``, of ``hi[p]`` in row ``2 p + 1`` (m/s, rad/s)."""

    lo: np.ndarray      # (p,) int64
    hi: np.ndarray      # (p,) int64
    vel: np.ndarray     # (2 p, 3)


def no_approach() -> Approach:
    """An empty :class:`Approach`."""
    return Approach(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))


class Reports(NamedTuple):
    """Contacts and impulses of the steps taken, one row per kept contact, step after step."""

    body_a: np.ndarray
    piece_a: np.ndarray
    vertex_a: np.ndarray
    body_b: np.ndarray
    piece_b: np.ndarray
    edge_b: np.ndarray
    point: np.ndarray          # (cap, 2)
    normal: np.ndarray         # (cap, 2)
    gap: np.ndarray
    edge_param: np.ndarray
    tangent: np.ndarray        # (cap, 2)
    r_a: np.ndarray            # (cap, 2)
    r_b: np.ndarray            # (cap, 2)
    mu_static: np.ndarray
    mu_dynamic: np.ndarray
    restitution: np.ndarray
    normal_impulse: np.ndarray
    tangent_impulse: np.ndarray
    step_end: np.ndarray       # (cap,) row count after each step with contacts
    counts: np.ndarray         # (2,) rows and steps written


def new_reports(capacity: int) -> Reports:
    """Empty report buffers for ``capacity`` contact rows."""
    i, f, v = (lambda: np.zeros(capacity, np.int64)), (lambda: np.zeros(capacity)), (
        lambda: np.zeros((capacity, 2)))
    return Reports(i(), i(), i(), i(), i(), i(), v(), v(), f(), f(), v(), v(), v(), f(), f(), f(),
                   f(), f(), i(), np.zeros(2, np.int64))


# ------------------------------------------------------------------------------ helpers
@inner
def _larger(a, b):
    """Python's ``max(a, b)``: ``b`` only when it is strictly larger (NaN never wins)."""
    return b if b > a else a


@inner
def _pairwise_sum(x, lo, n):
    """``numpy``'s pairwise summation of ``x[lo:lo + n]`` (its ``add`` reduction)."""
    if n < 8:
        r = 0.0
        for i in range(lo, lo + n):
            r += x[i]
        return r
    if n <= 128:
        r0, r1, r2, r3 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3]
        r4, r5, r6, r7 = x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
        i = 8
        while i < n - n % 8:
            r0 += x[lo + i]
            r1 += x[lo + i + 1]
            r2 += x[lo + i + 2]
            r3 += x[lo + i + 3]
            r4 += x[lo + i + 4]
            r5 += x[lo + i + 5]
            r6 += x[lo + i + 6]
            r7 += x[lo + i + 7]
            i += 8
        r = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            r += x[lo + i]
            i += 1
        return r
    half = n // 2
    half -= half % 8
    return _pairwise_sum(x, lo, half) + _pairwise_sum(x, lo + half, n - half)


@inner
def _segment_sum(x, lo, hi):
    """``np.add.reduceat``'s sum of a non-empty segment: the first value, then the rest
    summed pairwise."""
    if hi - lo == 1:
        return x[lo]
    return x[lo] + _pairwise_sum(x, lo + 1, hi - lo - 1)


@inner
def _prescribed(t, drives, driven_idx, position, velocity):
    """``World.apply_prescribed_motion``: driven bodies' positions and velocities at t."""
    for row in range(driven_idx.shape[0]):
        i = driven_idx[row]
        d, v, _ = segment_motion(t, drives, row)
        for j in range(2):
            u = drives.direction[row, j]
            position[i, j] = drives.base_m[row, j] + d * u
            velocity[i, j] = v * u


@inner(machine_inline=True)
def _world_shapes(ar, shapes, position, angle):
    """World vertices and edge normals ((nv, 2) each) and the pieces' bounding boxes
    (lo, hi: (n_pieces, 2)) at these poses."""
    nv = shapes.vertices.shape[0]
    n = position.shape[0]
    cos = empty_f(ar, n)
    sin = empty_f(ar, n)
    for i in range(n):
        cos[i] = math.cos(angle[i])
        sin[i] = math.sin(angle[i])
    w = empty_f2(ar, nv, 2)
    nw = empty_f2(ar, nv, 2)
    for k in range(nv):
        i = shapes.vertex_body[k]
        c, s = cos[i], sin[i]
        x, y = shapes.vertices[k, 0], shapes.vertices[k, 1]
        w[k, 0] = position[i, 0] + (c * x - s * y)
        w[k, 1] = position[i, 1] + (s * x + c * y)
        x, y = shapes.normals[k, 0], shapes.normals[k, 1]
        nw[k, 0] = c * x - s * y
        nw[k, 1] = s * x + c * y
    n_p = shapes.piece_body.shape[0]
    lo = empty_f2(ar, n_p, 2)
    hi = empty_f2(ar, n_p, 2)
    for p in range(n_p):
        for j in range(2):
            a = w[shapes.piece_start[p], j]
            b = a
            for k in range(shapes.piece_start[p] + 1, shapes.piece_start[p + 1]):
                a = min(a, w[k, j])
                b = max(b, w[k, j])
            lo[p, j] = a
            hi[p, j] = b
    return w, nw, lo, hi


@inner
def _separation(w, nw, a0, a1, b0, b1):
    """The largest separation of two convex pieces (vertex ranges ``a0:a1``, ``b0:b1``) along
    an edge normal of either (m; negative: overlapping at least that deep along every one),
    the unit axis, and True when it is an edge normal of the first piece (pointing from it
    to the second). It never exceeds their distance."""
    best, nx, ny, own = -np.inf, 0.0, 1.0, True
    for first in (True, False):
        e0, e1, v0, v1 = (a0, a1, b0, b1) if first else (b0, b1, a0, a1)
        for k in range(e0, e1):
            low = np.inf
            for j in range(v0, v1):
                low = min(low, nw[k, 0] * (w[j, 0] - w[k, 0]) + nw[k, 1] * (w[j, 1] - w[k, 1]))
            if low > best:
                best, nx, ny, own = low, nw[k, 0], nw[k, 1], first
    return best, nx, ny, own


@inner(machine_inline=True)
def safe_step_inline(ar, h, pos, ang, vel, om, bodies, shapes, drives, st):
    """The longest step up to ``h`` (s) in which no vertex can move more than the allowance
    ``st.substep_share`` x the thinner piece's width (half the narrow phase's depth window at
    the default) relative to a piece it is about to meet, in half a step: deeper, the
    midpoint's contact search can match it to the far face of a thin body, or miss it, and a
    contact that closes within a step acts from up to half a step's approach away.

    Conservative advancement over piece pairs: each pair's points close at most at ``c``, the
    pair's relative speed bound (``|v_a - v_b| + |omega_a| r_a + |omega_b| r_b`` plus what
    gravity and the drives add within the step), or, for pieces already touching, only its
    component along their separating axis. A pair apart by ``d`` may take ``d / (1.5 c)``
    (it cannot close, or reach the next midpoint's search, within the step); a touching or
    nearly touching one ``2 allowance / c``. Slow scenes never get past the first test, so
    their steps are the scheme's own."""
    dynamic = bodies.dynamic
    v_dyn, v_other, _, closing = speed_bounds_inline(vel, om, bodies.radius_m, dynamic)
    a_kin = 0.0
    for row in range(drives.omega_rad_s.shape[0]):
        w_d, amplitude = drives.omega_rad_s[row], drives.amplitude_m[row]
        v_other = _larger(v_other, 2.0 * w_d * amplitude)
        a_kin = _larger(a_kin, 2.0 * w_d * w_d * amplitude)
    accel = (bodies.g + a_kin) * h
    c_all = _larger(v_dyn + v_other, closing) + accel
    n_p = shapes.piece_body.shape[0]
    thinnest = np.inf
    for p in range(n_p):
        thinnest = min(thinnest, shapes.piece_width[p])
    # NaN speeds pass here: the step refuses them itself
    if not 0.5 * h * c_all > st.substep_share * thinnest:
        return h
    w, nw, lo, hi = _world_shapes(ar, shapes, pos, ang)
    slack = 10.0 * st.touch_m
    reach = 1.5 * h * c_all + slack
    key = empty_f(ar, n_p)
    for p in range(n_p):
        key[p] = lo[p, 0]
    order = _argsort(ar, key)
    safe = h
    for ii in range(n_p):
        p = order[ii]
        for jj in range(ii + 1, n_p):
            q = order[jj]
            if lo[q, 0] > hi[p, 0] + reach:
                break
            a, b = shapes.piece_body[p], shapes.piece_body[q]
            if a == b or not (dynamic[a] or dynamic[b]):
                continue
            if lo[p, 1] > hi[q, 1] + reach or lo[q, 1] > hi[p, 1] + reach:
                continue
            allow = st.substep_share * min(shapes.piece_width[p], shapes.piece_width[q])
            spin = abs(om[a]) * bodies.radius_m[a] + abs(om[b]) * bodies.radius_m[b]
            dvx, dvy = vel[b, 0] - vel[a, 0], vel[b, 1] - vel[a, 1]
            c = math.hypot(dvx, dvy) + spin + accel
            if not 0.5 * h * c > allow:
                continue
            sep, nx, ny, own = _separation(w, nw, shapes.piece_start[p],
                                           shapes.piece_start[p + 1], shapes.piece_start[q],
                                           shapes.piece_start[q + 1])
            if sep > slack:
                if sep >= 1.5 * h * c:
                    continue
                cut = max(sep / (1.5 * c), 2.0 * allow / c)
            else:
                # touching: they go deeper only along the axis they are separated on
                approach = -(nx * dvx + ny * dvy) if own else nx * dvx + ny * dvy
                c = max(approach, 0.0) + spin + accel
                if not 0.5 * h * c > allow:
                    continue
                cut = 2.0 * allow / c
            safe = min(safe, cut)
    return safe


safe_step = for_python(safe_step_inline)


@inner(machine_inline=True)
def _find_contacts(ar, shapes, position, angle, dynamic, margin, narrow):
    """``collision.find_contacts(shapes, position, angle, dynamic, margin=margin)``: the
    kept contacts' (vertex, edge, gap, edge_param, world vertices, world normals)."""
    n = position.shape[0]
    nv = shapes.vertices.shape[0]
    n_p = shapes.piece_body.shape[0]
    w, nw, lo, hi = _world_shapes(ar, shapes, position, angle)
    take = full_b(ar, n_p, True)
    dyn = empty_b(ar, n_p)
    any_dyn = False
    for p in range(n_p):
        dyn[p] = dynamic[shapes.piece_body[p]]
        any_dyn = any_dyn or dyn[p]
    none_i = empty_i(ar, 0)
    none_f = empty_f(ar, 0)
    finite = True
    for p in range(n_p):
        for j in range(2):
            finite = finite and lo[p, j] - lo[p, j] == 0.0 and hi[p, j] - hi[p, j] == 0.0
    if not finite:
        # find_contacts refuses non-finite bounds: the reference step raises its error
        return none_i, none_i, none_f, none_f, w, nw, False
    if n_p < 2 or not any_dyn:
        return none_i, none_i, none_f, none_f, w, nw, True
    coord = empty_f(ar, n)
    for i in range(n):
        coord[i] = max(abs(position[i, 0]), abs(position[i, 1]))
    vert, edge, gap, t, _ = narrow_phase_inline(
        ar, w, nw, lo, hi, shapes.piece_start, shapes.piece_body, take, dyn, shapes.piece_width,
        coord, shapes.piece_radius, shapes.vertex_active, shapes.edge_internal,
        shapes.next_vertex, shapes.prev_vertex, shapes.edge_length,
        NarrowPhaseTolerances(margin + narrow.bp_margin_m, margin, narrow.depth_m,
                              narrow.depth_fraction, narrow.tie_rel, narrow.param_tol,
                              narrow.angle_tol))
    if vert.shape[0] == 0:
        return none_i, none_i, none_f, none_f, w, nw, True
    o = clean_contacts_inline(ar, vert, edge, gap, t, shapes.cover_start, shapes.cover_lo,
                              shapes.cover_hi, shapes.next_vertex, shapes.vertex_canon,
                              shapes.vertex_body, nw, nv, shapes.n_piece_bodies,
                              narrow.param_tol, narrow.angle_tol)
    return (gather(ar, vert, o), gather(ar, edge, o), gather(ar, gap, o), gather(ar, t, o), w, nw,
            True)


@inner
def _nan_max(x, sel):
    """``x[sel].max()`` as numpy gives it (NaN wins); -inf when nothing is selected."""
    m = -np.inf
    for i in range(x.shape[0]):
        if sel[i]:
            if x[i] != x[i]:
                return x[i]
            m = max(m, x[i])
    return m


@inner
def _warm_find(ar, warm, keys):
    """Where these features are among the previous step's (``_Warm.lookup``), -1 where new."""
    k = keys.shape[0]
    at = full_i(ar, k, -1)
    size = warm.keys.shape[0]
    if size == 0:
        return at
    for q in range(k):
        lo, hi = 0, size
        while lo < hi:       # searchsorted, side='left'
            mid = (lo + hi) // 2
            if warm.keys[mid] < keys[q]:
                lo = mid + 1
            else:
                hi = mid
        pos = min(lo, size - 1)
        if warm.keys[pos] == keys[q]:
            at[q] = pos
    return at


@inner
def _heights(ar, point, order, gravity):
    """The contact points in ``order`` along -gravity (m times |g|: an order, not a
    length; all 0 without gravity)."""
    out = empty_f(ar, order.shape[0])
    for q in range(order.shape[0]):
        out[q] = -(point[order[q], 0] * gravity[0] + point[order[q], 1] * gravity[1])
    return out


@inner
def _record_batch(ints, floats, sel, rows, work, res, converged):
    """``SolverStats.record_batch`` of the islands with ``sel``."""
    n = 0
    n_conv = 0
    rows_sum = 0
    rows_max = 0
    work_sum = 0
    for i in range(sel.shape[0]):
        if sel[i]:
            n += 1
            n_conv += converged[i]
            rows_sum += rows[i]
            rows_max = max(rows_max, rows[i])
            work_sum += work[i]
    if n == 0:
        return
    ints[I_LCP_SOLVES] += n
    ints[I_LCP_ROWS] += rows_sum
    ints[I_MAX_LCP_ROWS] = max(ints[I_MAX_LCP_ROWS], rows_max)
    ints[I_PIVOTS] += work_sum
    ints[I_UNCONVERGED] += n - n_conv
    floats[F_MAX_RESIDUAL] = _larger(floats[F_MAX_RESIDUAL], _nan_max(res, sel))


@inner(machine_inline=True)
def _solve(ar, n_bodies, rows, bodies, problem, mu_s, mu_d, slip, colliding, half_vel, half_om,
           at, point, order, todo, warm, st, ints, floats, msgs, n_msgs):
    """``TimeStepper._solve`` (``rows`` an :class:`IslandRows`, ``problem`` a
    :class:`RowProblem`, arrays in island order; ``at``: each contact's place in the
    previous step's ``warm``, -1 where new; ``point``: the contact points in the step's
    order, which ``order`` maps to island order; PGS sweeps a pile bottom-up by them): the
    impulses and the row states of the small
    islands' answers, or ``ok`` False where the compiled Dantzig missed ``lcp_tol`` (the
    reference step takes over). ``slip``: the pre-step slip of each contact (m/s), and
    ``half_vel`` / ``half_om`` the bodies' free velocities at mid-step, for
    ``stop_within_step`` and ``breakaway_within_step`` (not in an island with a
    ``colliding`` contact: an impact's impulse is not spread over the step)."""
    starts, a = rows.starts, rows.a
    b_n, b_t, box, mu_lo, mu_hi = problem
    k = a.shape[0]
    n_isl = starts.shape[0] - 1
    lens = empty_i(ar, n_isl)
    n_rows = empty_i(ar, n_isl)
    isl = empty_i(ar, k)
    small = full_b(ar, n_isl, False)
    large = full_b(ar, n_isl, False)
    any_large = False
    for i in range(n_isl):
        lens[i] = starts[i + 1] - starts[i]
        nbox = 0
        for q in range(starts[i], starts[i + 1]):
            isl[q] = i
            nbox += box[q]
        n_rows[i] = lens[i] + nbox
        small[i] = todo[i] and n_rows[i] <= st.direct_max_rows
        large[i] = todo[i] and not small[i]
        any_large = any_large or large[i]
    # the order PGS sweeps a pile in: bottom-up; nothing to sort without a pile
    height = _heights(ar, point, order, bodies.gravity) if any_large else empty_f(ar, 0)
    # the friction law over the step is for smooth contact: an island with an impact keeps
    # Kawachi's impact law (its normal impulses move between the first answer and the next)
    steady = empty_b(ar, n_isl)
    for i in range(n_isl):
        steady[i] = small[i]
    for q in range(k):
        if colliding[q]:
            steady[isl[q]] = False
    may_slide = empty_b(ar, k)
    sliding = empty_b(ar, k)
    any_slide = False
    any_sliding = False
    for q in range(k):
        may_slide[q] = box[q] and mu_d[q] < mu_s[q]
        any_slide = any_slide or may_slide[q]
        # friction_rows gives a contact sliding into the step one-sided bounds
        sliding[q] = box[q] and mu_lo[q] != mu_hi[q] and steady[isl[q]]
        any_sliding = any_sliding or sliding[q]
    states_in = empty_i(ar, k)
    x_n, x_t = zeros_f(ar, k), zeros_f(ar, k)
    for q in range(k):
        states_in[q] = warm.state[at[q]] if at[q] >= 0 and st.reuse_row_states else -1
        if any_large and at[q] >= 0 and todo[isl[q]]:
            # PGS starts from the previous step's impulses (Dantzig from scratch)
            x_n[q] = warm.p_n[at[q]]
            x_t[q] = warm.p_t[at[q]]
    states = full_i(ar, k, -1)
    lo = copy_f(ar, mu_lo)
    hi = copy_f(ar, mu_hi)
    v_t_new = zeros_f(ar, k)
    ones = full_b(ar, n_isl, True)
    offset = zeros_f(ar, k)
    v_t_end = copy_f(ar, b_t)       # the free end slip, before a stop's impulse shifts b_t
    remain = empty_f(ar, k)
    for q in range(k):
        remain[q] = 1.0
    # the bounds as the passes below narrow them, the answers, the slip within the step
    bounded = RowProblem(b_n, b_t, box, lo, hi)
    out = RowImpulses(x_n, x_t, v_t_new)
    slip_state = StepSlip(slip, sliding, half_vel, half_om, v_t_end, mu_s, mu_d, offset, remain)
    pgs = PgsSettings(st.pgs_tol_mps, st.pgs_max_sweeps, st.pgs_check, st.pgs_omega,
                      st.pgs_momentum)
    for attempt in range(3):
        if small.any():
            res, work, codes = solve_small_inline(ar, small, rows, bounded, out, states_in,
                                                  states)
            for i in range(n_isl):
                if small[i] and res[i] > st.lcp_tol:
                    return x_n, x_t, states, False
            _record_batch(ints, floats, small, n_rows, work, res, ones)
        if large.any():
            res, vres, work = solve_pgs(ar, large, rows, bounded, out,
                                        zeros_f2(ar, n_bodies, 3), pgs, height)
            conv = empty_b(ar, n_isl)
            for i in range(n_isl):
                conv[i] = vres[i] <= st.pgs_tol_mps
            _record_batch(ints, floats, large, n_rows, work, res, conv)
            n_large = 0
            for i in range(n_isl):
                if large[i]:
                    n_large += 1
                    if not conv[i] and n_msgs[0] < msgs.shape[0]:
                        m = n_msgs[0]
                        msgs[m, 0], msgs[m, 1] = vres[i], res[i]
                        msgs[m, 2], msgs[m, 3] = work[i], n_rows[i]
                        n_msgs[0] += 1
            ints[I_PGS] += n_large
            floats[F_MAX_PGS_VRES] = _larger(floats[F_MAX_PGS_VRES], _nan_max(vres, large))
        if attempt == 2:
            break
        # a slip that stops within the step (small islands, first answer only)
        if attempt == 0 and any_sliding:
            redo = stop_within_step_inline(ar, small, rows, bounded, out, slip_state)
        else:
            redo = full_b(ar, n_isl, False)
        # dynamics.second_pass: after the first answer on the bounds friction_rows set, after
        # the second on the contacts that stopped within the step
        any_saturated = False
        if any_slide:
            for q in range(k):
                i = isl[q]
                if not (may_slide[q] and x_n[q] > 0 and (small[i] or large[i])):
                    continue
                if (remain[q] < 1.0) != (attempt == 1):
                    continue
                limit_lo = x_t[q] <= -lo[q] * x_n[q] * (1 - 1e-9)
                limit_hi = x_t[q] >= hi[q] * x_n[q] * (1 - 1e-9)
                v = v_t_new[q]
                if lo[q] == hi[q]:
                    if lo[q] > 0 and (limit_lo or limit_hi) and abs(v) > st.slip_tol_mps:
                        lo[q] = mu_d[q] * remain[q] if v > 0 else 0.0
                        hi[q] = mu_d[q] * remain[q] if v < 0 else 0.0
                        redo[i] = True
                elif hi[q] == mu_s[q] and hi[q] > 0 and limit_hi and v < -st.slip_tol_mps:
                    hi[q] = 0.0
                    redo[i] = True
                elif lo[q] == mu_s[q] and lo[q] > 0 and limit_lo and v > st.slip_tol_mps:
                    lo[q] = 0.0
                    redo[i] = True
        # a static contact that holds on average but not throughout its part of the step
        if any_sliding or attempt == 0:
            for i in range(n_isl):
                steady[i] = steady[i] and small[i]
            late = breakaway_within_step_inline(ar, steady, rows, bounded, out, slip_state,
                                                attempt == 1)
            for i in range(n_isl):
                redo[i] = redo[i] or late[i]
        for i in range(n_isl):
            any_saturated = any_saturated or redo[i]
        if not any_saturated:
            break
        for i in range(n_isl):
            small[i] = small[i] and redo[i]
            large[i] = large[i] and redo[i]
    for q in range(k):
        if offset[q] != 0.0:
            x_t[q] = x_t[q] + offset[q]
    return x_n, x_t, states, True


@inner
def _pair_index(approach, a, b):
    """Index of the body pair (a, b) in ``approach``, -1 if it is not there."""
    lo, hi = min(a, b), max(a, b)
    for p in range(approach.lo.shape[0]):
        if approach.lo[p] == lo and approach.hi[p] == hi:
            return p
    return -1


@inner
def _restore_approach(approach, a, b, normal, r_a, r_b, rest, newton, vel, om, b_n):
    """``TimeStepper._restore_approach``, in place on ``b_n``: a Newton row (``newton``) of a
    pair held back before bounces the normal velocity the pair came in with."""
    for q in range(a.shape[0]):
        if not newton[q]:
            continue
        p = _pair_index(approach, a[q], b[q])
        if p < 0:
            continue
        nx, ny = normal[q, 0], normal[q, 1]
        v_now = _contact_velocity(q, a[q], b[q], nx, ny, r_a, r_b, vel, om)[0]
        # the same contact with the pair's kept velocities (rows 2p: lower body, 2p + 1)
        ka = 2 * p + (0 if a[q] < b[q] else 1)
        came_in = _contact_velocity(q, ka, 4 * p + 1 - ka, nx, ny, r_a, r_b,
                                    approach.vel[:, :2], approach.vel[:, 2])[0]
        lowest = came_in if came_in < v_now or came_in != came_in else v_now
        lowest = lowest if lowest < 0.0 or lowest != lowest else 0.0
        now = v_now if v_now < 0.0 or v_now != v_now else 0.0
        b_n[q] = b_n[q] + rest[q] * (lowest - now)


@inner
def _held_back(ar, approach, a, b, held, vel, om):
    """``TimeStepper._held_back``: the pairs of the ``held`` contacts, each with the
    velocities ``approach`` kept for it, or the step's starting ones."""
    m = a.shape[0]
    lo = empty_i(ar, m)
    hi = empty_i(ar, m)
    pv = empty_f2(ar, 2 * m, 3)
    n_pairs = 0
    for q in range(m):
        if not held[q]:
            continue
        x, y = min(a[q], b[q]), max(a[q], b[q])
        seen = False
        for p in range(n_pairs):
            seen = seen or (lo[p] == x and hi[p] == y)
        if seen:
            continue
        lo[n_pairs], hi[n_pairs] = x, y
        old = _pair_index(approach, x, y)
        for side in range(2):
            r, i = 2 * n_pairs + side, y if side else x
            for j in range(3):
                if old >= 0:
                    pv[r, j] = approach.vel[2 * old + side, j]
                else:
                    pv[r, j] = vel[i, j] if j < 2 else om[i]
        n_pairs += 1
    return Approach(lo[:n_pairs], hi[:n_pairs], pv[:2 * n_pairs])


@inner(machine_inline=True)
def _step(ar, h, t0, pos, ang, vel, om, bodies, shapes, drives, st, warm, approach, ints, floats,
          rep, msgs, n_msgs):
    """One ``TimeStepper.step`` of ``h`` from ``t0``: ``(code, warm, approach)``; the state,
    the counters and the reports are written only when the step is taken (``DONE``)."""
    n = pos.shape[0]
    dynamic, dyn_idx = bodies.dynamic, bodies.dyn_idx
    half = 0.5 * h
    mid_pos = copy_f2(ar, pos)
    mid_ang = copy_f(ar, ang)
    mid_vel = copy_f2(ar, vel)
    drift_inline(dyn_idx, pos, ang, vel, om, half, mid_pos, mid_ang)
    _prescribed(t0 + 0.5 * h, drives, bodies.driven_idx, mid_pos, mid_vel)
    # free end-of-step velocities; driven bodies' positions and velocities at t0 + h
    end_pos = copy_f2(ar, mid_pos)
    end_vel = copy_f2(ar, mid_vel)
    end_om = copy_f(ar, om)
    for i in range(n):
        if dynamic[i]:
            for j in range(2):
                end_vel[i, j] = end_vel[i, j] + h * bodies.gravity[j]
    _prescribed(t0 + h, drives, bodies.driven_idx, end_pos, end_vel)

    # TimeStepper.margin
    v_max, v_kin, spin, closing = speed_bounds_inline(vel, om, bodies.radius_m, dynamic)
    for row in range(bodies.driven_idx.shape[0]):
        v_kin = _larger(v_kin, drives.omega_rad_s[row] * drives.amplitude_m[row] * 2)
    g = bodies.g
    slack = 10 * st.touch_m
    base = 1.5 * h * (v_max + v_kin + g * h) + slack
    margin = 1.5 * h * (_larger(v_max + v_kin, closing) + g * h) + slack

    vert, edge, gap, param, w, nw, finite = _find_contacts(ar, shapes, mid_pos, mid_ang, dynamic,
                                                           margin, st.narrow)
    if not finite:
        return REFERENCE, warm, approach
    k = vert.shape[0]
    if k and margin > base:
        # TimeStepper._within_reach
        far = False
        for q in range(k):
            far = far or gap[q] > base
        if far:
            sel = empty_i(ar, k)
            m = 0
            for q in range(k):
                ia = shapes.vertex_body[vert[q]]
                ib = shapes.vertex_body[edge[q]]
                dx, dy = vel[ia, 0] - vel[ib, 0], vel[ia, 1] - vel[ib, 1]
                close = (math.hypot(dx, dy) + abs(om[ia]) * bodies.radius_m[ia]
                         + abs(om[ib]) * bodies.radius_m[ib])
                reach = 1.5 * h * (close + g * h) + 10 * st.touch_m
                if not gap[q] > base or (dynamic[ia] and dynamic[ib] and gap[q] <= reach):
                    sel[m] = q
                    m += 1
            sel = sel[:m]
            vert, edge, gap, param = (gather(ar, vert, sel), gather(ar, edge, sel),
                                      gather(ar, gap, sel), gather(ar, param, sel))
            k = m

    new_pos = copy_f2(ar, pos)
    new_ang = copy_f(ar, ang)
    new_vel = copy_f2(ar, vel)
    new_om = copy_f(ar, om)
    step_ints = full_i(ar, ints.shape[0], 0)
    step_floats = copy_f(ar, floats)
    step_msgs = copy_i(ar, n_msgs)
    projected = full_b(ar, 0, False)
    m = 0
    if k:
        # TimeStepper._contacts
        body_a = gather(ar, shapes.vertex_body, vert)
        body_b = gather(ar, shapes.vertex_body, edge)
        piece_a = gather(ar, shapes.vertex_piece, vert)
        piece_b = gather(ar, shapes.vertex_piece, edge)
        point = gather_rows(ar, w, vert)
        normal = gather_rows(ar, nw, edge)
        slip_tol = _larger(st.slip_tol_mps, h * spin)
        settings = RowSettings(h, st.touch_m, st.direct_max_rows, st.push_out, st.push_max_mps,
                               st.slop_m, -2.0 * g * h, slip_tol, st.friction_impulse,
                               st.spec_depth, margin)
        # a part hopping over the track or passing near another finds contacts that all stay
        # apart (a third of the steps of one part conveying). With 2 k <= max_rows no island
        # is a pile, so then none gets a row and the step builds no islands
        if 2 * k > st.direct_max_rows or any_kept_inline(
                ar, body_a, body_b, point, normal, gap, mid_pos, end_vel, end_om, piece_a,
                piece_b, shapes.piece_width, settings):
            order, starts, isl_bodies, body_starts = island_groups_inline(ar, n, dynamic,
                                                                          body_a, body_b)
            (keep, tangent, r_a, r_b, mu_s, mu_d, rest, v_n_free, v_t_free, v_t_pre, pile,
             colliding, b_n, box, mu_lo, mu_hi, gap_min) = contact_rows_inline(
                ar, body_a, body_b, point, normal, gap, order, starts, mid_pos, end_vel, end_om,
                vel, om, bodies.mu_static, bodies.mu_dynamic, bodies.restitution, piece_a,
                piece_b, shapes.piece_width, settings)
            m = keep.shape[0]
    n_spare = 0
    if m:
        rows0, steps0 = rep.counts[0], rep.counts[1]
        if rows0 + m > rep.gap.shape[0] or steps0 + 1 > rep.step_end.shape[0]:
            return GROW, warm, approach
        spare = full_b(ar, k, True)
        for q in range(m):
            spare[keep[q]] = False
        if m < k:
            left_out = _where(ar, spare)
            body_a, body_b = gather(ar, body_a, keep), gather(ar, body_b, keep)
            s_vert, s_edge = gather(ar, vert, left_out), gather(ar, edge, left_out)
            s_point, s_normal = gather_rows(ar, point, left_out), gather_rows(ar, normal, left_out)
            s_a = gather(ar, shapes.vertex_body, s_vert)
            s_b = gather(ar, shapes.vertex_body, s_edge)
            vert, edge = gather(ar, vert, keep), gather(ar, edge, keep)
            piece_a, piece_b = gather(ar, piece_a, keep), gather(ar, piece_b, keep)
            point, normal = gather_rows(ar, point, keep), gather_rows(ar, normal, keep)
            gap, param = gather(ar, gap, keep), gather(ar, param, keep)
            order, starts, isl_bodies, body_starts = island_groups_inline(ar, n, dynamic,
                                                                          body_a, body_b)
            n_spare = k - m
        step_floats[F_MAX_PENETRATION] = _larger(step_floats[F_MAX_PENETRATION], -gap_min)
        projected = empty_b(ar, m)
        any_pile = False
        for q in range(m):
            projected[q] = not pile[q]
            any_pile = any_pile or pile[q]
        if n_spare and any_pile:
            # TimeStepper._outside_piles: piles are not projected
            in_pile = full_b(ar, n, False)
            for q in range(m):
                if pile[q]:
                    in_pile[body_a[q]] = True
                    in_pile[body_b[q]] = True
            ok = empty_i(ar, n_spare)
            n_ok = 0
            for q in range(n_spare):
                if not ((in_pile[s_a[q]] and dynamic[s_a[q]])
                        or (in_pile[s_b[q]] and dynamic[s_b[q]])):
                    ok[n_ok] = q
                    n_ok += 1
            ok = ok[:n_ok]
            s_vert, s_edge = gather(ar, s_vert, ok), gather(ar, s_edge, ok)
            s_point, s_normal = gather_rows(ar, s_point, ok), gather_rows(ar, s_normal, ok)
            s_a, s_b = gather(ar, s_a, ok), gather(ar, s_b, ok)
            n_spare = n_ok
        nv = shapes.vertices.shape[0]
        keys = empty_i(ar, m)
        for q in range(m):
            keys[q] = vert[q] * nv + edge[q]
        at = _warm_find(ar, warm, keys)
        p_n = zeros_f(ar, m)
        p_t = zeros_f(ar, m)
        p_state = full_i(ar, m, -1)
        bouncy = False
        for q in range(m):
            bouncy = bouncy or rest[q] > 0.0
        spec = empty_b(ar, m if bouncy else 0)
        newton = empty_b(ar, m if bouncy else 0)
        if bouncy:
            # speculative rows: neither a pile's nor a Newton row (the kernel's index set)
            for q in range(m):
                spec[q] = (not pile[q] and gap[q] > st.touch_m
                           and gap[q] + 0.5 * h * v_n_free[q] > st.touch_m)
                newton[q] = not pile[q] and not spec[q] and rest[q] > 0.0
            if approach.lo.shape[0]:
                _restore_approach(approach, body_a, body_b, normal, r_a, r_b, rest, newton,
                                  vel, om, b_n)
        n_isl = starts.shape[0] - 1
        step_ints[I_ISLANDS] += n_isl
        # an island whose normal rows all have b >= 0 is answered by zero impulses
        b_no = gather(ar, b_n, order)
        neg = full_b(ar, n_isl, False)
        n_neg = 0
        for i in range(n_isl):
            lo_v = b_no[starts[i]]
            for q in range(starts[i] + 1, starts[i + 1]):
                x = b_no[q]
                lo_v = x if x < lo_v or x != x else lo_v   # np.minimum (NaN wins)
            neg[i] = lo_v < 0.0
            n_neg += neg[i]
        step_ints[I_LCP_SOLVES] += n_isl - n_neg
        step_ints[I_TRIVIAL] += n_isl - n_neg
        a_o, b_o = gather(ar, body_a, order), gather(ar, body_b, order)
        normal_o, tangent_o = gather_rows(ar, normal, order), gather_rows(ar, tangent, order)
        r_a_o, r_b_o = gather_rows(ar, r_a, order), gather_rows(ar, r_b, order)
        if n_neg:
            # the bodies' free velocities at mid-step (the friction law's time course)
            half_vel = copy_f2(ar, mid_vel)
            for i in range(n):
                if dynamic[i]:
                    for j in range(2):
                        half_vel[i, j] = half_vel[i, j] + half * bodies.gravity[j]
            island_rows = IslandRows(starts, a_o, b_o, normal_o, tangent_o, r_a_o, r_b_o,
                                     bodies.inv_mass, bodies.inv_inertia)
            problem = RowProblem(b_no, gather(ar, v_t_free, order), gather(ar, box, order),
                                 gather(ar, mu_lo, order), gather(ar, mu_hi, order))
            x_n, x_t, states, ok_solve = _solve(
                ar, n, island_rows, bodies, problem, gather(ar, mu_s, order),
                gather(ar, mu_d, order), gather(ar, v_t_pre, order),
                gather(ar, colliding, order), half_vel, om, gather(ar, at, order), point, order,
                neg, warm, st, step_ints, step_floats, msgs, step_msgs)
            if not ok_solve:
                return REFERENCE, warm, approach
            for q in range(m):
                p_n[order[q]] = x_n[q]
                p_t[order[q]] = x_t[q]
                p_state[order[q]] = states[q]
            dv = zeros_f2(ar, n, 3)
            # (in the step's contact order: no island's start is read)
            apply_impulses_inline(ar, dv, IslandRows(starts, body_a, body_b, normal, tangent,
                                                     r_a, r_b, bodies.inv_mass,
                                                     bodies.inv_inertia), p_n, p_t)
            for i in range(n):
                if dynamic[i]:
                    end_vel[i, 0] = end_vel[i, 0] + dv[i, 0]
                    end_vel[i, 1] = end_vel[i, 1] + dv[i, 1]
                    end_om[i] = end_om[i] + dv[i, 2]
        for q in range(m):
            step_ints[I_IMPACTS] += colliding[q] and p_n[q] > 0
        if bouncy:
            held = empty_b(ar, m)
            for q in range(m):
                held[q] = spec[q] and rest[q] > 0.0 and p_n[q] > 0.0
            new_approach = _held_back(ar, approach, body_a, body_b, held, vel, om)
        else:
            new_approach = Approach(empty_i(ar, 0), empty_i(ar, 0), empty_f2(ar, 0, 3))
        # a contact carries its projection's row states on until it is projected again
        proj_state = full_i(ar, m, -1)
        for q in range(m):
            if at[q] >= 0:
                proj_state[q] = warm.projection_state[at[q]]
        o = _argsort_int(ar, keys)
        new_warm = Warm(gather(ar, keys, o), gather(ar, p_n, o), gather(ar, p_t, o),
                        gather(ar, p_state, o), gather(ar, proj_state, o))
    else:
        # carried on unchanged, into this step's arena: the one they live in is reset by the
        # step after next
        new_warm = Warm(copy_i(ar, warm.keys), copy_f(ar, warm.p_n), copy_f(ar, warm.p_t),
                        copy_i(ar, warm.state), copy_i(ar, warm.projection_state))
        new_approach = Approach(copy_i(ar, approach.lo), copy_i(ar, approach.hi),
                                copy_f2(ar, approach.vel))

    # the second half step
    drift_inline(dyn_idx, mid_pos, mid_ang, end_vel, end_om, half, new_pos, new_ang)
    for i in range(n):
        if dynamic[i]:
            new_vel[i, 0] = end_vel[i, 0]
            new_vel[i, 1] = end_vel[i, 1]
            new_om[i] = end_om[i]
    for row in range(bodies.driven_idx.shape[0]):
        i = bodies.driven_idx[row]
        for j in range(2):
            new_pos[i, j] = end_pos[i, j]
            new_vel[i, j] = end_vel[i, j]

    if m and projected.any():
        # TimeStepper._project: positions out along the contact normals
        cos = empty_f(ar, n)
        sin = empty_f(ar, n)
        for i in range(n):
            cos[i] = math.cos(new_ang[i])
            sin[i] = math.sin(new_ang[i])
        idx = _where(ar, projected)
        gap_end = zeros_f(ar, m)
        got = feature_gaps_inline(ar, idx, vert, edge, shapes.vertices, shapes.normals,
                                  shapes.vertex_body, new_pos, cos, sin)
        deep_any = False
        for q in range(idx.shape[0]):
            gap_end[idx[q]] = got[q]
            deep_any = deep_any or got[q] < -st.projection_slop_m
        if deep_any:
            if n_spare:
                # TimeStepper._with_spare: the contacts left out of the velocity solve too
                kk = m + n_spare
                c_a = concat(ar, body_a, s_a)
                c_b = concat(ar, body_b, s_b)
                c_vert = concat(ar, vert, s_vert)
                c_edge = concat(ar, edge, s_edge)
                c_normal = empty_f2(ar, kk, 2)
                c_tangent = empty_f2(ar, kk, 2)
                c_ra = empty_f2(ar, kk, 2)
                c_rb = empty_f2(ar, kk, 2)
                for q in range(kk):
                    for j in range(2):
                        if q < m:
                            c_normal[q, j] = normal[q, j]
                            c_tangent[q, j] = tangent[q, j]
                            c_ra[q, j] = r_a[q, j]
                            c_rb[q, j] = r_b[q, j]
                        else:
                            s = q - m
                            c_normal[q, j] = s_normal[s, j]
                            c_ra[q, j] = s_point[s, j] - mid_pos[s_a[s], j]
                            c_rb[q, j] = s_point[s, j] - mid_pos[s_b[s], j]
                    if q >= m:
                        c_tangent[q, 0] = -c_normal[q, 1]
                        c_tangent[q, 1] = c_normal[q, 0]
                mask = full_b(ar, kk, True)
                for q in range(m):
                    mask[q] = projected[q]
                idx = _where(ar, mask)
                gap_end = zeros_f(ar, kk)
                got = feature_gaps_inline(ar, idx, c_vert, c_edge, shapes.vertices,
                                          shapes.normals, shapes.vertex_body, new_pos, cos,
                                          sin)
                for q in range(idx.shape[0]):
                    gap_end[idx[q]] = got[q]
                order, starts, isl_bodies, body_starts = island_groups_inline(ar, n, dynamic,
                                                                              c_a, c_b)
                a_o, b_o = gather(ar, c_a, order), gather(ar, c_b, order)
                normal_o = gather_rows(ar, c_normal, order)
                tangent_o = gather_rows(ar, c_tangent, order)
                r_a_o, r_b_o = gather_rows(ar, c_ra, order), gather_rows(ar, c_rb, order)
            kk = order.shape[0]
            n_isl = starts.shape[0] - 1
            gap_o = gather(ar, gap_end, order)
            deep_o = empty_b(ar, kk)
            rhs = empty_f(ar, kk)
            for q in range(kk):
                deep_o[q] = gap_o[q] < -st.projection_slop_m
                rhs[q] = gap_o[q] + st.projection_slop_m
            sel = full_b(ar, n_isl, False)
            lens = empty_i(ar, n_isl)
            for i in range(n_isl):
                lens[i] = starts[i + 1] - starts[i]
                for q in range(starts[i], starts[i + 1]):
                    sel[i] = sel[i] or deep_o[q]
            zeros = zeros_f(ar, kk)
            x_n = zeros_f(ar, kk)
            # the row states of the contacts' last projection (TimeStepper._project): the
            # contacts of the velocity solve (the first m) are in this step's warm table at
            # the inverse of its order o, the spare ones not at all
            slot = empty_i(ar, m)
            for q in range(m):
                slot[o[q]] = q
            proj_at = full_i(ar, kk, -1)
            for q in range(kk):
                if order[q] < m:
                    proj_at[q] = slot[order[q]]
            states_in = full_i(ar, kk, -1)
            if st.reuse_row_states:
                for q in range(kk):
                    if proj_at[q] >= 0:
                        states_in[q] = new_warm.projection_state[proj_at[q]]
            states_out = empty_i(ar, kk)
            proj_rows = IslandRows(starts, a_o, b_o, normal_o, tangent_o, r_a_o, r_b_o,
                                   bodies.inv_mass, bodies.inv_inertia)
            # the normal rows alone: no friction row, no bounds
            res, work, codes = solve_small_inline(
                ar, sel, proj_rows, RowProblem(rhs, zeros, full_b(ar, kk, False), zeros, zeros),
                RowImpulses(x_n, zeros_f(ar, kk), zeros_f(ar, kk)), states_in, states_out)
            for i in range(n_isl):
                if sel[i] and res[i] > st.lcp_tol:
                    return REFERENCE, warm, approach
                for q in range(starts[i], starts[i + 1]):
                    if sel[i] and proj_at[q] >= 0:
                        new_warm.projection_state[proj_at[q]] = states_out[q]
            _record_batch(step_ints, step_floats, sel, lens, work, res, sel)
            dv = zeros_f2(ar, n, 3)
            apply_impulses_inline(ar, dv, proj_rows, x_n, zeros)
            sunk = empty_f(ar, kk)
            for q in range(kk):
                x = -gap_o[q]
                sunk[q] = (x if x > 0.0 or x != x else 0.0) * (1.0 if deep_o[q] else 0.0)
            for i in range(n_isl):
                limit = st.projection_reach * _segment_sum(sunk, starts[i], starts[i + 1])
                for q in range(body_starts[i], body_starts[i + 1]):
                    bi = isl_bodies[q]
                    travel = (math.hypot(dv[bi, 0], dv[bi, 1])
                              + abs(dv[bi, 2]) * bodies.radius_m[bi])
                    travel = travel if travel > 1e-300 or travel != travel else 1e-300
                    scale = limit / travel
                    scale = scale if scale < 1.0 or scale != scale else 1.0
                    for j in range(3):
                        dv[bi, j] = dv[bi, j] * scale
            for i in range(n):
                if dynamic[i]:
                    new_pos[i, 0] = new_pos[i, 0] + dv[i, 0]
                    new_pos[i, 1] = new_pos[i, 1] + dv[i, 1]
                    new_ang[i] = new_ang[i] + dv[i, 2]

    # the step is taken: write it
    step_ints[I_STEPS] += 1
    for i in range(n):
        for j in range(2):
            pos[i, j] = new_pos[i, j]
            vel[i, j] = new_vel[i, j]
        ang[i] = new_ang[i]
        om[i] = new_om[i]
    for c in range(ints.shape[0]):
        if c == I_MAX_LCP_ROWS:
            ints[c] = max(ints[c], step_ints[c])
        else:
            ints[c] += step_ints[c]
    for c in range(floats.shape[0]):
        floats[c] = step_floats[c]
    n_msgs[0] = step_msgs[0]
    if m:
        r0 = rep.counts[0]
        for q in range(m):
            r = r0 + q
            rep.body_a[r], rep.piece_a[r], rep.vertex_a[r] = body_a[q], piece_a[q], vert[q]
            rep.body_b[r], rep.piece_b[r], rep.edge_b[r] = body_b[q], piece_b[q], edge[q]
            for j in range(2):
                rep.point[r, j] = point[q, j]
                rep.normal[r, j] = normal[q, j]
                rep.tangent[r, j] = tangent[q, j]
                rep.r_a[r, j] = r_a[q, j]
                rep.r_b[r, j] = r_b[q, j]
            rep.gap[r], rep.edge_param[r] = gap[q], param[q]
            rep.mu_static[r], rep.mu_dynamic[r], rep.restitution[r] = mu_s[q], mu_d[q], rest[q]
            rep.normal_impulse[r], rep.tangent_impulse[r] = p_n[q], p_t[q]
        rep.counts[0] = r0 + m
        rep.step_end[rep.counts[1]] = r0 + m
        rep.counts[1] += 1
    return DONE, new_warm, new_approach


@jit
def advance(t, t_end, pos, ang, vel, om, bodies, shapes, drives, st, warm, approach, ints,
            floats, rep, msgs, n_msgs, arenas):
    """``TimeStepper.advance`` from ``t`` to ``t_end`` (s) by ``st.time_step_s``, the last
    step shortened to land on ``t_end``: ``(code, t, warm, approach)``, where ``code`` is
    ``DONE`` or why the step at ``t`` is left to the caller (``REFERENCE``, ``GROW``). A
    step in which a pair could close too fast for the scheme is shortened
    (:func:`safe_step_inline`); the next one starts where it ended.

    A step's scratch comes from one of the two ``arenas`` (:mod:`feeder_sim.compiled.arena`),
    reset when the step starts; steps alternate between them because the impulses (and
    held-back velocities) a step leaves for the next one live in its arena. They leave as
    ordinary arrays."""
    h = st.time_step_s
    code = DONE
    n = 0
    scratch = (borrow(arenas[0]), borrow(arenas[1]))
    # everything below works on views no kernel owns (``arena.borrow``): Python holds the
    # arrays until the call returns
    pos, ang, vel, om = borrow(pos), borrow(ang), borrow(vel), borrow(om)
    ints, floats, msgs, n_msgs = borrow(ints), borrow(floats), borrow(msgs), borrow(n_msgs)
    warm = Warm(borrow(warm.keys), borrow(warm.p_n), borrow(warm.p_t), borrow(warm.state),
                borrow(warm.projection_state))
    approach = Approach(borrow(approach.lo), borrow(approach.hi), borrow(approach.vel))
    bodies = BodyArrays(
        borrow(bodies.dynamic), borrow(bodies.dyn_idx), borrow(bodies.driven_idx),
        borrow(bodies.inv_mass), borrow(bodies.inv_inertia), borrow(bodies.radius_m),
        borrow(bodies.mu_static), borrow(bodies.mu_dynamic), borrow(bodies.restitution),
        borrow(bodies.gravity), bodies.g, borrow(bodies.kind), borrow(bodies.drive_row))
    shapes = ShapeArrays(
        borrow(shapes.vertices), borrow(shapes.normals), borrow(shapes.piece_start),
        borrow(shapes.piece_body), borrow(shapes.piece_radius), borrow(shapes.vertex_body),
        borrow(shapes.vertex_piece), borrow(shapes.next_vertex), borrow(shapes.prev_vertex),
        borrow(shapes.edge_length), borrow(shapes.piece_width), borrow(shapes.vertex_active),
        borrow(shapes.edge_internal), borrow(shapes.cover_start), borrow(shapes.cover_lo),
        borrow(shapes.cover_hi), borrow(shapes.vertex_canon), shapes.n_piece_bodies)
    drives = DriveSegments(
        borrow(drives.direction), borrow(drives.base_m), borrow(drives.start_s),
        borrow(drives.amplitude_m), borrow(drives.omega_rad_s), borrow(drives.phase_rad),
        borrow(drives.offset_m), borrow(drives.blend_s))
    rep = Reports(
        borrow(rep.body_a), borrow(rep.piece_a), borrow(rep.vertex_a), borrow(rep.body_b),
        borrow(rep.piece_b), borrow(rep.edge_b), borrow(rep.point), borrow(rep.normal),
        borrow(rep.gap), borrow(rep.edge_param), borrow(rep.tangent), borrow(rep.r_a),
        borrow(rep.r_b), borrow(rep.mu_static), borrow(rep.mu_dynamic), borrow(rep.restitution),
        borrow(rep.normal_impulse), borrow(rep.tangent_impulse), borrow(rep.step_end),
        borrow(rep.counts))
    while t_end - t > 1e-9 * h:
        full = min(h, t_end - t)
        ar = scratch[n & 1]
        release(ar, 0)
        step = safe_step_inline(ar, full, pos, ang, vel, om, bodies, shapes, drives, st)
        code, warm, approach = _step(ar, step, t, pos, ang, vel, om, bodies, shapes, drives,
                                     st, warm, approach, ints, floats, rep, msgs, n_msgs)
        if code != DONE:
            break
        if step < full:
            ints[I_SUBSTEPS] += 1
        t = t + step
        n += 1
    out_warm = Warm(warm.keys.copy(), warm.p_n.copy(), warm.p_t.copy(), warm.state.copy(),
                    warm.projection_state.copy())
    out_approach = Approach(approach.lo.copy(), approach.hi.copy(), approach.vel.copy())
    # what the steps left is copied out: free the arenas' overflow blocks
    release(scratch[0], 0)
    release(scratch[1], 0)
    return code, t, out_warm, out_approach
