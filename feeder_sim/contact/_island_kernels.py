"""Compiled stages of a time step's contact work: islands, contact rows, the small islands'
exact solve (Baraff-Dantzig, :mod:`._lcp_kernels`) and the large islands' projected
Gauss-Seidel, impulses applied to velocities, and the state updates around them.

Who calls what: ``dynamics.islands`` and ``TimeStepper`` -> ``island_groups``; ``TimeStepper``
-> ``drift``, ``speed_bounds``, ``contact_rows``, ``solve_small`` (also the position
projection's normal-row problems, rather than a kernel of its own that would compile
``dantzig`` a second time), ``solve_pgs``, ``apply_impulses``, ``feature_gaps``. Each kernel
reproduces the numpy code in :mod:`.dynamics` / ``time_stepping`` it replaces with the same
arithmetic where that code is the reference (``test/stepping/test_pile.py`` holds them together).

Each kernel takes a scratch arena first (``ar``, :mod:`feeder_sim.compiled.arena`): the
compiled step passes its own, calls from Python ``heap_state()``, whose arrays are ordinary
numpy ones.

Compile time (measured by ``benchmarks/compile.py``): a cold time-stepping run compiles
these kernels, later runs load their machine code from the cache. The code avoids numba's
library sorts, ``lstsq``, ``@`` and slice assignment, and is kept flat, because each of them
lengthens that first compile.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.arena import (
    arange_i,
    copy_i,
    empty_b,
    empty_f,
    empty_f2,
    empty_i,
    full_b,
    full_i,
    full_i2,
    gather,
    gather_rows,
    zeros_f,
    zeros_f2,
)
from feeder_sim.compiled.jit import for_python, inner, jit
from feeder_sim.contact._collision_kernels import _argsort
from feeder_sim.contact._lcp_kernels import (
    _affine,
    _dense_residual,
    _dz_solve,
    dantzig,
    solve_with_states,
)


class IslandRows(NamedTuple):
    """The contacts of a step's islands, in island order, and the bodies they act on: what
    every solve of an island reads."""

    starts: np.ndarray       # (n_islands + 1,) int: island i has contacts starts[i]:starts[i+1]
    a: np.ndarray            # (c,) int: each contact's body a
    b: np.ndarray            # (c,) int: its body b
    normal: np.ndarray       # (c, 2): unit normal
    tangent: np.ndarray      # (c, 2): unit tangent
    r_a: np.ndarray          # (c, 2) m: contact point relative to body a's centre of mass
    r_b: np.ndarray          # (c, 2) m: relative to body b's
    inv_mass: np.ndarray     # (n_bodies,) 1/kg
    inv_inertia: np.ndarray  # (n_bodies,) 1/(kg m^2)


class RowProblem(NamedTuple):
    """Each contact's velocities before the impulses and its friction bounds: the rows of the
    islands' LCPs."""

    b_n: np.ndarray     # (c,) m/s: normal velocity
    b_t: np.ndarray     # (c,) m/s: tangential velocity
    box: np.ndarray     # (c,) bool: the contact has a friction row
    mu_lo: np.ndarray   # (c,): bounds -mu_lo x_N <= x_T <= mu_hi x_N
    mu_hi: np.ndarray   # (c,)


class RowImpulses(NamedTuple):
    """What a solve writes per contact."""

    x_n: np.ndarray     # (c,) N s: normal impulse (a solve from a warm start reads it first)
    x_t: np.ndarray     # (c,) N s: tangential impulse
    w_t: np.ndarray     # (c,) m/s: tangential velocity after them (contacts with box)


class StepSlip(NamedTuple):
    """How each contact slips over the step: what Coulomb's law within the step reads
    (``stop_within_step``, ``breakaway_within_step``) and writes (``offset``, ``remain``)."""

    slip: np.ndarray       # (c,) m/s: tangential slip at the step's start
    sliding: np.ndarray    # (c,) bool: slid into the step (one-sided bounds)
    half_vel: np.ndarray   # (n_bodies, 2) m/s: free velocities at mid-step
    half_om: np.ndarray    # (n_bodies,) rad/s
    v_t_end: np.ndarray    # (c,) m/s: free slip at the step's end
    mu_s: np.ndarray       # (c,): static friction coefficient
    mu_d: np.ndarray       # (c,): dynamic
    offset: np.ndarray     # (c,) N s: impulse of the slide before a stop
    remain: np.ndarray     # (c,): the part of the step after a stop (1: none)


class PgsSettings(NamedTuple):
    """How projected Gauss-Seidel sweeps an island (``TimeStepSettings.pgs_*``)."""

    tol_mps: float      # velocity residual to stop at, m/s
    max_sweeps: int
    check: int          # sweeps between residual checks (and conjugate steps)
    omega: float        # SOR factor
    momentum: bool      # conjugate gradient steps (Silcowitz, Niebe and Erleben)


class RowJacobians(NamedTuple):
    """The contact rows' Jacobian blocks (``_rows``): rows [N_0..N_{c-1}, T_0..T_{c-1}]."""

    ja: np.ndarray      # (2c, 3): on body a, (d, r_a x d)
    jb: np.ndarray      # (2c, 3): on body b, -(d, r_b x d)
    ma: np.ndarray      # (2c, 3): ja times body a's inverse mass and inertia
    mb: np.ndarray      # (2c, 3): jb times body b's


@inner
def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@inner(machine_inline=True)
def island_groups_inline(ar, n_bodies, dynamic, a, b):
    """Islands of dynamic bodies joined by contacts (static / kinematic bodies never join).

    Returns ``(order, starts, bodies, body_starts)``: island i owns the contacts
    ``order[starts[i]:starts[i+1]]`` (ascending) and the dynamic bodies
    ``bodies[body_starts[i]:body_starts[i+1]]`` (ascending); islands are ordered by their
    smallest body index.
    """
    k = a.shape[0]
    parent = arange_i(ar, n_bodies)
    for c in range(k):
        i, j = a[c], b[c]
        if dynamic[i] and dynamic[j]:
            ri, rj = _find(parent, i), _find(parent, j)
            if ri != rj:
                if ri < rj:
                    parent[rj] = ri
                else:
                    parent[ri] = rj
    # island number of every root, ascending root order
    root_of = empty_i(ar, k)
    used = full_b(ar, n_bodies, False)
    for c in range(k):
        owner = a[c] if dynamic[a[c]] else b[c]
        r = _find(parent, owner)
        root_of[c] = r
        used[r] = True
    island_of_root = full_i(ar, n_bodies, -1)
    n_isl = 0
    for r in range(n_bodies):
        if used[r]:
            island_of_root[r] = n_isl
            n_isl += 1
    # contacts: counting sort by island, stable
    starts = full_i(ar, n_isl + 1, 0)
    for c in range(k):
        starts[island_of_root[root_of[c]] + 1] += 1
    for i in range(n_isl):
        starts[i + 1] += starts[i]
    fill = copy_i(ar, starts[:-1])
    order = empty_i(ar, k)
    for c in range(k):
        i = island_of_root[root_of[c]]
        order[fill[i]] = c
        fill[i] += 1
    # bodies: dynamic bodies that appear in a contact, by island then index
    member = full_b(ar, n_bodies, False)
    for c in range(k):
        if dynamic[a[c]]:
            member[a[c]] = True
        if dynamic[b[c]]:
            member[b[c]] = True
    body_starts = full_i(ar, n_isl + 1, 0)
    for i in range(n_bodies):
        if member[i]:
            body_starts[island_of_root[_find(parent, i)] + 1] += 1
    for i in range(n_isl):
        body_starts[i + 1] += body_starts[i]
    bfill = copy_i(ar, body_starts[:-1])
    bodies = empty_i(ar, body_starts[n_isl])
    for i in range(n_bodies):
        if member[i]:
            isl = island_of_root[_find(parent, i)]
            bodies[bfill[isl]] = i
            bfill[isl] += 1
    return order, starts, bodies, body_starts


island_groups = for_python(island_groups_inline)


