"""The closed-form phases of one dynamic body, chained through its events, compiled.

A part on a vibrating track meets a few events every cycle: a slip stops or reverses, static
friction gives way, a contact lifts off, the part lands again. Each is resolved from the part's
contacts alone: the held ones, and at a landing the corners that reached a face. :func:`follow`
runs the whole sequence (collision impulses, force LCP, mode, closed-form phase, its first
event, ...) without returning to Python for each event, which is where
:mod:`feeder_sim.stepping.event_driven.stepper` spends most of its time on such a part.

It stops and leaves the event to ``EventDriven``'s general path wherever that path could see
more than it does: a held corner at the end of its edge or near another edge of its piece, a
corner touching near a corner of a piece or on an edge covered by another piece of its body,
a touching corner of a non-dynamic body, an LCP the pivoting does not solve within tolerance,
a mode without a closed form, or two events within the cascade window. Each step is the one
``EventDriven._settle`` takes for these contacts (same kernels, same tolerances), except that
the LCPs always pivot where the general path first tries the last active set; the two answers
agree to the LCP tolerance.

Contacts are held as :class:`ChainContacts`, arrays with one row per contact.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.arena import heap_arena
from feeder_sim.compiled.jit import inner, jit
from feeder_sim.model.world import DRIVEN, MOVING
from feeder_sim.stepping.event_driven import _kernels as kern


class ChainTolerances(NamedTuple):
    """Thresholds of the chain (``EventDriven`` sets them from its settings)."""

    event_threshold: float     # event function value taken as zero
    slip_tol_mps: float        # slip speed below which a contact sticks, m/s
    touch_m: float             # gap below which a corner touches, m
    lcp_tol: float             # residual an LCP answer must reach
    cascade_window_s: float    # events closer in time count as one cascade, s
    spin_limit: float          # angular speed of a closed-form mode, rad/s
    alpha_limit: float         # angular acceleration of a closed-form mode, rad/s^2
    force_tol: float           # contact force taken as zero, N
    acc_tol: float             # acceleration taken as zero, m/s^2
    near_m: float              # a corner this near another edge leaves the chain, m
    rest_speed_mps: float      # approach speed below which a landing is plastic, m/s
    friction_impulse: float    # 1.0: tangential impulses at collisions, 0.0: none


class BodyArrays(NamedTuple):
    """What the chain needs of every body."""

    dynamic: np.ndarray        # (n,) bool
    inv_mass: np.ndarray       # (n,) 1/kg
    inv_inertia: np.ndarray    # (n,) 1/(kg m^2)
    radius: np.ndarray         # (n,) m
    gravity: np.ndarray        # (2,) m/s^2


class PhaseModel(NamedTuple):
    """How every body moves in a closed-form phase (see ``_kernels.advance``)."""

    kind: np.ndarray               # (n,) FIXED / DRIVEN / MOVING
    index: np.ndarray              # (n,) drive row of a driven body, else -1
    free_acceleration: np.ndarray  # (n, 2) acceleration of a free body, m/s^2
    drives: kern.Drives


class ChainContacts(NamedTuple):
    """Contacts of the chain, one row per contact (vertex, edges and normal local to their
    bodies)."""

    vertex: np.ndarray         # (k,) global vertex index
    edge: np.ndarray           # (k,) global edge index (its first vertex)
    piece: np.ndarray          # (k,) the edge's piece
    body_a: np.ndarray         # (k,) vertex body
    body_b: np.ndarray         # (k,) edge body
    vertex_local: np.ndarray   # (k, 2)
    edge_start: np.ndarray     # (k, 2)
    edge_end: np.ndarray       # (k, 2)
    normal: np.ndarray         # (k, 2)
    mu_static: np.ndarray      # (k,)
    mu_dynamic: np.ndarray     # (k,)
    restitution: np.ndarray    # (k,)


class ChainMode(NamedTuple):
    """The held contacts' friction state and the closed-form phase of their mode."""

    friction: np.ndarray       # (k,) NO_FRICTION / STICK / SLIDE
    sigma: np.ndarray          # (k,) slip direction of a sliding contact
    phi0: np.ndarray           # (n, 2) acceleration without drive terms, m/s^2
    phi1: np.ndarray           # (n, 2, nd) acceleration per unit drive acceleration
    f0: np.ndarray             # (2k,) contact forces without drive terms, N
    f1: np.ndarray             # (2k, nd)


