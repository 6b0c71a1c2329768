"""The closed-form phases of one dynamic body, chained through their mode changes, compiled.

A part sliding or sticking on a vibrating track meets, every cycle, events that change only
its contact mode: a slip stops or reverses, static friction gives way, a contact lifts off.
At such an event the touching contacts are the held ones and none approaches, so the next mode
follows from Baraff's force LCP over them alone. :func:`follow` runs that sequence (force LCP,
mode, closed-form phase, its first event, ...) without returning to Python for each event,
which is where :mod:`feeder_sim.event_driven` spends most of its time on such a part.

It stops, and leaves the event to ``EventDriven``'s general path, at any other event: a
candidate corner within touch, a held corner at the end of its edge or near another edge of
its piece, a contact approaching, a force LCP the pivoting does not solve within tolerance, a
mode without a closed form, or two events within the cascade window. Each step is the one
``EventDriven._settle`` takes for these contacts (same kernels, same tolerances), except that
the force LCP always pivots where the general path first tries the last active set; the two
answers agree to the LCP tolerance.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from feeder_sim import _ed_kernels as kern

_JIT = {'cache': True, 'nogil': True, 'error_model': 'numpy'}

DONE, EVENT, REFRESH = kern.DONE, kern.EVENT, kern.REFRESH
PAUSE = 3         # the impulse record is full: the next phase starts in the next call


@numba.njit(**_JIT)
def _free_acceleration(t, kind, index, drives, gravity, acc):
    """Every body's acceleration without contact forces: gravity on the dynamic ones, the
    drive's on driven ones, none on the others."""
    dr_u, _, dr_amp, dr_w, dr_phase, t_ref = drives
    for i in range(kind.shape[0]):
        if kind[i] == kern.MOVING:
            acc[i, 0], acc[i, 1] = gravity[0], gravity[1]
        elif kind[i] == kern.DRIVEN:
            d = index[i]
            a = -dr_amp[d] * dr_w[d] * dr_w[d] * math.sin(dr_phase[d] + dr_w[d] * (t - t_ref))
            acc[i, 0], acc[i, 1] = a * dr_u[d, 0], a * dr_u[d, 1]
        else:
            acc[i, 0] = acc[i, 1] = 0.0


@numba.njit(**_JIT)
def _segment_distance(px, py, q0x, q0y, q1x, q1y):
    ex, ey = q1x - q0x, q1y - q0y
    s = max(0.0, min(1.0, ((px - q0x) * ex + (py - q0y) * ey) / (ex * ex + ey * ey)))
    return math.hypot(px - q0x - s * ex, py - q0y - s * ey)


@numba.njit(**_JIT)
def _only_held_touch(pos, ang, sel, held, f_edge, f_piece, geometry, cands, near_m, touch_m):
    """True if the held contacts ``sel`` are all that touch: no candidate corner within
    ``touch_m`` of its piece and no held corner within ``near_m`` of another edge of its
    piece (contact detection could pair them then)."""
    verts, normals, next_vertex, piece_start = geometry
    cv_body, cv_local, cp_body, cp_start, cp_end, _, _ = cands
    for i in range(cv_body.shape[0]):
        if kern._vertex_piece_gap(pos, ang, cv_body[i], cv_local[i], cp_body[i], cp_start[i],
                                  cp_end[i], verts, normals) <= touch_m:
            return False
    c_a, c_b, vloc = held[0], held[1], held[2]
    for q in range(sel.shape[0]):
        i = sel[q]
        px, py = kern.world_point(pos, ang, c_a[i], vloc[i])
        p = f_piece[i]
        for e in range(piece_start[p], piece_start[p + 1]):
            if e == f_edge[i]:
                continue
            q0x, q0y = kern.world_point(pos, ang, c_b[i], verts[e])
            q1x, q1y = kern.world_point(pos, ang, c_b[i], verts[next_vertex[e]])
            if _segment_distance(px, py, q0x, q0y, q1x, q1y) <= near_m:
                return False
    return True