@inner
def _rows(ar, rows):
    """Per-row Jacobian blocks of the contacts of ``rows`` (:class:`IslandRows`): a
    :class:`RowJacobians`, rows [N_0..N_{c-1}, T_0..T_{c-1}].

    ``ja[i] = (d, r_a x d)`` acts on body a, ``jb[i] = -(d, r_b x d)`` on body b; ``ma`` /
    ``mb`` are the same blocks multiplied by the inverse mass (so ``dv = M^-1 J^T x``)."""
    _, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia = rows
    c = a.shape[0]
    m = 2 * c
    ja = empty_f2(ar, m, 3)
    jb = empty_f2(ar, m, 3)
    ma = empty_f2(ar, m, 3)
    mb = empty_f2(ar, m, 3)
    for i in range(m):
        k = i if i < c else i - c
        if i < c:
            dx, dy = normal[k, 0], normal[k, 1]
        else:
            dx, dy = tangent[k, 0], tangent[k, 1]
        ia, ib = a[k], b[k]
        ja[i, 0] = dx
        ja[i, 1] = dy
        ja[i, 2] = r_a[k, 0] * dy - r_a[k, 1] * dx
        jb[i, 0] = -dx
        jb[i, 1] = -dy
        jb[i, 2] = -(r_b[k, 0] * dy - r_b[k, 1] * dx)
        for q in range(2):
            ma[i, q] = inv_mass[ia] * ja[i, q]
            mb[i, q] = inv_mass[ib] * jb[i, q]
        ma[i, 2] = inv_inertia[ia] * ja[i, 2]
        mb[i, 2] = inv_inertia[ib] * jb[i, 2]
    return RowJacobians(ja, jb, ma, mb)


@inner(machine_inline=True)
def apply_impulses_inline(ar, dv, rows, p_n, p_t):
    """``dv[body] += M^-1 J^T p`` for impulses (p_n, p_t) at the contacts of ``rows``
    (:class:`IslandRows`); dv is (n_bodies, 3).

    Summed like ``IslandJacobian.velocity_change`` (``inv_mass * (J.T @ impulse)``): per body
    and component, the normal rows in contact order, then the tangent rows, then one
    multiplication by the inverse mass, so the velocities match the numpy path."""
    _, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia = rows
    n = dv.shape[0]
    s = zeros_f2(ar, n, 3)
    for kind in range(2):
        d = normal if kind == 0 else tangent
        p = p_n if kind == 0 else p_t
        for k in range(a.shape[0]):
            dx, dy = d[k, 0], d[k, 1]
            ia, ib = a[k], b[k]
            s[ia, 0] += dx * p[k]
            s[ia, 1] += dy * p[k]
            s[ia, 2] += (r_a[k, 0] * dy - r_a[k, 1] * dx) * p[k]
            s[ib, 0] += -dx * p[k]
            s[ib, 1] += -dy * p[k]
            s[ib, 2] += -(r_b[k, 0] * dy - r_b[k, 1] * dx) * p[k]
    for i in range(n):
        dv[i, 0] += inv_mass[i] * s[i, 0]
        dv[i, 1] += inv_mass[i] * s[i, 1]
        dv[i, 2] += inv_inertia[i] * s[i, 2]


apply_impulses = for_python(apply_impulses_inline)


@inner
def _row_w(i, k, a, b, ja, jb, dv, bias):
    ia, ib = a[k], b[k]
    return (bias + ja[i, 0] * dv[ia, 0] + ja[i, 1] * dv[ia, 1] + ja[i, 2] * dv[ia, 2]
            + jb[i, 0] * dv[ib, 0] + jb[i, 1] * dv[ib, 1] + jb[i, 2] * dv[ib, 2])


@inner
def _row_add(i, k, a, b, ma, mb, dv, delta):
    ia, ib = a[k], b[k]
    dv[ia, 0] += ma[i, 0] * delta
    dv[ia, 1] += ma[i, 1] * delta
    dv[ia, 2] += ma[i, 2] * delta
    dv[ib, 0] += mb[i, 0] * delta
    dv[ib, 1] += mb[i, 1] * delta
    dv[ib, 2] += mb[i, 2] * delta


@inner
def _island_residual(lo_c, hi_c, a, b, jac, dv, problem, out, diag):
    """Two measures of how far one island's impulses (of ``out``, :class:`RowImpulses`) are
    from solving its LCP (``problem``, :class:`RowProblem`; ``jac`` its
    :class:`RowJacobians`).

    * ``lcp.residual`` of the assembled problem (scale-free; the assembled matrix is
      symmetric positive semi-definite, so ``max|A|`` is its largest diagonal entry);
    * the natural-map residual in m/s: the largest velocity change a further projected
      Gauss-Seidel step would make, ``A_ii |x_i - proj(x_i - w_i / A_ii)|``. Unlike the
      former it does not scale with the largest ``|b|`` of the island (speculative contacts
      far apart have b ~ gap / h ~ 1 m/s), so it bounds the velocity error of every contact.

    Also writes the tangential w (new tangential velocity) of every contact to ``out.w_t``.
    Returns (lcp residual, velocity residual)."""
    ja, jb = jac.ja, jac.jb
    b_n, b_t, box, mu_lo, mu_hi = problem
    x_n, x_t, w_t_out = out
    c = a.shape[0]
    amax = 0.0
    bmax = 0.0
    xmax = 0.0
    for k in range(lo_c, hi_c):
        amax = max(amax, diag[k])
        bmax = max(bmax, abs(b_n[k]))
        xmax = max(xmax, abs(x_n[k]))
        if box[k]:
            amax = max(amax, diag[k + c])
            bmax = max(bmax, abs(b_t[k]))
            xmax = max(xmax, abs(x_t[k]))
    if not (xmax - xmax == 0.0):
        return np.inf, np.inf
    s_w = max(1e-300, max(bmax, amax * xmax))
    s_x = s_w / amax if amax > 0.0 else max(1e-300, xmax)
    r = 0.0
    rv = 0.0
    for k in range(lo_c, hi_c):
        w = _row_w(k, k, a, b, ja, jb, dv, b_n[k])
        x = x_n[k]
        r = max(r, max(-x / s_x, max(-w / s_w, abs(x * w) / (s_x * s_w))))
        if diag[k] > 0.0:
            rv = max(rv, abs(x - max(x - w / diag[k], 0.0)) * diag[k])
        wt = _row_w(k + c, k, a, b, ja, jb, dv, b_t[k])
        w_t_out[k] = wt
        if box[k]:
            xj = max(x, 0.0)
            xk = x_t[k]
            dl = xk + mu_lo[k] * xj
            dh = mu_hi[k] * xj - xk
            away = wt * max(dl, 0.0) if wt > 0.0 else -wt * max(dh, 0.0)
            r = max(r, max(-dl / s_x, max(-dh / s_x, away / (s_x * s_w))))
            if diag[k + c] > 0.0:
                y = min(max(xk - wt / diag[k + c], -mu_lo[k] * xj), mu_hi[k] * xj)
                rv = max(rv, abs(xk - y) * diag[k + c])
    return max(r, 0.0), rv


@inner(inline='always')
def _contact_velocity(i, ia, ib, nx, ny, r_a, r_b, velocity, omega):
    """Normal and tangential velocity (m/s) of contact i's vertex relative to the edge's
    material point under it: ``v_a + omega_a x r_a - (v_b + omega_b x r_b)`` on n and t."""
    pax = velocity[ia, 0] + omega[ia] * -r_a[i, 1]
    pay = velocity[ia, 1] + omega[ia] * r_a[i, 0]
    pbx = velocity[ib, 0] + omega[ib] * -r_b[i, 1]
    pby = velocity[ib, 1] + omega[ib] * r_b[i, 0]
    rx, ry = pax - pbx, pay - pby
    return rx * nx + ry * ny, rx * -ny + ry * nx


@jit
def contact_velocities(a, b, normal, r_a, r_b, velocity, omega):
    """Normal and tangential relative velocity (m/s) of every contact (``_contact_velocity``)."""
    k = a.shape[0]
    v_n = np.empty(k)
    v_t = np.empty(k)
    for i in range(k):
        v_n[i], v_t[i] = _contact_velocity(i, a[i], b[i], normal[i, 0], normal[i, 1], r_a, r_b,
                                           velocity, omega)
    return v_n, v_t


@inner(machine_inline=True)
def drift_inline(idx, position, angle, velocity, omega, half_h, out_position, out_angle):
    """``out = position + half_h * velocity`` (and the same for the angles) for the bodies
    ``idx``: a half step of Moreau's midpoint scheme, with the bits of numpy's
    ``position[idx] + 0.5 * h * velocity[idx]`` (``half_h = 0.5 * h``)."""
    for q in range(idx.shape[0]):
        i = idx[q]
        out_position[i, 0] = position[i, 0] + half_h * velocity[i, 0]
        out_position[i, 1] = position[i, 1] + half_h * velocity[i, 1]
        out_angle[i] = angle[i] + half_h * omega[i]