class Near(NamedTuple):
    """Candidate collisions before the held contacts are left out."""

    vertex: np.ndarray         # (c,) global vertex index
    piece: np.ndarray          # (c,) piece it may enter
    arrays: kern.CandidateArrays
    anchor_pos: np.ndarray     # (n, 2) poses at detection, m
    anchor_ang: np.ndarray     # (n,)
    margin: float              # m


class ModeCandidates(NamedTuple):
    """The candidates of a mode: those of :class:`Near` but the held corners on their
    pieces."""

    vertex: np.ndarray
    piece: np.ndarray
    arrays: kern.CandidateArrays


class ChainGeometry(NamedTuple):
    """The bodies' shapes as the chain reads them."""

    verts: np.ndarray          # (V, 2) local vertices
    normals: np.ndarray        # (V, 2) local normal of the edge starting at each vertex
    next_vertex: np.ndarray    # (V,)
    prev_vertex: np.ndarray    # (V,)
    piece_start: np.ndarray    # (P + 1,) first edge of each piece
    edge_length: np.ndarray    # (V,) m
    covered: np.ndarray        # (V,) another piece of its body covers part of the edge


class ImpulseRecord(NamedTuple):
    """Contact impulses the chain transmitted, one row per contact and phase or collision."""

    vertex: np.ndarray
    edge: np.ndarray
    body_a: np.ndarray
    body_b: np.ndarray
    point: np.ndarray          # (m, 2) world point, m
    normal: np.ndarray         # (m, 2)
    normal_impulse: np.ndarray     # (m,) N s
    tangent_impulse: np.ndarray    # (m,) N s


class ChainResult(NamedTuple):
    """What :func:`follow` returns."""

    status: int                # DONE, EVENT or REFRESH
    t: float                   # s
    steps: int
    events: int
    rows: int                  # rows of the impulse record filled
    held: ChainContacts        # the mode that runs on (DONE, REFRESH)
    friction: np.ndarray
    sigma: np.ndarray
    phi0: np.ndarray
    phi1: np.ndarray
    f0: np.ndarray
    f1: np.ndarray
    stats: np.ndarray          # (N_STATS,) by the indices below


DONE, EVENT, REFRESH = kern.DONE, kern.EVENT, kern.REFRESH
# Statistics ``follow`` returns, by index.
(N_LCPS, N_TRIVIAL, LCP_ROWS, MAX_ROWS, MAX_RESIDUAL, MAX_PENETRATION, PIVOTS, IMPACTS,
 ENERGY_FIXES, SLIP_CLOSURES, N_STATS) = range(11)


@jit
def _take(c, idx):
    """The contacts ``idx`` of ``c``."""
    return ChainContacts(c.vertex[idx], c.edge[idx], c.piece[idx], c.body_a[idx],
                         c.body_b[idx], c.vertex_local[idx], c.edge_start[idx],
                         c.edge_end[idx], c.normal[idx], c.mu_static[idx],
                         c.mu_dynamic[idx], c.restitution[idx])


@jit
def _join(c, d):
    """The contacts of ``c`` followed by those of ``d``."""
    return ChainContacts(
        np.concatenate((c.vertex, d.vertex)), np.concatenate((c.edge, d.edge)),
        np.concatenate((c.piece, d.piece)), np.concatenate((c.body_a, d.body_a)),
        np.concatenate((c.body_b, d.body_b)),
        np.concatenate((c.vertex_local, d.vertex_local)),
        np.concatenate((c.edge_start, d.edge_start)), np.concatenate((c.edge_end, d.edge_end)),
        np.concatenate((c.normal, d.normal)), np.concatenate((c.mu_static, d.mu_static)),
        np.concatenate((c.mu_dynamic, d.mu_dynamic)),
        np.concatenate((c.restitution, d.restitution)))


@inner
def _geometry(pos, ang, c):
    """World point, normal, gap and edge parameter of the contacts ``c``."""
    return kern.held_geometry(pos, ang, c.body_a, c.body_b, c.vertex_local, c.edge_start,
                              c.edge_end, c.normal)


@inner
def _arms(pos, c, point):
    """Contact points relative to the vertex body's and the edge body's origin."""
    k = point.shape[0]
    r_a = np.empty((k, 2))
    r_b = np.empty((k, 2))
    for i in range(k):
        for j in range(2):
            r_a[i, j] = point[i, j] - pos[c.body_a[i], j]
            r_b[i, j] = point[i, j] - pos[c.body_b[i], j]
    return r_a, r_b