@numba.njit(**_JIT)
def _regular(g, offset, first_geometric):
    """True if every event function below its level is a force, friction-cone or slip one."""
    for j in range(first_geometric, g.shape[0]):
        if g[j] + offset[j] < 0.0:
            return False
    return True


@numba.njit(**_JIT)
def _mode_at_event(t, sel, pos, ang, vel, om, model, world, held, f_mu_s, f_mu_d, tols,
                   acc, lcp_stats):
    """The next mode over the held contacts ``sel`` at an event (``EventDriven._settle``):
    ``(ok, sel, friction, sigma, normal, r_a, r_b)``; not ok where the general path must
    decide (a contact approaches, the LCP misses)."""
    kind, index, drives = model[0], model[1], model[3]
    dynamic, inv_mass, inv_inertia, gravity = world[0], world[1], world[2], world[4]
    slip_tol, lcp_tol, force_tol, acc_tol = tols[1], tols[3], tols[7], tols[8]
    c_a, c_b, vloc, q0loc, q1loc, nloc = held[0], held[1], held[2], held[3], held[4], held[5]
    k = sel.shape[0]
    point, normal, gap, _ = kern.held_geometry(pos, ang, c_a[sel], c_b[sel], vloc[sel],
                                               q0loc[sel], q1loc[sel], nloc[sel])
    for i in range(k):
        lcp_stats[5] = max(lcp_stats[5], -gap[i])
    a, b = c_a[sel], c_b[sel]
    r_a = np.empty((k, 2))
    r_b = np.empty((k, 2))
    for i in range(k):
        for j in range(2):
            r_a[i, j] = point[i, j] - pos[a[i], j]
            r_b[i, j] = point[i, j] - pos[b[i], j]
    v_n, v_t = kern.relative_velocity(normal, r_a, r_b, a, b, vel, om)
    none_i = np.zeros(0, np.int64)
    none_f = np.zeros(0)
    fail = (False, none_i, none_i, none_f, np.zeros((0, 2)), np.zeros((0, 2)),
            np.zeros((0, 2)))
    n_rest = 0
    for i in range(k):
        if v_n[i] < -slip_tol * 10:
            return fail
        if abs(v_n[i]) <= slip_tol * 10:
            n_rest += 1
    rest = np.empty(n_rest, np.int64)
    n_rest = 0
    for i in range(k):
        if abs(v_n[i]) <= slip_tol * 10:
            rest[n_rest] = i
            n_rest += 1
    normal, r_a, r_b, a, b = normal[rest], r_a[rest], r_b[rest], a[rest], b[rest]
    v_n, v_t = v_n[rest], v_t[rest]
    sel = sel[rest]
    mu_s, mu_d = f_mu_s[sel], f_mu_d[sel]
    k = n_rest
    sliding = np.abs(v_t) > slip_tol
    sigma = np.sign(v_t)
    _free_acceleration(t, kind, index, drives, gravity, acc)
    b_full, fr = kern.force_problem(normal, r_a, r_b, a, b, om, acc, v_n, v_t, sliding, mu_s,
                                    mu_d)
    lcp_stats[0] += 1
    if k == 0 or b_full[:k].min() >= 0.0:
        lcp_stats[1] += 1
        f = np.zeros(2 * k)
        a_rel = b_full
    else:
        bodies = np.unique(a)
        ok, _, _, W = kern.contact_jacobian(normal, r_a, r_b, a, b, dynamic, inv_mass,
                                            inv_inertia, bodies)
        if not ok:
            lcp_stats[0] -= 1
            return fail
        f, x, _, res, pivots, _, _ = kern.lcp_dantzig(W, b_full, fr, mu_s, mu_s,
                                                      -sigma * mu_d)
        if not res <= lcp_tol:
            lcp_stats[0] -= 1
            return fail
        m = x.shape[0]
        lcp_stats[2] += m
        lcp_stats[3] = max(lcp_stats[3], m)
        lcp_stats[4] = max(lcp_stats[4], res)
        lcp_stats[6] += pivots
        a_rel = W @ f + b_full
    keep, friction, sigma = kern.mode_rows(f, a_rel, fr, mu_s, sigma, force_tol, acc_tol)
    kept = np.flatnonzero(keep)
    return (True, sel[kept], friction[kept], sigma[kept], normal[kept], r_a[kept],
            r_b[kept])