drift = for_python(drift_inline)


@inner(machine_inline=True)
def speed_bounds_inline(velocity, omega, radius, dynamic):
    """The largest ``|v| + |omega| r`` (speed bound of a body's points) of the dynamic bodies
    and of the others, the largest ``omega^2 r`` of the dynamic bodies, and a bound on the
    speed at which points of two dynamic bodies close on each other (twice the largest
    ``|v - c| + |omega| r``, c the centre of the dynamic velocities' bounding box): the
    reductions of ``TimeStepper.margin`` / ``_slip_tol`` (NaN propagates)."""
    v_dyn = 0.0
    v_other = 0.0
    spin = 0.0
    lo_x = lo_y = np.inf
    hi_x = hi_y = -np.inf
    for i in range(velocity.shape[0]):
        s = (np.sqrt(velocity[i, 0] * velocity[i, 0] + velocity[i, 1] * velocity[i, 1])
             + abs(omega[i]) * radius[i])
        if dynamic[i]:
            v_dyn = s if s > v_dyn or s != s else v_dyn
            q = omega[i] * omega[i] * radius[i]
            spin = q if q > spin or q != q else spin
            lo_x, hi_x = min(lo_x, velocity[i, 0]), max(hi_x, velocity[i, 0])
            lo_y, hi_y = min(lo_y, velocity[i, 1]), max(hi_y, velocity[i, 1])
        else:
            v_other = s if s > v_other or s != s else v_other
    cx, cy = 0.5 * (lo_x + hi_x), 0.5 * (lo_y + hi_y)
    spread = 0.0
    for i in range(velocity.shape[0]):
        if dynamic[i]:
            s = (np.sqrt((velocity[i, 0] - cx) ** 2 + (velocity[i, 1] - cy) ** 2)
                 + abs(omega[i]) * radius[i])
            spread = s if s > spread or s != s else spread
    return v_dyn, v_other, spin, 2.0 * spread


speed_bounds = for_python(speed_bounds_inline)


class RowSettings(NamedTuple):
    """The scalars ``contact_rows`` decides and builds the rows with."""

    h_s: float                  # time step
    touch_m: float              # a contact touches at gap <= touch_m
    max_rows: int               # an island with more rows is a pile
    push_out: float             # share of a pile's penetration pushed out per step
    push_max_mps: float         # cap of that push-out velocity
    slop_m: float               # penetration a pile keeps
    collide_speed_mps: float    # a contact approaching faster (v_N below this) collides
    slip_tol_mps: float         # a pre-step slip above this slides (dynamic friction)
    friction_impulse: bool      # colliding contacts get friction rows too
    spec_depth: float           # speculative allowance, share of the smaller piece width
    reach_m: float              # distance a point can travel in the step


@inner(inline='always')
def _free_velocity(i, ia, ib, point, normal, position, v_end, w_end, r_a, r_b):
    """Contact i's lever arms (written to ``r_a[i]``, ``r_b[i]``, m, from the bodies'
    ``position``) and its normal and tangential velocity (m/s) at the free end-of-step
    velocities ``v_end`` / ``w_end`` (``contact_velocities``)."""
    for q in range(2):
        r_a[i, q] = point[i, q] - position[ia, q]
        r_b[i, q] = point[i, q] - position[ib, q]
    return _contact_velocity(i, ia, ib, normal[i, 0], normal[i, 1], r_a, r_b, v_end, w_end)


@inner(inline='always')
def _kept(pile, gap, vn_free, width_a, width_b, settings):
    """``contact_rows``' choice for one contact: (kept, speculative, allowance m)."""
    touch, h = settings.touch_m, settings.h_s
    if pile or gap <= touch or gap + 0.5 * h * vn_free <= touch:
        return True, False, 0.0
    d = settings.spec_depth * (width_a if width_a < width_b else width_b)
    if gap + d <= settings.reach_m:
        return True, True, d
    return False, False, 0.0


@inner(machine_inline=True)
def any_kept_inline(ar, a, b, point, normal, gap, position, v_end, w_end, piece_a, piece_b,
                    piece_width, settings):
    """Whether :func:`contact_rows_inline` keeps any of these contacts, none of which is in a
    pile (the caller knows: ``2 k <= max_rows``). A step whose contacts all stay apart
    builds no islands and no rows."""
    n = a.shape[0]
    r_a = empty_f2(ar, n, 2)
    r_b = empty_f2(ar, n, 2)
    for i in range(n):
        vn_free = _free_velocity(i, a[i], b[i], point, normal, position, v_end, w_end, r_a,
                                 r_b)[0]
        if _kept(False, gap[i], vn_free, piece_width[piece_a[i]], piece_width[piece_b[i]],
                 settings)[0]:
            return True
    return False


@inner(machine_inline=True)
def contact_rows_inline(ar, a, b, point, normal, gap, order, starts, position, v_end, w_end,
                        v_pre, w_pre, mu_s_body, mu_d_body, e_body, piece_a, piece_b,
                        piece_width, settings):
    """The per-contact part of ``TimeStepper._contacts`` in one pass (the numpy expressions it
    replaces are quoted; same operations in the same order, so the same bits).

    Contacts come as found at the midpoint configuration (``position``); ``order`` / ``starts``
    are their islands (``island_groups``). A contact is kept when its island is a pile
    (``2 * size > max_rows``), it touches (``gap <= touch``) or it would close its gap by the
    end of the step (``gap + 0.5 * h * v_N_free <= touch``): a Newton row. A contact of a small
    island kept for none of these is speculative when ``gap + allow <= reach`` (``allow`` =
    ``spec_depth`` x the smaller width of its two pieces, ``reach`` the distance a point can
    travel in the step): its row ``v'_N + (gap + allow) / h >= 0`` lets it close by at most
    ``gap + allow`` before the next midpoint. Returns the kept indices, then per
    kept contact: ``dynamics.contact_set``'s tangent, r_a, r_b, mu_static, mu_dynamic,
    restitution; the free end-of-step velocities v_N, v_T (``v_end`` / ``w_end``); the
    pre-step slip v_T (``v_pre`` / ``w_pre``); pile, colliding, the normal rows' b, then
    ``dynamics.friction_rows``' BOX flag, mu_lo, mu_hi; and the smallest kept gap.
    ``settings`` is a :class:`RowSettings`."""
    h, touch, max_rows = settings.h_s, settings.touch_m, settings.max_rows
    push_out, push_max, slop = settings.push_out, settings.push_max_mps, settings.slop_m
    collide_speed, slip_tol = settings.collide_speed_mps, settings.slip_tol_mps
    friction_impulse = settings.friction_impulse
    n = a.shape[0]
    size = empty_i(ar, n)
    for i in range(starts.shape[0] - 1):
        for q in range(starts[i], starts[i + 1]):
            size[order[q]] = starts[i + 1] - starts[i]
    r_a = empty_f2(ar, n, 2)
    r_b = empty_f2(ar, n, 2)
    vn_free = empty_f(ar, n)
    vt_free = empty_f(ar, n)
    keep = empty_i(ar, n)
    allow = empty_f(ar, n)
    spec = empty_b(ar, n)
    m = 0
    for i in range(n):
        vn_free[i], vt_free[i] = _free_velocity(i, a[i], b[i], point, normal, position, v_end,
                                                w_end, r_a, r_b)
        kept, spec[i], allow[i] = _kept(2 * size[i] > max_rows, gap[i], vn_free[i],
                                        piece_width[piece_a[i]], piece_width[piece_b[i]],
                                        settings)
        if kept:
            keep[m] = i
            m += 1
    keep = keep[:m]
    tangent = empty_f2(ar, m, 2)
    ra = empty_f2(ar, m, 2)
    rb = empty_f2(ar, m, 2)
    mu_s = empty_f(ar, m)
    mu_d = empty_f(ar, m)
    rest = empty_f(ar, m)
    v_n = empty_f(ar, m)
    v_t = empty_f(ar, m)
    slip = empty_f(ar, m)
    pile = empty_b(ar, m)
    colliding = empty_b(ar, m)
    b_n = empty_f(ar, m)
    box = empty_b(ar, m)
    mu_lo = empty_f(ar, m)
    mu_hi = empty_f(ar, m)
    gap_min = np.inf
    for q in range(m):
        i = keep[q]
        ia, ib = a[i], b[i]
        nx, ny = normal[i, 0], normal[i, 1]
        tangent[q, 0] = -ny
        tangent[q, 1] = nx
        for j in range(2):
            ra[q, j] = r_a[i, j]
            rb[q, j] = r_b[i, j]
        # world.mix: friction the geometric mean, restitution the larger value
        x, y = mu_s_body[ia], mu_s_body[ib]
        mu_s[q] = x if x == y else np.sqrt(x * y)
        x, y = mu_d_body[ia], mu_d_body[ib]
        mu_d[q] = x if x == y else np.sqrt(x * y)
        x, y = e_body[ia], e_body[ib]
        rest[q] = x if x == y else max(x, y)
        v_n[q] = vn_free[i]
        v_t[q] = vt_free[i]
        # contact_velocities at the pre-step velocities
        vn_pre, vt_pre = _contact_velocity(i, ia, ib, nx, ny, r_a, r_b, v_pre, w_pre)
        slip[q] = vt_pre
        g = gap[i]
        gap_min = min(gap_min, g)
        pl = 2 * size[i] > max_rows
        pile[q] = pl
        touching = g <= touch
        # colliding = (touching | ~pile) & (v_n_pre < -2 g h)
        colliding[q] = (touching or not pl) and vn_pre < collide_speed
        # newton = v_n_free + e min(v_n_pre, 0);
        # push = min(push_out max(-gap - slop, 0) 2 / h, push_max).
        # np.minimum / np.maximum return the second operand on a tie (the sign of a zero) and
        # propagate NaN; numba's min / max return the first, hence the explicit forms.
        newton = vn_free[i] + rest[q] * (vn_pre if vn_pre < 0.0 or vn_pre != vn_pre else 0.0)
        if not pl:
            b_n[q] = vn_free[i] + (g + allow[i]) / h if spec[i] else newton
        elif touching:
            depth = -g - slop
            depth = depth if depth > 0.0 or depth != depth else 0.0
            push = push_out * depth * 2.0 / h
            b_n[q] = newton - (push if push < push_max or push != push else push_max)
        else:
            b_n[q] = vn_free[i] + 2.0 * g / h
        # friction_rows(restick=True): the pre-step slip picks static or dynamic friction
        # against the slip; where mu_s > mu_d, mu_s on the side that holds the contact once
        # it stops (else 0)
        sliding = abs(vt_pre) > slip_tol
        mu = mu_d[q] if sliding else mu_s[q]
        hold = mu_s[q] if mu_s[q] > mu_d[q] else 0.0
        mu_lo[q] = hold if sliding and vt_pre < 0 else mu
        mu_hi[q] = hold if sliding and vt_pre > 0 else mu
        box[q] = (mu_lo[q] > 0.0 or mu_hi[q] > 0.0) and (friction_impulse or not colliding[q])
    return (keep, tangent, ra, rb, mu_s, mu_d, rest, v_n, v_t, slip, pile, colliding, b_n, box,
            mu_lo, mu_hi, gap_min)