@inner
def _free_acceleration(t, kind, index, drives, gravity, acc):
    """Every body's acceleration without contact forces: gravity on the dynamic ones, the
    drive's on driven ones, none on the others."""
    dr_u, _, dr_amp, dr_w, dr_phase, t_ref = drives
    for i in range(kind.shape[0]):
        if kind[i] == MOVING:
            acc[i, 0], acc[i, 1] = gravity[0], gravity[1]
        elif kind[i] == DRIVEN:
            d = index[i]
            a = -dr_amp[d] * dr_w[d] * dr_w[d] * math.sin(dr_phase[d] + dr_w[d] * (t - t_ref))
            acc[i, 0], acc[i, 1] = a * dr_u[d, 0], a * dr_u[d, 1]
        else:
            acc[i, 0] = acc[i, 1] = 0.0


@inner
def _segment_distance(px, py, q0x, q0y, q1x, q1y):
    ex, ey = q1x - q0x, q1y - q0y
    s = max(0.0, min(1.0, ((px - q0x) * ex + (py - q0y) * ey) / (ex * ex + ey * ey)))
    return math.hypot(px - q0x - s * ex, py - q0y - s * ey)


@inner
def _edge_ends_fired(g, offset, first, end):
    """True if an edge-parameter event function (``g[first:end]``) is below its level."""
    for j in range(first, end):
        if g[j] + offset[j] < 0.0:
            return True
    return False


@inner
def _touching(pos, ang, held, cands, world, geometry, materials, near_m, touch_m):
    """The contacts contact detection would find at (pos, ang) besides the held ones:
    ``(ok, new contacts)``, not ok where the general path must find them.

    A candidate corner within ``touch_m`` of its piece touches the piece's edge it lies on.
    Not ok: a held corner within ``near_m`` of another edge of its piece, a touching corner
    within ``near_m`` of a second edge line (near the piece's corner), deeper than ``near_m``,
    pointing out of the edge, of a non-dynamic body, on a dynamic piece, or on an edge
    another piece of its body covers."""
    verts, normals, next_vertex, prev_vertex, piece_start, edge_length, covered = geometry
    dynamic = world.dynamic
    mu_s, mu_d, restitution = materials
    c_vertex, c_piece = cands.vertex, cands.piece
    cv_body, cv_local, cp_body, cp_start, cp_end, _, _ = cands.arrays
    nothing = ChainContacts(np.zeros(0, np.int64), np.zeros(0, np.int64),
                            np.zeros(0, np.int64), np.zeros(0, np.int64),
                            np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)),
                            np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0),
                            np.zeros(0))
    for q in range(held.vertex.shape[0]):
        a, b = held.body_a[q], held.body_b[q]
        px, py = kern.world_point(pos, ang, a, held.vertex_local[q])
        p = held.piece[q]
        for e in range(piece_start[p], piece_start[p + 1]):
            if e == held.edge[q]:
                continue
            q0x, q0y = kern.world_point(pos, ang, b, verts[e])
            q1x, q1y = kern.world_point(pos, ang, b, verts[next_vertex[e]])
            if _segment_distance(px, py, q0x, q0y, q1x, q1y) <= near_m:
                return False, nothing
    found = np.zeros(cv_body.shape[0], np.int64)
    edge_of = np.zeros(cv_body.shape[0], np.int64)
    n_new = 0
    for i in range(cv_body.shape[0]):
        if kern._vertex_piece_gap(pos, ang, cv_body[i], cv_local[i], cp_body[i], cp_start[i],
                                  cp_end[i], verts, normals) > touch_m:
            continue
        a, b, v = cv_body[i], cp_body[i], c_vertex[i]
        if not dynamic[a] or dynamic[b]:
            return False, nothing
        px, py = kern.world_point(pos, ang, a, verts[v])
        cb, sb = math.cos(ang[b]), math.sin(ang[b])
        best, second, e_best, nx, ny = -np.inf, -np.inf, -1, 0.0, 0.0
        for e in range(cp_start[i], cp_end[i]):
            d, ex, ey = kern.edge_line_distance(px, py, pos, cb, sb, b, e, verts, normals)
            if d > best:
                best, second, e_best, nx, ny = d, best, e, ex, ey
            elif d > second:
                second = d
        if second > -near_m or best < -near_m or covered[e_best]:
            return False, nothing
        # both neighbours of the corner on the edge's outer side (as contact detection asks)
        for w, edge in ((prev_vertex[v], prev_vertex[v]), (next_vertex[v], v)):
            ux, uy = kern.world_point(pos, ang, a, verts[w])
            if nx * (ux - px) + ny * (uy - py) < -max(touch_m, 1e-9 * edge_length[edge]):
                return False, nothing
        found[n_new], edge_of[n_new] = i, e_best
        n_new += 1
    new_vertex = np.empty(n_new, np.int64)
    new_edge = np.empty(n_new, np.int64)
    new_piece = np.empty(n_new, np.int64)
    new_a = np.empty(n_new, np.int64)
    new_b = np.empty(n_new, np.int64)
    new_mu_s = np.empty(n_new)
    new_mu_d = np.empty(n_new)
    new_e = np.empty(n_new)
    for q in range(n_new):
        i, e = found[q], edge_of[q]
        a, b = cv_body[i], cp_body[i]
        new_vertex[q], new_edge[q], new_piece[q] = c_vertex[i], e, c_piece[i]
        new_a[q], new_b[q] = a, b
        new_mu_s[q], new_mu_d[q], new_e[q] = mu_s[a, b], mu_d[a, b], restitution[a, b]
    return True, ChainContacts(new_vertex, new_edge, new_piece, new_a, new_b,
                               verts[new_vertex], verts[new_edge],
                               verts[next_vertex[new_edge]], normals[new_edge], new_mu_s,
                               new_mu_d, new_e)