@numba.njit(**_JIT)
def _closed_form(sel, friction, sigma, normal, r_a, r_b, om, model, world, held, f_mu_d,
                 tols):
    """The phase of the mode (``EventDriven._closed_form``): ``(ok, phi0, phi1, f0, f1)``."""
    kind, index, free_phi0, drives = model
    dynamic, inv_mass, inv_inertia, radius, gravity = world
    n, nd = kind.shape[0], drives[2].shape[0]
    k = sel.shape[0]
    phi0 = free_phi0.copy()
    phi1 = np.zeros((n, 2, nd))
    if k == 0:
        return True, phi0, phi1, np.zeros(0), np.zeros((0, nd))
    a, b = held[0][sel], held[1][sel]
    for i in range(k):
        if not dynamic[a[i]] or dynamic[b[i]]:
            return False, phi0, phi1, np.zeros(0), np.zeros((0, nd))
    ok, bodies, dv, f = kern.closed_form_mode(
        normal, r_a, r_b, a, b, dynamic, inv_mass, inv_inertia, friction, sigma, f_mu_d[sel],
        om, radius, tols[5], tols[6], gravity, index, drives[0])
    if not ok:
        return False, phi0, phi1, np.zeros(0), np.zeros((0, nd))
    for q in range(bodies.shape[0]):
        i = bodies[q]
        for j in range(2):
            phi0[i, j] += dv[q, j, 0]
            for d in range(nd):
                phi1[i, j, d] = dv[q, j, 1 + d]
    return True, phi0, phi1, np.ascontiguousarray(f[:, 0]), np.ascontiguousarray(f[:, 1:])


@numba.njit(**_JIT)
def _candidates(near, f_vertex, f_piece, sel):
    """The candidates of a mode: those of ``near`` but the held corners on their pieces."""
    keep = kern.held_mask(near[0], near[1], f_vertex[sel], f_piece[sel])
    c = near[2]
    return (c[0][keep], c[1][keep], c[2][keep], c[3][keep], c[4][keep], c[5][keep],
            c[6][keep])