contact_rows = for_python(contact_rows_inline)


@inner(machine_inline=True)
def feature_gaps_inline(ar, idx, vertex, edge, vertices, normals, vertex_body, position, cos,
                        sin):
    """Gaps of the vertex-edge features of contacts ``idx`` at another configuration:
    ``collision.evaluate_gaps`` (its gap) with the same arithmetic, so the same bits; ``cos`` /
    ``sin`` of the body angles are numpy's. Used by the position projection, which needs the
    gaps of a few contacts: evaluate_gaps' numpy calls cost as much for a few as for many."""
    out = empty_f(ar, idx.shape[0])
    for q in range(idx.shape[0]):
        i = idx[q]
        v, e = vertex[i], edge[i]
        ba, bb = vertex_body[v], vertex_body[e]
        c, s = cos[ba], sin[ba]
        x, y = vertices[v, 0], vertices[v, 1]
        px = position[ba, 0] + (c * x - s * y)
        py = position[ba, 1] + (s * x + c * y)
        c, s = cos[bb], sin[bb]
        x, y = vertices[e, 0], vertices[e, 1]
        qx = position[bb, 0] + (c * x - s * y)
        qy = position[bb, 1] + (s * x + c * y)
        x, y = normals[e, 0], normals[e, 1]
        out[q] = (c * x - s * y) * (px - qx) + (s * x + c * y) * (py - qy)
    return out


feature_gaps = for_python(feature_gaps_inline)


# Columns of a contact's record in the projected Gauss-Seidel (``_pgs_records``): the Jacobian
# blocks of its normal row (ja, jb: 0-5) and their M^-1 multiples (ma, mb: 6-11), the same for
# its friction row (12-23), then b_N, b_T, the SOR steps, the diagonal entries A_ii and the
# friction bounds.
_R_BN, _R_BT, _R_SN, _R_ST, _R_DN, _R_DT, _R_LO, _R_HI = range(24, 32)
_R_WIDTH = 32


@inner
def _pgs_records(ar, rows, jac, step, diag, problem):
    """Everything a sweep reads about contact k in row k of one (c, 32) array, so that a sweep
    streams through memory once instead of gathering from a dozen arrays, and per contact
    whether its vertex / edge body is fixed (zero inverse mass and inertia)."""
    a, b, inv_mass, inv_inertia = rows.a, rows.b, rows.inv_mass, rows.inv_inertia
    ja, jb, ma, mb = jac
    b_n, b_t, _, mu_lo, mu_hi = problem
    c = a.shape[0]
    R = empty_f2(ar, c, _R_WIDTH)
    fixed_a = empty_b(ar, c)
    fixed_b = empty_b(ar, c)
    for k in range(c):
        t = k + c
        for q in range(3):
            R[k, q] = ja[k, q]
            R[k, 3 + q] = jb[k, q]
            R[k, 6 + q] = ma[k, q]
            R[k, 9 + q] = mb[k, q]
            R[k, 12 + q] = ja[t, q]
            R[k, 15 + q] = jb[t, q]
            R[k, 18 + q] = ma[t, q]
            R[k, 21 + q] = mb[t, q]
        R[k, _R_BN] = b_n[k]
        R[k, _R_BT] = b_t[k]
        R[k, _R_SN] = step[k]
        R[k, _R_ST] = step[t]
        R[k, _R_DN] = diag[k]
        R[k, _R_DT] = diag[t]
        R[k, _R_LO] = mu_lo[k]
        R[k, _R_HI] = mu_hi[k]
        fixed_a[k] = inv_mass[a[k]] == 0.0 and inv_inertia[a[k]] == 0.0
        fixed_b[k] = inv_mass[b[k]] == 0.0 and inv_inertia[b[k]] == 0.0
    return R, fixed_a, fixed_b


@inner(inline='always')
def _push(dv, R, k, ia, ib, col, d):
    """Add the velocity change of an impulse change ``d`` on row ``k`` to both its bodies
    (``R[k, col:col + 6]`` hold M^-1 J^T for body a, then body b)."""
    dv[ia, 0] += R[k, col] * d
    dv[ia, 1] += R[k, col + 1] * d
    dv[ia, 2] += R[k, col + 2] * d
    dv[ib, 0] += R[k, col + 3] * d
    dv[ib, 1] += R[k, col + 4] * d
    dv[ib, 2] += R[k, col + 5] * d