@jit
def _record(c, point, normal, p, rec, rows):
    """Stacked contact impulses ``p`` of the contacts ``c`` into ``rec`` from row ``rows``."""
    rec_vertex, rec_edge, rec_a, rec_b, rec_point, rec_normal, rec_pn, rec_pt = rec
    k = point.shape[0]
    for i in range(k):
        r = rows + i
        rec_vertex[r], rec_edge[r] = c.vertex[i], c.edge[i]
        rec_a[r], rec_b[r] = c.body_a[i], c.body_b[i]
        rec_point[r] = point[i]
        rec_normal[r] = normal[i]
        rec_pn[r], rec_pt[r] = p[i], p[k + i]
    return rows + k


@inner
def _count(stats, x, res, pivots):
    """An LCP solved by pivoting into the statistics (``SolverStats.record``)."""
    stats[N_LCPS] += 1
    stats[LCP_ROWS] += x.shape[0]
    stats[MAX_ROWS] = max(stats[MAX_ROWS], x.shape[0])
    stats[MAX_RESIDUAL] = max(stats[MAX_RESIDUAL], res)
    stats[PIVOTS] += pivots


@inner
def _impacts(c, pos, ang, vel, om, world, tols, stats, rec, rows):
    """Collision impulses until no contact approaches (``EventDriven._impact``): velocities
    change in place and each impulse is recorded; ``(ok, rows)``."""
    dynamic, inv_mass, inv_inertia = world.dynamic, world.inv_mass, world.inv_inertia
    slip_tol, lcp_tol = tols.slip_tol_mps, tols.lcp_tol
    rest_speed, friction_impulse = tols.rest_speed_mps, tols.friction_impulse
    k = c.vertex.shape[0]
    point, normal, _, _ = _geometry(pos, ang, c)
    r_a, r_b = _arms(pos, c, point)
    bodies = kern.sorted_unique(heap_arena(), c.body_a)
    no_friction = np.zeros(k, np.int64)
    slave = np.zeros(k)
    for _ in range(20):
        v_n, v_t = kern.relative_velocity(normal, r_a, r_b, c.body_a, c.body_b, vel, om)
        colliding = v_n < -slip_tol * 10
        if not colliding.any():
            break
        ok, J, minv, W = kern.contact_jacobian(normal, r_a, r_b, c.body_a, c.body_b, dynamic,
                                               inv_mass, inv_inertia, bodies)
        if not ok:
            return False, rows
        b_full = kern.impact_rhs(v_n, v_t, c.restitution, rest_speed)
        # Kawachi's rule (time_stepping.friction_rows): the pre-impact slip picks static or
        # dynamic friction, and dynamic friction cannot reverse the slip.
        friction = np.full(k, kern.BOX_ROW, np.int64)
        mu_lo = np.empty(k)
        mu_hi = np.empty(k)
        for i in range(k):
            sliding = abs(v_t[i]) > slip_tol
            mu = c.mu_dynamic[i] if sliding else c.mu_static[i]
            if mu <= 0.0 or friction_impulse == 0.0:
                friction[i] = 0
            mu_lo[i] = 0.0 if sliding and v_t[i] < 0.0 else mu
            mu_hi[i] = 0.0 if sliding and v_t[i] > 0.0 else mu
        p, x, _, res, pivots, _, _ = kern.lcp_dantzig(W, b_full, friction, mu_lo, mu_hi, slave)
        if not res <= lcp_tol:
            return False, rows
        _count(stats, x, res, pivots)
        dv, gain, scale = kern.impulse_effect(J, minv, W, p, v_n, v_t)
        if gain > 1e-9 * max(1e-12, scale):
            # never let a collision create kinetic energy: the frictionless impulse cannot
            stats[ENERGY_FIXES] += 1
            p, x, _, res, pivots, _, _ = kern.lcp_dantzig(W, b_full, no_friction, mu_lo, mu_hi,
                                                          slave)
            if not res <= lcp_tol:
                return False, rows
            _count(stats, x, res, pivots)
            dv = kern.impulse_effect(J, minv, W, p, v_n, v_t)[0]
        for q in range(bodies.shape[0]):
            i = bodies[q]
            vel[i, 0] += dv[q, 0]
            vel[i, 1] += dv[q, 1]
            om[i] += dv[q, 2]
        rows = _record(c, point, normal, p, rec, rows)
        stats[IMPACTS] += 1
    return True, rows