@numba.njit(**_JIT)
def follow(t0, t_stop, h, state, model, world, held, features, mode, near, geometry, scales,
           tols, record):
    """Follow the held closed-form mode from t0 to t_stop through the mode changes that need
    nothing but the held contacts (module docstring).

    ``state`` (pos, ang, vel, om) is every body's state at t0, updated in place to the returned
    time. ``model`` (kind, index, free acceleration, drives) and ``world`` (dynamic, inverse
    mass and inertia, radius, gravity) as ``EventDriven`` holds them. ``held`` are the kernel
    arrays of the mode's contacts (the first six of ``_Mode.held``) and ``features`` their
    (vertex, edge, piece, mu_static, mu_dynamic); ``mode`` (friction, sigma, phi0, phi1, f0, f1)
    the held mode and its phase. ``near`` (vertex, piece, kernel arrays, anchor position,
    anchor angle, margin) the candidates before the held ones are left out. ``geometry`` is
    (verts, normals, next vertex, piece start); ``scales`` the event functions' (force, speed,
    gap); ``tols`` (event threshold, slip tolerance, touch, LCP tolerance, cascade window,
    spin limit, angular acceleration limit, force and acceleration tolerances of a mode,
    nearness of a held corner to another edge).

    Every phase's contact impulses go into ``record`` (vertex, edge, body_a, body_b, point,
    normal, normal impulse, tangential impulse), a row per contact.

    Returns ``(status, t, steps, events, rows, sel, friction, sigma, phi0, phi1, f0, f1,
    stats)``: DONE at t_stop, EVENT at an event left to the general path (the mode is then
    void), REFRESH where the candidates must be detected again, PAUSE with the record full; for
    all but EVENT the held mode is ``sel`` (rows of ``held``) with its friction, slip direction
    and phase. ``stats``: force LCPs, trivial ones, rows, largest rows, largest residual,
    deepest penetration (m), pivots.
    """
    pos, ang, vel, om = state
    kind, index = model[0], model[1]
    drives = model[3]
    radius = world[3]
    verts, normals = geometry[0], geometry[1]
    f_vertex, f_edge, f_piece, f_mu_s, f_mu_d = features
    friction, sigma, phi0, phi1, f0, f1 = mode
    rec_vertex, rec_edge, rec_a, rec_b, rec_point, rec_normal, rec_pn, rec_pt = record
    threshold, touch_m, cascade_s, near_m = tols[0], tols[2], tols[4], tols[9]
    n, nd = pos.shape[0], drives[2].shape[0]
    reach = (near[3], near[4], radius, 0.5 * near[5])
    stats = np.zeros(7)
    acc = np.empty((n, 2))
    p_out, a_out = np.empty((n, 2)), np.empty(n)
    v_out, w_out = np.empty((n, 2)), np.empty(n)
    dvel = np.empty(nd)
    sel = np.arange(held[0].shape[0])
    cands = _candidates(near, f_vertex, f_piece, sel)
    t = t0
    steps = events = rows = 0
    while True:
        k = sel.shape[0]
        c_a, c_b = held[0][sel], held[1][sel]
        vloc, q0loc, q1loc, nloc = held[2][sel], held[3][sel], held[4][sel], held[5][sel]
        _, normal, _, _ = kern.held_geometry(pos, ang, c_a, c_b, vloc, q0loc, q1loc, nloc)
        group, n_groups = kern.sticking_groups(kern.contact_groups(c_a, c_b, normal), friction)
        n_slide = 0
        for i in range(k):
            n_slide += friction[i] == kern.SLIDE
        contacts = (c_a, c_b, vloc, q0loc, q1loc, nloc, f0, f1, friction, sigma, f_mu_s[sel],
                    group, n_groups)
        bodies = (kind, index, pos.copy(), ang.copy(), vel.copy(), om.copy(), phi0, phi1)
        first_geometric = k + n_groups + n_slide
        g = np.empty(first_geometric + 2 * k + cands[0].shape[0])
        status, t_new, taken, offset = kern.advance_watching(
            t, t_stop, h, threshold, bodies, drives, contacts, cands, verts, normals, scales,
            reach, p_out, a_out, v_out, w_out, dvel, g)
        steps += taken
        if k:
            for i in range(k):
                s = sel[i]
                rec_vertex[rows], rec_edge[rows] = f_vertex[s], f_edge[s]
                rec_a[rows], rec_b[rows] = c_a[i], c_b[i]
                rec_pn[rows] = f0[i] * (t_new - t)
                rec_pt[rows] = f0[k + i] * (t_new - t)
                for d in range(nd):
                    rec_pn[rows] += f1[i, d] * dvel[d]
                    rec_pt[rows] += f1[k + i, d] * dvel[d]
                rows += 1
            point, normal, _, _ = kern.held_geometry(p_out, a_out, c_a, c_b, vloc, q0loc,
                                                     q1loc, nloc)
            rec_point[rows - k:rows] = point
            rec_normal[rows - k:rows] = normal
        pos[:], ang[:], vel[:], om[:] = p_out, a_out, v_out, w_out
        started, t = t, t_new
        if status != EVENT:
            break
        if t - started < cascade_s or not _regular(g, offset, first_geometric) or \
                not _only_held_touch(pos, ang, sel, held, f_edge, f_piece, geometry, cands,
                                     near_m, touch_m):
            break
        ok, sel, friction, sigma, normal, r_a, r_b = _mode_at_event(
            t, sel, pos, ang, vel, om, model, world, held, f_mu_s, f_mu_d, tols, acc, stats)
        if not ok:
            break
        ok, phi0, phi1, f0, f1 = _closed_form(sel, friction, sigma, normal, r_a, r_b, om,
                                              model, world, held, f_mu_d, tols)
        if not ok:
            break
        events += 1
        cands = _candidates(near, f_vertex, f_piece, sel)
        if rows + sel.shape[0] > rec_pn.shape[0]:
            status = PAUSE
            break
    return (status, t, steps, events, rows, sel, friction, sigma, phi0, phi1, f0, f1,
            stats)