@inner
def _pgs_island(lo_c, hi_c, a, b, R, fixed_a, fixed_b, dv, box, x_n, x_t, g_n, g_t, sweeps):
    """``sweeps`` projected Gauss-Seidel sweeps over contacts lo_c..hi_c-1 in order, each
    normal followed by its friction row, whose bounds use the normal just updated (velocity
    form: ``dv`` holds M^-1 J^T x of the island's bodies; contact data in ``R``, see
    ``_pgs_records``; steps are the SOR factor / A_ii, 0 for a row without a positive pivot).
    Always forward: alternating directions can cycle between two fixed points when contacts
    are redundant (two corners of a box edge give identical friction rows). The row updates
    are written out (no helper calls) because this is the innermost loop. Adds each row's
    impulse changes to ``g_n`` / ``g_t``; returns the largest velocity change ``A_ii |dx_i|``
    of the last sweep (m/s).

    A row's w is ``b + ja . dv_a + jb . dv_b`` summed left to right. The sweep is bound by the
    latency of that chain of additions, so the three terms of a fixed body (the track, a
    wall) are left out: its dv stays exactly +0.0 (it only ever receives 0 * d), its terms are
    +-0.0, and adding them can only turn a w of -0.0 into +0.0, which changes no impulse (the
    update is skipped when d is zero) nor any other bit of the answer."""
    change = 0.0
    for _ in range(sweeps):
        change = 0.0
        for k in range(lo_c, hi_c):
            ia, ib = a[k], b[k]
            # w = b + J dv, written out: an inlined helper would count references of dv and
            # R at every call (two calls per array per contact and sweep)
            fa, fb = fixed_a[k], fixed_b[k]
            w = R[k, _R_BN]
            if not fa:
                w = w + R[k, 0] * dv[ia, 0] + R[k, 1] * dv[ia, 1] + R[k, 2] * dv[ia, 2]
            if not fb:
                w = w + R[k, 3] * dv[ib, 0] + R[k, 4] * dv[ib, 1] + R[k, 5] * dv[ib, 2]
            xo = x_n[k]
            xn = xo - R[k, _R_SN] * w
            if xn < 0.0:
                xn = 0.0
            d = xn - xo
            if d != 0.0:
                change = max(change, abs(d) * R[k, _R_DN])
                _push(dv, R, k, ia, ib, 6, d)
                x_n[k] = xn
                g_n[k] += d
            # (xn now equals x_n[k] bit for bit: x_n never holds -0.0)
            if xn == 0.0:
                # an open contact carries no friction: no need to evaluate its row
                d = -x_t[k]
                if d != 0.0:
                    change = max(change, abs(d) * R[k, _R_DT])
                    _push(dv, R, k, ia, ib, 18, d)
                    x_t[k] = 0.0
                    g_t[k] += d
            elif box[k]:
                w = R[k, _R_BT]
                if not fa:
                    w = w + R[k, 12] * dv[ia, 0] + R[k, 13] * dv[ia, 1] + R[k, 14] * dv[ia, 2]
                if not fb:
                    w = w + R[k, 15] * dv[ib, 0] + R[k, 16] * dv[ib, 1] + R[k, 17] * dv[ib, 2]
                xo = x_t[k]
                xt = xo - R[k, _R_ST] * w
                xt = min(max(xt, -R[k, _R_LO] * xn), R[k, _R_HI] * xn)
                d = xt - xo
                if d != 0.0:
                    change = max(change, abs(d) * R[k, _R_DT])
                    _push(dv, R, k, ia, ib, 18, d)
                    x_t[k] = xt
                    g_t[k] += d
    return change


@inner(machine_inline=True)
def _coupling(a, b, k, kj, ma, mb, gm, ja, jb, gj):
    """A Delassus entry: row ``gm`` of the inverse-mass-weighted Jacobians (``ma``, ``mb``) of
    contact ``k`` against row ``gj`` of the Jacobians (``ja``, ``jb``) of contact ``kj``,
    summed over the bodies the two contacts share (``a`` / ``b`` the bodies of each side)."""
    s = 0.0
    if a[k] == a[kj]:
        s += ma[gm, 0] * ja[gj, 0] + ma[gm, 1] * ja[gj, 1] + ma[gm, 2] * ja[gj, 2]
    if a[k] == b[kj]:
        s += ma[gm, 0] * jb[gj, 0] + ma[gm, 1] * jb[gj, 1] + ma[gm, 2] * jb[gj, 2]
    if b[k] == a[kj]:
        s += mb[gm, 0] * ja[gj, 0] + mb[gm, 1] * ja[gj, 1] + mb[gm, 2] * ja[gj, 2]
    if b[k] == b[kj]:
        s += mb[gm, 0] * jb[gj, 0] + mb[gm, 1] * jb[gj, 1] + mb[gm, 2] * jb[gj, 2]
    return s


@inner
def _island_dense(ar, lo_c, hi_c, a, b, jac, problem):
    """The assembled problem of contacts lo_c..hi_c-1 (``dynamics.assemble``'s layout: the
    normals, then the friction rows of contacts with ``box``; ``jac`` the contacts'
    :class:`RowJacobians`, ``problem`` their :class:`RowProblem`): A, b, normal_of, mu_lo,
    mu_hi, and for each row its contact and whether it is a friction row."""
    ja, jb, ma, mb = jac
    b_n, b_t, box, mu_lo, mu_hi = problem
    c = a.shape[0]
    nc = hi_c - lo_c
    m = nc
    for k in range(lo_c, hi_c):
        if box[k]:
            m += 1
    rc = empty_i(ar, m)
    rf = full_b(ar, m, False)
    p = nc
    for q in range(nc):
        rc[q] = lo_c + q
        if box[lo_c + q]:
            rc[p] = lo_c + q
            rf[p] = True
            p += 1
    A = empty_f2(ar, m, m)
    bb = empty_f(ar, m)
    nof = full_i(ar, m, -1)
    lo = zeros_f(ar, m)
    hi = zeros_f(ar, m)
    for i in range(m):
        k = rc[i]
        gi = k + c if rf[i] else k
        if rf[i]:
            bb[i] = b_t[k]
            nof[i] = k - lo_c
            lo[i] = mu_lo[k]
            hi[i] = mu_hi[k]
        else:
            bb[i] = b_n[k]
        for j in range(i, m):
            kj = rc[j]
            gj = kj + c if rf[j] else kj
            s = _coupling(a, b, k, kj, ma, mb, gi, ja, jb, gj)
            A[i, j] = s
            A[j, i] = s
    return A, bb, nof, lo, hi, rc, rf


# Row states kept per contact from one step to the next (``solve_small``): the normal row's in
# the low three bits, the friction row's above them, NO_FRICTION_ROW there for a contact
# without one; -1 where there is nothing to go on.
_STATE_BITS = 3
NO_FRICTION_ROW = 7
# An island solved on its previous row states is taken when the answer's lcp.residual is
# at most this: round-off of a solution in those states (Dantzig's own answers reach
# 1e-16 to 1e-14), far below the lcp_tol its answers must meet (1e-9 by default).
STATES_TOL = 1e-12


@inner(machine_inline=True)
def solve_small_inline(ar, select, rows, problem, out, states_in, states_out):
    """The islands with ``select`` (of ``rows``, :class:`IslandRows`) by Baraff-Dantzig
    (``dantzig``), from scratch, or in one solve where every contact of an island comes with
    the row states it ended the last step in (``states_in``, see ``_STATE_BITS``) and the
    problem solved in those states is solved to ``STATES_TOL`` (a part resting or sliding
    as it did: the same answer to round-off, without pivoting to it again).

    An island's problem has its normal rows, then the friction rows of the contacts with
    ``box[k]`` (bounds ``[-mu_lo x_N, mu_hi x_N]``; other contacts keep x_T = 0), exactly
    ``dynamics.assemble``'s layout (``problem``, :class:`RowProblem`). Writes the impulses and
    the new tangential velocity of contacts with a friction row to ``out``
    (:class:`RowImpulses`) and the row states the answer ends in to ``states_out`` (-1 where
    Dantzig failed); returns per island the residual (``lcp.residual``), the pivots and the
    Dantzig abort codes (pass, retry)."""
    starts, a, b = rows.starts, rows.a, rows.b
    b_n, b_t, box, mu_lo, mu_hi = problem
    x_n, x_t, w_t = out
    n_isl = starts.shape[0] - 1
    jac = _rows(ar, rows)
    ja, jb, ma, mb = jac
    res = zeros_f(ar, n_isl)
    work = full_i(ar, n_isl, 0)
    codes = full_i2(ar, n_isl, 2, 0)
    for isl in range(n_isl):
        if not select[isl]:
            continue
        A, bb, nof, lo, hi, rc, rf = _island_dense(ar, starts[isl], starts[isl + 1], a, b, jac,
                                                   problem)
        m = bb.shape[0]
        known = True
        for k in range(starts[isl], starts[isl + 1]):
            known = known and states_in[k] >= 0
        r = np.inf
        st = empty_i(ar, m)
        x, wv = bb, bb
        if known:
            for i in range(m):
                packed = states_in[rc[i]]
                st[i] = packed >> _STATE_BITS if rf[i] else packed & NO_FRICTION_ROW
            x, wv, r = solve_with_states(ar, A, bb, nof, lo, hi, st)
        if r <= STATES_TOL:
            piv, c1, c2 = 0, 0, 0
        else:
            x, piv, c1, c2, st = dantzig(ar, A, bb, nof, lo, hi, 50 * m + 50)
            wv = _affine(ar, A, x, bb)
            r = _dense_residual(A, bb, x, wv, nof, lo, hi)
        res[isl] = r
        work[isl] = piv
        codes[isl, 0], codes[isl, 1] = c1, c2
        for k in range(starts[isl], starts[isl + 1]):
            x_t[k] = 0.0
            states_out[k] = -1
        for i in range(m):
            # the normal rows come first: a contact's friction row finds its normal's state
            k = rc[i]
            if rf[i]:
                x_t[k] = x[i]
                w_t[k] = wv[i]
            else:
                x_n[k] = x[i]
            if c1 == 0:
                states_out[k] = ((states_out[k] & NO_FRICTION_ROW) | (st[i] << _STATE_BITS)
                                 if rf[i] else (NO_FRICTION_ROW << _STATE_BITS) | st[i])
    return res, work, codes