@inner
def _mode_at_event(t, c, pos, ang, vel, om, model, world, tols, acc, stats, rec, rows):
    """The next mode over the contacts ``c`` (``ContactModes.choose``, its slip closure
    recorded from row ``rows`` of ``rec``): ``(ok, contacts kept, friction, sigma, normal,
    r_a, r_b, their LCP normal forces, rows)``; not ok where the general path must decide (a
    contact approaches, the LCP misses)."""
    kind, index, drives = model.kind, model.index, model.drives
    dynamic, inv_mass, inv_inertia, _, gravity = world
    slip_tol, lcp_tol = tols.slip_tol_mps, tols.lcp_tol
    force_tol, acc_tol = tols.force_tol, tols.acc_tol
    k = c.vertex.shape[0]
    point, normal, gap, _ = _geometry(pos, ang, c)
    for i in range(k):
        stats[MAX_PENETRATION] = max(stats[MAX_PENETRATION], -gap[i])
    r_a, r_b = _arms(pos, c, point)
    v_n, v_t = kern.relative_velocity(normal, r_a, r_b, c.body_a, c.body_b, vel, om)
    fail = (False, c, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2)),
            np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), rows)
    zeno = kern.zeno_speed(normal, c.body_a, c.body_b, dynamic, gravity, tols.touch_m)
    for i in range(k):
        # an approach, or a slow normal motion ContactModes.settle closes (Zeno)
        if v_n[i] < -slip_tol * 10 or slip_tol * 1e-2 < abs(v_n[i]) < zeno[i]:
            return fail
    rest = np.flatnonzero(np.abs(v_n) <= slip_tol * 10)
    c = _take(c, rest)
    normal, r_a, r_b = normal[rest], r_a[rest], r_b[rest]
    v_n, v_t = v_n[rest], v_t[rest]
    a, b, mu_s, mu_d = c.body_a, c.body_b, c.mu_static, c.mu_dynamic
    k = rest.shape[0]
    sliding = np.abs(v_t) > slip_tol
    sigma = np.sign(v_t)
    _free_acceleration(t, kind, index, drives, gravity, acc)
    b_full, fr = kern.force_problem(normal, r_a, r_b, a, b, om, acc, v_n, v_t, sliding, mu_s,
                                    mu_d)
    if k == 0 or b_full[:k].min() >= 0.0:
        f = np.zeros(2 * k)
        a_rel = b_full
        if k:
            stats[N_LCPS] += 1
            stats[N_TRIVIAL] += 1
    else:
        ok, _, _, W = kern.contact_jacobian(normal, r_a, r_b, a, b, dynamic, inv_mass,
                                            inv_inertia, kern.sorted_unique(heap_arena(), a))
        if not ok:
            return fail
        f, x, _, res, pivots, _, _ = kern.lcp_dantzig(W, b_full, fr, mu_s, mu_s,
                                                      -sigma * mu_d)
        if not res <= lcp_tol:
            return fail
        _count(stats, x, res, pivots)
        a_rel = W @ f + b_full
    keep, friction, sigma = kern.mode_rows(f, a_rel, fr, mu_s, sigma, force_tol, acc_tol, a, b,
                                           normal)
    kept = np.flatnonzero(keep)
    force_n = f[kept]
    c = _take(c, kept)
    friction, sigma, normal, r_a, r_b = (friction[kept], sigma[kept], normal[kept], r_a[kept],
                                         r_b[kept])
    if kern.slip_left(friction, v_t[kept], slip_tol):
        bodies = kern.sorted_unique(heap_arena(), c.body_a)
        ok, J, minv, W = kern.contact_jacobian(normal, r_a, r_b, c.body_a, c.body_b, dynamic,
                                               inv_mass, inv_inertia, bodies)
        if not ok:
            return fail
        p = kern.stick_closure(W, v_n[kept], v_t[kept], friction)
        dv = minv * (J.T @ p)
        for q in range(bodies.shape[0]):
            i = bodies[q]
            vel[i, 0] += dv[3 * q]
            vel[i, 1] += dv[3 * q + 1]
            om[i] += dv[3 * q + 2]
        rows = _record(c, point[rest][kept], normal, p, rec, rows)
        stats[SLIP_CLOSURES] += 1
    return True, c, friction, sigma, normal, r_a, r_b, force_n, rows