solve_small = for_python(solve_small_inline)


@inner(machine_inline=True)
def stop_within_step_inline(ar, select, rows, problem, out, slip_state):
    """Coulomb's law over a step for the contacts whose slip stops within it (of ``rows``;
    ``problem``, ``out`` and ``slip_state`` a :class:`RowProblem`, :class:`RowImpulses`
    and :class:`StepSlip`).

    A contact that slides into the step (pre-step slip ``slip``, m/s, with ``sliding``) with
    a friction row is held by ``mu_d`` against its slip until the slip reaches zero, and only
    from that instant on by the static law. The step's first answer (``x_n``, ``x_t`` in N s,
    end slip ``w_t``) tells where that happens: with the contact's friction held at
    ``-sigma mu_d x_n`` for the whole step, its end slip would be ``u_1 = w_t + (W d)_T`` with
    ``d = -sigma mu_d x_n - x_t`` on the friction rows of the island's sliding contacts (``W``
    the Delassus matrix, with the pressing contacts' normal impulses adjusted to keep them
    pressing, ``_keep_pressing``: two corners of one box slip as one and stop at one instant;
    each with its own Delassus entry alone, the stop came out at twice its time); where
    ``u_1`` has the
    other sign the slip stops within the step, at the fraction ``phi`` where the free slip
    (a parabola through its values at the step's start, middle and end: ``slip``, the free
    velocities ``half_vel`` / ``half_om`` at mid-step, ``b_t``) plus the impulses spread
    evenly over the step passes through zero (``_first_zero``).
    Its impulse is then ``-sigma mu_d phi x_n`` (the slide, written to ``offset`` and added
    to the island's free velocities ``b_n`` / ``b_t`` as an applied impulse) plus what the
    rest of the step gives from rest: bounds ``mu_s (1 - phi)`` on both sides (``mu_lo`` /
    ``mu_hi``; ``remain`` = 1 - phi), which become one-sided ``mu_d (1 - phi)`` where it
    cannot hold (the second pass). With the hold side alone (``mu_s`` for the whole step) a
    slip that reverses at a drive's turning point was held for the rest of the step, and
    conveying at 100 steps per period came out at up to 1.5 times its speed.

    Islands with ``select`` only; contacts with ``remain < 1`` are left as they are (a stop
    is taken once a step). Returns per island whether it must be solved again."""
    starts, a, b, normal, _, r_a, r_b, inv_mass, _ = rows
    b_n, b_t, box, mu_lo, mu_hi = problem
    x_n, x_t, w_t = out
    slip, sliding, half_vel, half_om, _, mu_s, mu_d, offset, remain = slip_state
    n_isl = starts.shape[0] - 1
    c = a.shape[0]
    redo = full_b(ar, n_isl, False)
    # the sliding contacts' friction held at -sigma mu_d x_n, all at once: contacts of one
    # body slip together, so each one's end slip depends on the others' friction too
    change = zeros_f(ar, c)
    any_sliding = False
    for isl in range(n_isl):
        if not select[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            if box[q] and sliding[q] and x_n[q] > 0.0 and remain[q] == 1.0:
                sigma = 1.0 if slip[q] > 0.0 else -1.0
                change[q] = -sigma * mu_d[q] * x_n[q] - x_t[q]
                any_sliding = True
    if not any_sliding:
        return redo
    jac = _rows(ar, rows)
    ja, jb, ma, mb = jac
    dv = zeros_f2(ar, inv_mass.shape[0], 3)
    _add_tangent_impulses(n_isl, select, starts, a, b, ma, mb, c, change, dv)
    for isl in range(n_isl):
        if select[isl]:
            _keep_pressing(ar, starts[isl], starts[isl + 1], a, b, jac, x_n, dv)
    any_redo = False
    for isl in range(n_isl):
        if not select[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            if not (box[q] and sliding[q] and x_n[q] > 0.0 and remain[q] == 1.0):
                continue
            u0 = slip[q]
            sigma = 1.0 if u0 > 0.0 else -1.0
            u1 = _row_w(c + q, q, a, b, ja, jb, dv, w_t[q])
            if sigma * u1 >= 0.0:
                continue        # it slides through the step
            if half_vel.shape[0]:
                f_half = _contact_velocity(q, a[q], b[q], normal[q, 0], normal[q, 1], r_a, r_b,
                                           half_vel, half_om)[1]
            else:
                f_half = 0.5 * (u0 + b_t[q])        # no mid-step velocities: a straight line
            phi = _first_zero(u0, u1, f_half, b_t[q])
            offset[q] = -sigma * mu_d[q] * phi * x_n[q]
            remain[q] = 1.0 - phi
            mu_lo[q] = mu_s[q] * remain[q]
            mu_hi[q] = mu_lo[q]
            redo[isl] = True
            any_redo = True
    if not any_redo:
        return redo
    for i in range(dv.shape[0]):
        for j in range(3):
            dv[i, j] = 0.0
    _add_tangent_impulses(n_isl, redo, starts, a, b, ma, mb, c, offset, dv)
    for isl in range(n_isl):
        if not redo[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            b_n[q] = _row_w(q, q, a, b, ja, jb, dv, b_n[q])
            b_t[q] = _row_w(c + q, q, a, b, ja, jb, dv, b_t[q])
    return redo


stop_within_step = for_python(stop_within_step_inline)


@inner(machine_inline=True)
def breakaway_within_step_inline(ar, select, rows, problem, out, slip_state, after_stop):
    """A static contact that holds over its part of the step on average but not throughout
    (of ``rows``; ``problem``, ``out`` and ``slip_state`` a :class:`RowProblem`,
    :class:`RowImpulses` and :class:`StepSlip`; it narrows the friction bounds).

    The static law on a step's impulse compares the step's mean demand with ``mu_s``; the
    demand changes within the step (a drive's acceleration), so a contact can stick at the
    step's start and have to slide before its end, or stop (``stop_within_step``) where it
    cannot be held at all. The free slip over the step is known at its start (``slip``), at
    its middle (the free velocities ``half_vel`` / ``half_om`` at ``t + h/2``) and at its end
    (``v_t_end``): a parabola, whose slope gives the demand's time course, scaled to the held
    impulse ``x_t`` (its mean). From the contact's static start ``s0`` (``1 - remain``: 0, or
    where its slip stopped) the demand ratio ``r`` to ``mu_s`` runs linearly from ``r0`` to
    ``r1``; where it crosses 1 at ``s_b`` the contact breaks away: it sticks until then (mean
    ratio ``(r0 + 1) / 2``) and slides with ``mu_d`` after, so its bound becomes one-sided
    ``mu_s (s_b - s0) (r0 + 1) / 2 + mu_d (1 - s_b)`` against the slip to come. Without it the
    break came a whole step late or early, an error ``(mu_s - mu_d) p_N`` per break that
    persists where a part never sticks long (near the breakaway threshold).

    Contacts with a static row (``mu_lo == mu_hi``) in islands with ``select``, those after a
    stop (``after_stop``) or those static from the step's start, whose body pair holds (its
    contacts' impulses sum to less than their bounds).
    Returns per island whether it must be solved again."""
    starts, a, b, normal, _, r_a, r_b, _, _ = rows
    _, _, box, mu_lo, mu_hi = problem
    x_n, x_t = out.x_n, out.x_t
    slip, _, half_vel, half_om, v_t_end, mu_s, mu_d, _, remain = slip_state
    n_isl = starts.shape[0] - 1
    c = a.shape[0]
    redo = full_b(ar, n_isl, False)
    static = full_b(ar, c, False)
    mean = zeros_f(ar, c)
    c1 = zeros_f(ar, c)
    c2 = zeros_f(ar, c)
    for isl in range(n_isl):
        if not select[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            if not (box[q] and x_n[q] > 0.0 and mu_lo[q] == mu_hi[q] and mu_lo[q] > 0.0
                    and (remain[q] < 1.0) == after_stop):
                continue
            s0 = 1.0 - remain[q]
            f0 = slip[q]
            f_half = _contact_velocity(q, a[q], b[q], normal[q, 0], normal[q, 1], r_a, r_b,
                                       half_vel, half_om)[1]
            f1 = v_t_end[q]
            c1[q] = 4.0 * (f_half - f0) - (f1 - f0)
            c2[q] = (f1 - f0) - c1[q]
            mean[q] = (f1 - (f0 + (c1[q] + c2[q] * s0) * s0)) / (1.0 - s0)
            static[q] = mean[q] != 0.0
    new_bound = empty_f(ar, c)
    for q in range(c):
        new_bound[q] = -1.0
    for isl in range(n_isl):
        if not select[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            if not static[q]:
                continue
            # the contacts between the same two bodies slip as one: their held impulses
            # share the demand in whatever split the LCP chose, so they break together
            demand, bound = 0.0, 0.0
            for p in range(starts[isl], starts[isl + 1]):
                if static[p] and a[p] == a[q] and b[p] == b[q]:
                    demand += -x_t[p] if mean[p] > 0.0 else x_t[p]
                    bound += mu_lo[p] * x_n[p]
            if not demand < bound * (1.0 - 1e-9):
                continue        # saturated: the second pass's
            s0 = 1.0 - remain[q]
            r_mean = demand / bound
            r0 = r_mean * (c1[q] + 2.0 * c2[q] * s0) / mean[q]
            r1 = r_mean * (c1[q] + 2.0 * c2[q]) / mean[q]
            if r0 >= 1.0:
                s_b = s0
            elif r1 > 1.0:
                s_b = s0 + (1.0 - s0) * (1.0 - r0) / (r1 - r0)
            else:
                continue
            new_bound[q] = mu_s[q] * (s_b - s0) * (r0 + 1.0) * 0.5 + mu_d[q] * (1.0 - s_b)
            redo[isl] = True
    for q in range(c):
        if new_bound[q] >= 0.0:
            mu_lo[q] = new_bound[q] if mean[q] > 0.0 else 0.0
            mu_hi[q] = 0.0 if mean[q] > 0.0 else new_bound[q]
    return redo


breakaway_within_step = for_python(breakaway_within_step_inline)


@inner
def _first_zero(u0, u1, f_half, f1):
    """Where in (0, 1) a slip ``u(s) = f(s) + (u1 - f1) s`` that runs from ``u0`` to ``u1`` (of
    the other sign) crosses zero: ``f`` the free slip, the parabola through ``u0``, ``f_half``
    and ``f1`` at s = 0, 1/2, 1, and ``u1 - f1`` the step's impulses spread evenly over it.
    A drive's acceleration changes within a step: a straight line from ``u0`` to ``u1``
    misplaces the stop by a fraction of the step, which the rest of the step's static law
    then holds or throws the wrong way near the breakaway threshold."""
    c1 = 4.0 * (f_half - u0) - (f1 - u0)
    c2 = (f1 - u0) - c1
    k1 = c1 + (u1 - f1)
    # c2 s^2 + k1 s + u0 = 0, one root in (0, 1) since u(0) u(1) < 0; the form without
    # cancellation, the straight line where the curvature does not count
    linear = u0 / (u0 - u1)
    if abs(c2) <= 1e-12 * (abs(k1) + abs(u0)):
        return linear
    disc = k1 * k1 - 4.0 * c2 * u0
    if disc < 0.0:
        return linear
    root = math.sqrt(disc)
    qq = -0.5 * (k1 + (root if k1 >= 0.0 else -root))
    for s in (qq / c2, u0 / qq if qq != 0.0 else -1.0):
        if 0.0 < s < 1.0:
            return s
    return linear


@inner
def _keep_pressing(ar, lo_c, hi_c, a, b, jac, x_n, dv):
    """Add to the velocity change ``dv`` the normal impulses of the contacts lo_c..hi_c-1 that
    press (``x_n > 0``) which keep their normal velocities as they were: the Schur complement
    of the normal rows. A box sliding on two corners does not turn under its friction: its
    normal forces shift between the corners instead, so its slip answers a change of friction
    with ``1/m``, not with ``1/m + (h/2)^2 / I`` (60 % more for a 20 x 10 mm box)."""
    ja, jb, ma, mb = jac
    m = 0
    for k in range(lo_c, hi_c):
        if x_n[k] > 0.0:
            m += 1
    if m == 0:
        return
    rows = empty_i(ar, m)
    m = 0
    for k in range(lo_c, hi_c):
        if x_n[k] > 0.0:
            rows[m] = k
            m += 1
    W = empty_f2(ar, m, m)
    rhs = empty_f(ar, m)
    amax = 0.0
    for i in range(m):
        k = rows[i]
        rhs[i] = -_row_w(k, k, a, b, ja, jb, dv, 0.0)
        for j in range(m):
            kj = rows[j]
            # (kj's inverse mass row against k's Jacobian row: the sum in the same order)
            s = _coupling(a, b, kj, k, ma, mb, kj, ja, jb, k)
            W[i, j] = s
            amax = max(amax, abs(s))
    counts = full_i(ar, 2, 0)       # named, as every caller of _dz_solve does
    y = _dz_solve(ar, W, rhs, amax, counts)
    for i in range(m):
        k = rows[i]
        for j in range(3):
            dv[a[k], j] += ma[k, j] * y[i]
            dv[b[k], j] += mb[k, j] * y[i]


@inner
def _add_tangent_impulses(n_isl, select, starts, a, b, ma, mb, c, p, dv):
    """``dv += M^-1 J_T^T p`` for the tangent impulses ``p`` of the islands with ``select``."""
    for isl in range(n_isl):
        if not select[isl]:
            continue
        for q in range(starts[isl], starts[isl + 1]):
            if p[q] != 0.0:
                ia, ib = a[q], b[q]
                for j in range(3):
                    dv[ia, j] += ma[c + q, j] * p[q]
                    dv[ib, j] += mb[c + q, j] * p[q]


@inner(inline='always')
def _push_all(dv, dv0, P, R, k, ia, ib, col, d):
    """``_push`` into the velocities, their last snapshot and the direction alike."""
    _push(dv, R, k, ia, ib, col, d)
    _push(dv0, R, k, ia, ib, col, d)
    _push(P, R, k, ia, ib, col, d)


@inner(inline='always')
def _conjugate_row(x, p, g, k, beta, lo, hi, dv, dv0, P, R, ia, ib, col):
    """Row k of ``_momentum``: x moves by beta p into [lo, hi]; only what the bounds cut off
    is pushed through the contact (``R`` columns from ``col``). The direction becomes the
    row's whole change since the last step; returns the new x."""
    free = x[k] + beta * p[k]
    new = min(max(free, lo), hi)
    cut = new - free
    if cut != 0.0:
        _push_all(dv, dv0, P, R, k, ia, ib, col, cut)
    p[k] = g[k] + (new - x[k])
    x[k] = new
    g[k] = 0.0
    return new


@inner
def _momentum(lo_c, hi_c, a, b, R, bodies, dv, dv0, P, box, mu_lo, mu_hi, x_n, x_t, g_n, g_t,
              p_n, p_t, rr_old):
    """One step of Silcowitz, Niebe and Erleben's nonsmooth nonlinear conjugate gradient
    (NNCG) after the sweeps that changed the impulses of contacts lo_c..hi_c-1 by ``g_n`` /
    ``g_t`` and the velocities of the island's ``bodies`` from ``dv0`` to
    ``dv``: with beta = |g|^2 / ``rr_old`` (|g|^2 of the step before), the impulses move on by
    beta times the previous direction ``p_n`` / ``p_t`` (in velocities ``P``, per body),
    projected onto x_N >= 0 and the friction bounds, and the direction becomes this step's
    whole change. The velocities move by beta P body by body; only the rows the projection
    cuts back are pushed through their contact (some 4 % of them in a 1000-part pile).
    beta > 1 (the sweeps changed more than in the step before: no longer a descent)
    restarts from a zero direction. Clears ``g`` and leaves ``dv0`` = ``dv``; returns |g|^2,
    the next step's ``rr_old``."""
    rr = 0.0
    for k in range(lo_c, hi_c):
        rr += g_n[k] * g_n[k] + g_t[k] * g_t[k]
    beta = rr / rr_old          # the first step: rr_old inf, beta 0 (the direction is g)
    if not (beta <= 1.0):
        for q in range(bodies.shape[0]):
            i = bodies[q]
            for j in range(3):
                P[i, j] = 0.0
                dv0[i, j] = dv[i, j]
        for k in range(lo_c, hi_c):
            p_n[k] = 0.0
            p_t[k] = 0.0
            g_n[k] = 0.0
            g_t[k] = 0.0
        return rr
    for q in range(bodies.shape[0]):
        i = bodies[q]
        for j in range(3):
            step = beta * P[i, j]
            P[i, j] = (dv[i, j] - dv0[i, j]) + step
            dv[i, j] += step
            dv0[i, j] = dv[i, j]
    for k in range(lo_c, hi_c):
        ia, ib = a[k], b[k]
        xn = _conjugate_row(x_n, p_n, g_n, k, beta, 0.0, np.inf, dv, dv0, P, R, ia, ib, 6)
        lo, hi = (-mu_lo[k] * xn, mu_hi[k] * xn) if box[k] else (0.0, 0.0)
        _conjugate_row(x_t, p_t, g_t, k, beta, lo, hi, dv, dv0, P, R, ia, ib, 18)
    return rr


@jit
def solve_pgs(ar, select, rows, problem, out, dv, pgs, height):
    """:func:`_solve_pgs_in_order` with each selected island's contacts taken bottom-up, in
    order of ``height`` (along -gravity, any unit; ties keep their order): consecutive rows
    then mostly belong to parts side by side rather than to one body, whose velocity each
    row must wait for, and a sweep of a settled pile costs less while about as many sweeps
    are needed (``benchmarks/pile.py``). The arguments are those of ``_solve_pgs_in_order``
    in the caller's order; ``out`` is written back in it."""
    starts, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia = rows
    b_n, b_t, box, mu_lo, mu_hi = problem
    x_n, x_t, w_t = out
    c = a.shape[0]
    perm = arange_i(ar, c)
    for isl in range(starts.shape[0] - 1):
        if select[isl]:
            lo_c = starts[isl]
            local = _argsort(ar, height[lo_c:starts[isl + 1]])
            for q in range(local.shape[0]):
                perm[lo_c + q] = lo_c + local[q]
    s_x_n, s_x_t, s_w_t = gather(ar, x_n, perm), gather(ar, x_t, perm), gather(ar, w_t, perm)
    sorted_rows = IslandRows(
        starts, gather(ar, a, perm), gather(ar, b, perm), gather_rows(ar, normal, perm),
        gather_rows(ar, tangent, perm), gather_rows(ar, r_a, perm), gather_rows(ar, r_b, perm),
        inv_mass, inv_inertia)
    sorted_problem = RowProblem(gather(ar, b_n, perm), gather(ar, b_t, perm),
                                gather(ar, box, perm), gather(ar, mu_lo, perm),
                                gather(ar, mu_hi, perm))
    res, vres, work = _solve_pgs_in_order(ar, select, sorted_rows, sorted_problem,
                                          RowImpulses(s_x_n, s_x_t, s_w_t), dv, pgs)
    for q in range(c):
        x_n[perm[q]] = s_x_n[q]
        x_t[perm[q]] = s_x_t[q]
        w_t[perm[q]] = s_w_t[q]
    return res, vres, work


@inner
def _solve_pgs_in_order(ar, select, rows, problem, out, dv, pgs):
    """The islands with ``select`` (of ``rows``, :class:`IslandRows`; their LCPs'
    ``problem``, :class:`RowProblem`) by projected Gauss-Seidel in velocity form
    (``_pgs_island``; ``pgs`` a :class:`PgsSettings`), with ``momentum``: each ``check``
    sweeps followed by a nonsmooth
    conjugate gradient step (``_momentum``; the 200-part pile of the throughput benchmark
    needs 39 sweeps per solve instead of 62).

    ``x_n`` / ``x_t`` hold the warm start (the previous step's impulses of the same
    features, 0 for new ones) on entry and the answer on return; ``dv`` (n_bodies, 3) is
    scratch and must be zero. Each island is swept until its velocity residual (m/s, see
    ``_island_residual``, checked every ``check`` sweeps) is <= ``tol`` or ``max_sweeps``
    is reached; the answer is always that of a sweep, whose impulses lie within their
    bounds. Writes the new tangential velocities to ``w_t``; returns per island the
    ``lcp.residual``, the velocity residual and the sweeps."""
    starts, a, b, _, _, _, _, inv_mass, inv_inertia = rows
    b_n, b_t, box, mu_lo, mu_hi = problem
    x_n, x_t, w_t = out
    tol, max_sweeps, check, omega, momentum = pgs
    c = a.shape[0]
    n_isl = starts.shape[0] - 1
    jac = _rows(ar, rows)
    ja, jb, ma, mb = jac
    diag = empty_f(ar, 2 * c)
    for i in range(2 * c):
        diag[i] = (ja[i, 0] * ma[i, 0] + ja[i, 1] * ma[i, 1] + ja[i, 2] * ma[i, 2]
                   + jb[i, 0] * mb[i, 0] + jb[i, 1] * mb[i, 1] + jb[i, 2] * mb[i, 2])
    step = zeros_f(ar, 2 * c)
    for i in range(2 * c):
        if diag[i] > 0.0:
            step[i] = omega / diag[i]
    R, fixed_a, fixed_b = _pgs_records(ar, rows, jac, step, diag, problem)
    res = zeros_f(ar, n_isl)
    vres = zeros_f(ar, n_isl)
    work = full_i(ar, n_isl, 0)
    g_n = zeros_f(ar, c)
    g_t = zeros_f(ar, c)
    p_n = zeros_f(ar, c)
    p_t = zeros_f(ar, c)
    nbod = dv.shape[0]
    seen = full_b(ar, nbod, False)
    bodies = empty_i(ar, nbod)
    dv0 = empty_f2(ar, nbod, 3)
    P = empty_f2(ar, nbod, 3)
    for isl in range(n_isl):
        if not select[isl]:
            continue
        lo_c, hi_c = starts[isl], starts[isl + 1]
        for k in range(lo_c, hi_c):
            # project the warm start and accumulate its velocity change
            if not (x_n[k] > 0.0):
                x_n[k] = 0.0
            if box[k]:
                x_t[k] = min(max(x_t[k], -mu_lo[k] * x_n[k]), mu_hi[k] * x_n[k])
            else:
                x_t[k] = 0.0
            _row_add(k, k, a, b, ma, mb, dv, x_n[k])
            _row_add(k + c, k, a, b, ma, mb, dv, x_t[k])
        # sweep until a sweep changes no velocity by more than tol, then confirm with the
        # residual at the final point (the stopping test, recorded with lcp.residual)
        r, rv = _island_residual(lo_c, hi_c, a, b, jac, dv, problem, out, diag)
        s = 0
        rr = np.inf
        nb = 0
        if momentum:
            for k in range(lo_c, hi_c):
                for i in (a[k], b[k]):
                    if not seen[i] and (inv_mass[i] != 0.0 or inv_inertia[i] != 0.0):
                        seen[i] = True
                        bodies[nb] = i
                        nb += 1
                        for j in range(3):
                            dv0[i, j] = dv[i, j]
                            P[i, j] = 0.0
        isl_bodies = bodies[:nb]
        while rv > tol and s < max_sweeps:
            n = min(check, max_sweeps - s)
            change = _pgs_island(lo_c, hi_c, a, b, R, fixed_a, fixed_b, dv, box, x_n, x_t,
                                 g_n, g_t, n)
            s += n
            if change <= tol or s >= max_sweeps:
                r, rv = _island_residual(lo_c, hi_c, a, b, jac, dv, problem, out, diag)
                if rv <= tol or s >= max_sweeps:
                    break
            if momentum:
                rr = _momentum(lo_c, hi_c, a, b, R, isl_bodies, dv, dv0, P, box, mu_lo, mu_hi,
                               x_n, x_t, g_n, g_t, p_n, p_t, rr)
        res[isl] = r
        vres[isl] = rv
        work[isl] = s
    return res, vres, work