@inner
def _closed_form(c, friction, sigma, normal, r_a, r_b, om, model, world, tols):
    """The phase of the mode (``EventDriven._closed_form``): ``(ok, phi0, phi1, f0, f1)``."""
    kind, index, free_phi0, drives = model
    dynamic, inv_mass, inv_inertia, radius, gravity = world
    n, nd = kind.shape[0], drives.amplitude.shape[0]
    k = c.vertex.shape[0]
    phi0 = free_phi0.copy()
    phi1 = np.zeros((n, 2, nd))
    if k == 0:
        return True, phi0, phi1, np.zeros(0), np.zeros((0, nd))
    ok, bodies, dv, f = kern.closed_form_mode(
        normal, r_a, r_b, c.body_a, c.body_b, dynamic, inv_mass, inv_inertia, friction, sigma,
        c.mu_dynamic, om, radius, tols.spin_limit, tols.alpha_limit, gravity, index, drives.u)
    if not ok:
        return False, phi0, phi1, np.zeros(0), np.zeros((0, nd))
    for q in range(bodies.shape[0]):
        i = bodies[q]
        for j in range(2):
            phi0[i, j] += dv[q, j, 0]
            for d in range(nd):
                phi1[i, j, d] = dv[q, j, 1 + d]
    return True, phi0, phi1, np.ascontiguousarray(f[:, 0]), np.ascontiguousarray(f[:, 1:])


@inner
def _candidates(near, c):
    """The candidates of a mode (vertex, piece, kernel arrays): those of ``near`` but the
    held corners on their pieces."""
    keep = kern.held_mask(near.vertex, near.piece, c.vertex, c.piece)
    a = near.arrays
    return ModeCandidates(near.vertex[keep], near.piece[keep], kern.CandidateArrays(
        a.vertex_body[keep], a.vertex_local[keep], a.piece_body[keep], a.piece_start[keep],
        a.piece_end[keep], a.wedge[keep], a.piece_width[keep]))


@jit
def follow(t0, t_stop, h, state, model, world, held, mode, near, geometry, materials, scales,
           tols, record):
    """Follow the held closed-form mode from t0 to t_stop through the events one body's own
    contacts resolve (module docstring).

    ``state`` (pos, ang, vel, om) is every body's state at t0, updated in place to the returned
    time; ``model`` (:class:`PhaseModel`) and ``world`` (:class:`BodyArrays`) as the stepper
    holds them; ``held`` the mode's contacts (:class:`ChainContacts`) and ``mode``
    (:class:`ChainMode`) their state and phase; ``near`` (:class:`Near`) the candidates before
    the held ones are left out; ``materials`` the (n, n) mu_static, mu_dynamic and restitution
    of body pairs; ``scales`` those of the event functions.

    Every phase's and collision's contact impulses go into ``record`` (:class:`ImpulseRecord`),
    a row per contact.

    Returns a :class:`ChainResult`: status DONE at t_stop, EVENT at an event left to the
    general path (the mode is then void), REFRESH where the candidates must be detected again;
    for DONE and REFRESH the held mode that runs on.
    """
    pos, ang, vel, om = state
    kind, index = model.kind, model.index
    drives = model.drives
    radius = world.radius
    verts, normals = geometry.verts, geometry.normals
    friction, sigma, phi0, phi1, f0, f1 = mode
    threshold, touch_m = tols.event_threshold, tols.touch_m
    cascade_s, near_m = tols.cascade_window_s, tols.near_m
    capacity = record.normal_impulse.shape[0]
    n, nd = pos.shape[0], drives.amplitude.shape[0]
    reach = kern.Reach(near.anchor_pos, near.anchor_ang, radius, 0.5 * near.margin)
    stats = np.zeros(N_STATS)
    acc = np.empty((n, 2))
    p_out, a_out = np.empty((n, 2)), np.empty(n)
    v_out, w_out = np.empty((n, 2)), np.empty(n)
    dvel = np.empty(nd)
    cands = _candidates(near, held)
    t = t0
    steps = events = 0
    rows = np.int64(0)   # never a literal: typing would compile _record and _impacts for it
    while True:
        k = held.vertex.shape[0]
        _, normal, _, _ = _geometry(pos, ang, held)
        group, n_groups = kern.sticking_groups(
            kern.contact_groups(held.body_a, held.body_b, normal), friction)
        n_slide = 0
        for i in range(k):
            n_slide += friction[i] == kern.SLIDE
        contacts = kern.HeldContacts(held.body_a, held.body_b, held.vertex_local,
                                     held.edge_start, held.edge_end, held.normal, f0, f1,
                                     friction, sigma, held.mu_static, group, n_groups)
        bodies = kern.PhaseBodies(kind, index, pos.copy(), ang.copy(), vel.copy(), om.copy(),
                                  phi0, phi1)
        first_param = k + n_groups + n_slide
        g = np.empty(first_param + 2 * k + cands.vertex.shape[0])
        status, t_new, taken, offset = kern.advance_watching(
            t, t_stop, h, threshold, bodies, drives, contacts, cands.arrays, verts, normals,
            scales, reach, p_out, a_out, v_out, w_out, dvel, g)
        steps += taken
        if k:
            impulse = f0 * (t_new - t) + f1 @ dvel
            point, normal, _, _ = _geometry(p_out, a_out, held)
            rows = _record(held, point, normal, impulse, record, rows)
        pos[:], ang[:], vel[:], om[:] = p_out, a_out, v_out, w_out
        started, t = t, t_new
        if status != EVENT or t - started < cascade_s or \
                _edge_ends_fired(g, offset, first_param, first_param + 2 * k):
            break
        ok, new = _touching(pos, ang, held, cands, world, geometry, materials, near_m, touch_m)
        # room for every collision impulse and the next phase
        if not ok or rows + 22 * (k + new.vertex.shape[0]) > capacity:
            break
        c = _join(held, new) if new.vertex.shape[0] else held
        ok, rows = _impacts(c, pos, ang, vel, om, world, tols, stats, record, rows)
        if not ok:
            break
        # the general path chooses the mode again where this cannot: count its LCP only here
        before = stats.copy()
        ok, c, friction_new, sigma_new, normal, r_a, r_b, force_n, rows = _mode_at_event(
            t, c, pos, ang, vel, om, model, world, tols, acc, stats, record, rows)
        if ok:
            ok, phi0_new, phi1_new, f0_new, f1_new = _closed_form(
                c, friction_new, sigma_new, normal, r_a, r_b, om, model, world, tols)
        # a held contact the mode cannot keep (kern.leaving: a block starting to tip on one
        # corner): the general path lets it go and holds what stays (EventDriven._hold)
        if ok and kern.leaving(t, drives, force_n, f0_new, f1_new, tols.force_tol,
                               threshold * scales.force).any():
            ok = False
        if not ok:
            # (a slip closure stays: the general path finds the contacts at rest)
            closures = stats[SLIP_CLOSURES]
            stats[:] = before
            stats[SLIP_CLOSURES] = closures
            break
        held, friction, sigma = c, friction_new, sigma_new
        phi0, phi1, f0, f1 = phi0_new, phi1_new, f0_new, f1_new
        events += 1
        cands = _candidates(near, held)
    return ChainResult(status, t, steps, events, rows, held, friction, sigma, phi0, phi1, f0,
                       f1, stats)
