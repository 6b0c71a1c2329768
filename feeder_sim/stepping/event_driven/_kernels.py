"""Numba kernels of the event-driven method (:mod:`feeder_sim.stepping.event_driven.stepper`).

* Closed-form phases (``advance``): bodies are FIXED (static or undriven, pose constant),
  DRIVEN (pose from a sinusoidal drive ``d(t) = A sin(phase + w (t - t_ref))`` along ``u``) or
  MOVING (dynamic: the anchor state at ``t0`` and the acceleration ``phi0 + phi1 @ s(t)``, with
  ``s`` the drives' scalar accelerations; the angle advances at the anchor's constant rate).
  Held contacts carry their forces ``f0 + f1 @ s(t)`` (normal rows, then tangential rows).
* Candidate collisions: an active corner against a convex piece, whose gap is the largest
  signed distance of the corner from the piece's edge lines (< 0 only inside the piece),
  leaving out lines the corner lies flush on with its own piece on their inner side.
  Candidate arrays: vertex body, local coordinates, piece body, first and end edge, the
  corner's two edge vectors (local, ``(c, 2, 2)``) and the piece's minimum width (m).
* Small contact systems: Jacobian and Delassus matrix, the boxed LCP of
  :func:`feeder_sim.contact.dynamics.assemble`, an LCP solved on a given active set and its
  residual,
  the force LCP's right-hand side and the mode it implies.
* Integrated phases: the held mode's right-hand side, event functions and forces
  (``mode_rhs``) and Dormand–Prince 5(4) steps (``dopri_step``).

All kernels are compiled with ``cache=True``: the first run on a machine compiles them, once
(``benchmarks/compile.py`` measures it); later runs load the cached machine code.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.arena import heap_arena
from feeder_sim.compiled.jit import inner, jit
from feeder_sim.contact._collision_kernels import sorted_unique
from feeder_sim.contact._lcp_kernels import BOX_ROW, reduce_lcp, SLAVED_ROW
from feeder_sim.contact._lcp_kernels import lcp_dantzig as lcp_dantzig
from feeder_sim.contact._lcp_kernels import lcp_known_pattern as lcp_known_pattern
from feeder_sim.contact._lcp_kernels import lcp_pattern as lcp_pattern
from feeder_sim.contact.candidates import world_point
from feeder_sim.model.world import DRIVEN, FIXED

DONE, EVENT, REFRESH = 0, 1, 2
NO_FRICTION, STICK, SLIDE = 0, 1, 2
# A corner within FLUSH_M (m) of an edge line whose edges leave it at most FLUSH_ANGLE (rad)
# outwards of that line lies flush on it (``_flush``). FLUSH_M is ten times the depth at which
# a collision event fires (1e-12 m), so a corner that drifts by round-off stays flush.
FLUSH_M = 1e-11
FLUSH_ANGLE = 1e-9


class Drives(NamedTuple):
    """The sinusoidal drives of a closed-form phase, ``d(t) = A sin(phase + w (t - t_ref))``
    along ``u``."""

    u: np.ndarray              # (nd, 2) direction
    base: np.ndarray           # (nd, 2) position of the driven body at d = 0, m
    amplitude: np.ndarray      # (nd,) m
    omega: np.ndarray          # (nd,) rad/s
    phase: np.ndarray          # (nd,) rad at t_ref
    t_ref: float               # s


class PhaseBodies(NamedTuple):
    """Every body of a closed-form phase: its kind and the anchor state at the phase start."""

    kind: np.ndarray           # (n,) FIXED / DRIVEN / MOVING
    index: np.ndarray          # (n,) drive of a DRIVEN body
    pos0: np.ndarray           # (n, 2) m
    ang0: np.ndarray           # (n,) rad
    vel0: np.ndarray           # (n, 2) m/s
    om0: np.ndarray            # (n,) rad/s
    phi0: np.ndarray           # (n, 2) acceleration without drive terms, m/s^2
    phi1: np.ndarray           # (n, 2, nd) acceleration per unit drive acceleration


class HeldContacts(NamedTuple):
    """The held contacts of a mode (vertex and edge local to their bodies), their force
    coefficients in a closed-form phase and their friction state."""

    body_a: np.ndarray         # (k,) vertex body
    body_b: np.ndarray         # (k,) edge body
    vertex: np.ndarray         # (k, 2)
    edge_start: np.ndarray     # (k, 2)
    edge_end: np.ndarray       # (k, 2)
    normal: np.ndarray         # (k, 2) the edge's outward normal
    f0: np.ndarray             # (2k,) forces without drive terms, N (empty when integrated)
    f1: np.ndarray             # (2k, nd) forces per unit drive acceleration
    friction: np.ndarray       # (k,) NO_FRICTION / STICK / SLIDE
    sigma: np.ndarray          # (k,) slip direction of a sliding contact
    mu_static: np.ndarray      # (k,)
    group: np.ndarray          # (k,) sticking group, renumbered 0.. (-1: not sticking)
    n_groups: int


class CandidateArrays(NamedTuple):
    """Candidate collisions: an active corner against a convex piece of another body."""

    vertex_body: np.ndarray    # (c,)
    vertex_local: np.ndarray   # (c, 2) the corner in its body's frame, m
    piece_body: np.ndarray     # (c,)
    piece_start: np.ndarray    # (c,) first edge of the piece
    piece_end: np.ndarray      # (c,) one past its last edge
    wedge: np.ndarray          # (c, 2, 2) the corner's two edge vectors, local
    piece_width: np.ndarray    # (c,) the piece's minimum width, m


class EventScales(NamedTuple):
    """What the event functions are divided by to be O(1)."""

    force: float               # N
    speed: float               # m/s
    gap: float                 # m


class Reach(NamedTuple):
    """How far bodies may move from where the candidates were detected."""

    anchor_pos: np.ndarray     # (n, 2) m
    anchor_ang: np.ndarray     # (n,) rad
    radius: np.ndarray         # (n,) m
    limit: float               # m


class RhsSpec(NamedTuple):
    """Everything the compiled right-hand side of an integrated mode reads (``mode_rhs``)."""

    dyn: np.ndarray            # (nd,) dynamic bodies
    col: np.ndarray            # (n,) first Jacobian column of a dynamic body, else -1
    kind: np.ndarray           # (n,) FIXED / DRIVEN / MOVING
    index: np.ndarray          # (n,) drive of a DRIVEN body
    pos_fixed: np.ndarray      # (n, 2) pose of the fixed bodies, m
    ang_fixed: np.ndarray      # (n,)
    drives: Drives
    gravity: np.ndarray        # (2,) m/s^2
    inv_mass: np.ndarray       # (n,) 1/kg
    inv_inertia: np.ndarray    # (n,) 1/(kg m^2)
    contacts: HeldContacts
    mu_dynamic: np.ndarray     # (k,)
    cands: CandidateArrays | None
    verts: np.ndarray
    normals: np.ndarray
    scales: EventScales


@jit
def _poses(t, t0, kind, index, pos0, ang0, vel0, om0, phi0, phi1, dr_u, dr_base, dr_amp,
           dr_w, dr_phase, t_ref, pos, ang, vel, om, acc_drive, dvel_drive):
    """Poses and velocities of every body at t; drive accelerations and velocity changes."""
    tau = t - t0
    nd = dr_amp.shape[0]
    disp = np.empty(nd)
    dval = np.empty(nd)
    vval = np.empty(nd)
    for d in range(nd):
        a, w = dr_amp[d], dr_w[d]
        ph, ph0 = dr_phase[d] + w * (t - t_ref), dr_phase[d] + w * (t0 - t_ref)
        s, c = math.sin(ph), math.cos(ph)
        d0, v0 = a * math.sin(ph0), a * w * math.cos(ph0)
        dval[d], vval[d] = a * s, a * w * c
        acc_drive[d] = -a * w * w * s
        disp[d] = dval[d] - d0 - v0 * tau
        dvel_drive[d] = vval[d] - v0
    for i in range(kind.shape[0]):
        k = kind[i]
        if k == FIXED:
            pos[i, 0], pos[i, 1] = pos0[i, 0], pos0[i, 1]
            vel[i, 0], vel[i, 1] = vel0[i, 0], vel0[i, 1]
            ang[i], om[i] = ang0[i], om0[i]
        elif k == DRIVEN:
            d = index[i]
            for j in range(2):
                pos[i, j] = dr_base[d, j] + dval[d] * dr_u[d, j]
                vel[i, j] = vval[d] * dr_u[d, j]
            ang[i], om[i] = ang0[i], 0.0
        else:
            for j in range(2):
                p = pos0[i, j] + tau * (vel0[i, j] + 0.5 * tau * phi0[i, j])
                v = vel0[i, j] + tau * phi0[i, j]
                for d in range(nd):
                    p += phi1[i, j, d] * disp[d]
                    v += phi1[i, j, d] * dvel_drive[d]
                pos[i, j], vel[i, j] = p, v
            ang[i] = ang0[i] + om0[i] * tau
            om[i] = om0[i]


@inner
def edge_line_distance(px, py, pos, c, s, pbody, j, verts, normals):
    """Signed distance (m) of the world point (px, py) from the line of edge ``j`` of body
    ``pbody`` (turned by cos c, sin s), and the edge's world normal."""
    qx = pos[pbody, 0] + c * verts[j, 0] - s * verts[j, 1]
    qy = pos[pbody, 1] + s * verts[j, 0] + c * verts[j, 1]
    nx = c * normals[j, 0] - s * normals[j, 1]
    ny = s * normals[j, 0] + c * normals[j, 1]
    return nx * (px - qx) + ny * (py - qy), nx, ny


@inner
def _vertex_piece_gap(pos, ang, vbody, local, pbody, start, end, verts, normals):
    """Largest signed distance (m) of a corner from a convex piece's edge lines."""
    px, py = world_point(pos, ang, vbody, local)
    c, s = math.cos(ang[pbody]), math.sin(ang[pbody])
    best = -np.inf
    for j in range(start, end):
        d = edge_line_distance(px, py, pos, c, s, pbody, j, verts, normals)[0]
        if d > best:
            best = d
    return best


@inner
def _gap_off_flush(pos, ang, vbody, local, wedge, pbody, start, end, verts, normals, best):
    """Collision gap (m) of a corner whose largest distance ``best`` from a convex piece's
    edge lines is within FLUSH_M of 0: the largest distance from the lines it does not lie
    flush on (see ``_flush``), or ``best`` if it lies flush on every one.

    Leaving out lines within FLUSH_M changes nothing when the largest distance is farther
    than that from 0, so the callers test ``abs(best) <= FLUSH_M`` inline and call this only
    then: the plain largest distance is the hot loop of every step."""
    px, py = world_point(pos, ang, vbody, local)
    ca, sa = math.cos(ang[vbody]), math.sin(ang[vbody])
    c, s = math.cos(ang[pbody]), math.sin(ang[pbody])
    inner = -np.inf
    for j in range(start, end):
        d, nx, ny = edge_line_distance(px, py, pos, c, s, pbody, j, verts, normals)
        if d > inner and not (abs(d) <= FLUSH_M and _flush(ca, sa, wedge, nx, ny)):
            inner = d
    return inner if inner > -np.inf else best


@inner
def _flush(c, s, wedge, nx, ny):
    """True if the corner's piece lies on the inner side of the edge line (normal n) through
    it: both edges leaving the corner run along the line or into the other piece.

    Such a line does not show the corner outside: a block sliding face-on into an identical
    one with aligned corners has every corner exactly on the line of a side face of the other
    block while the faces overlap, so the largest distance stays 0 and the overlap is never
    seen. ``c, s``: cosine and sine of the corner's body angle."""
    for i in range(2):
        ex = c * wedge[i, 0] - s * wedge[i, 1]
        ey = s * wedge[i, 0] + c * wedge[i, 1]
        if nx * ex + ny * ey > FLUSH_ANGLE * math.sqrt(ex * ex + ey * ey):
            return False
    return True


@jit
def candidate_gaps(pos, ang, cands, verts, normals, out):
    """Gap (m) of every candidate vertex against its piece: > 0 outside, < 0 inside."""
    for i in range(cands.vertex_body.shape[0]):
        out[i] = _candidate_gap(pos, ang, cands, i, verts, normals)


@inner
def _candidate_gap(pos, ang, cands, i, verts, normals):
    """Collision gap (m) of candidate ``i``: the corner's largest distance from its piece's
    edge lines, leaving out those it lies flush on (``_gap_off_flush``)."""
    cv_body, cv_local, cp_body, cp_start, cp_end, cv_wedge, _ = cands
    d = _vertex_piece_gap(pos, ang, cv_body[i], cv_local[i], cp_body[i], cp_start[i],
                          cp_end[i], verts, normals)
    if abs(d) <= FLUSH_M:
        d = _gap_off_flush(pos, ang, cv_body[i], cv_local[i], cv_wedge[i], cp_body[i],
                           cp_start[i], cp_end[i], verts, normals, d)
    return d


@inner
def _geometric_events(params, cands, pos, ang, verts, normals, gap_scale, g, j):
    """The last event functions of a held mode from ``g[j]`` on: each held contact's edge
    parameter and its distance from 1 (both must stay >= 0), then each candidate's gap in
    units of ``gap_scale`` (m)."""
    for i in range(params.shape[0]):
        g[j] = params[i]
        j += 1
    for i in range(params.shape[0]):
        g[j] = 1.0 - params[i]
        j += 1
    for i in range(cands.vertex_body.shape[0]):
        g[j] = _candidate_gap(pos, ang, cands, i, verts, normals) / gap_scale
        j += 1


@inner
def _contact_geometry(pos, ang, vel, om, a, b, vloc, q0loc, q1loc, nloc):
    """Edge parameter, tangential relative velocity, point and normal of one contact."""
    px, py = world_point(pos, ang, a, vloc)
    q0x, q0y = world_point(pos, ang, b, q0loc)
    q1x, q1y = world_point(pos, ang, b, q1loc)
    cb, sb = math.cos(ang[b]), math.sin(ang[b])
    nx, ny = cb * nloc[0] - sb * nloc[1], sb * nloc[0] + cb * nloc[1]
    ex, ey = q1x - q0x, q1y - q0y
    param = ((px - q0x) * ex + (py - q0y) * ey) / (ex * ex + ey * ey)
    gap = nx * (px - q0x) + ny * (py - q0y)
    rax, ray = px - pos[a, 0], py - pos[a, 1]
    rbx, rby = px - pos[b, 0], py - pos[b, 1]
    relx = (vel[a, 0] - om[a] * ray) - (vel[b, 0] - om[b] * rby)
    rely = (vel[a, 1] + om[a] * rax) - (vel[b, 1] + om[b] * rbx)
    v_t = -ny * relx + nx * rely
    return param, v_t, gap, px, py, nx, ny


@inner
def _force_events(f, k, mu_s, group, n_groups, force_scale, g):
    """The first event functions of a held mode: each normal force (must stay >= 0), then each
    sticking group's friction-cone margin; returns the next free index of ``g``."""
    j = 0
    for i in range(k):
        g[j] = f[i] / force_scale
        j += 1
    sum_n = np.zeros(n_groups)
    sum_t = np.zeros(n_groups)
    for i in range(k):
        if group[i] >= 0:
            sum_n[group[i]] += f[i] * mu_s[i]
            sum_t[group[i]] += f[k + i]
    for q in range(n_groups):
        g[j] = (sum_n[q] - abs(sum_t[q])) / force_scale
        j += 1
    return j


@inner
def _events(t, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang, vel, om,
            acc_drive, dvel_drive, g):
    kind, index, pos0, ang0, vel0, om0, phi0, phi1 = bodies
    dr_u, dr_base, dr_amp, dr_w, dr_phase, t_ref = drives
    (c_a, c_b, vloc, q0loc, q1loc, nloc, f0, f1, friction, sigma, mu_s, group,
     n_groups) = contacts
    force_scale, speed_scale, gap_scale = scales
    _poses(t, t0, kind, index, pos0, ang0, vel0, om0, phi0, phi1, dr_u, dr_base, dr_amp, dr_w,
           dr_phase, t_ref, pos, ang, vel, om, acc_drive, dvel_drive)
    k = c_a.shape[0]
    nd = dr_amp.shape[0]
    f = np.empty(2 * k)
    for r in range(2 * k):
        v = f0[r]
        for d in range(nd):
            v += f1[r, d] * acc_drive[d]
        f[r] = v
    j = _force_events(f, k, mu_s, group, n_groups, force_scale, g)
    params = np.empty(k)
    for i in range(k):
        param, v_t, _, _, _, _, _ = _contact_geometry(pos, ang, vel, om, c_a[i], c_b[i],
                                                      vloc[i], q0loc[i], q1loc[i], nloc[i])
        params[i] = param
        if friction[i] == SLIDE:
            g[j] = sigma[i] * v_t / speed_scale
            j += 1
    _geometric_events(params, cands, pos, ang, verts, normals, gap_scale, g, j)


@inner
def _speed_bounds(h, bodies, drives, vel, om, speed, turn):
    """Every body's largest translational speed (m/s) and turning rate (rad/s) over the next
    h of a closed-form phase, into ``speed`` and ``turn``."""
    kind, index, _, _, _, _, phi0, phi1 = bodies
    _, _, dr_amp, dr_w, _, _ = drives
    nd = dr_amp.shape[0]
    for i in range(kind.shape[0]):
        k = kind[i]
        if k == FIXED:
            speed[i], turn[i] = 0.0, 0.0
        elif k == DRIVEN:
            speed[i], turn[i] = abs(dr_amp[index[i]] * dr_w[index[i]]), 0.0
        else:
            v = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2) + h * (
                math.sqrt(phi0[i, 0] ** 2 + phi0[i, 1] ** 2))
            for d in range(nd):
                change = min(2.0, h * abs(dr_w[d])) * abs(dr_amp[d] * dr_w[d])
                v += change * math.sqrt(phi1[i, 0, d] ** 2 + phi1[i, 1, d] ** 2)
            speed[i], turn[i] = v, abs(om[i])


@jit
def _within_reach(h, kind, pos, ang, speed, turn, reach):
    """True if no body can get farther than its reach from the candidates' anchor in h."""
    anchor_pos, anchor_ang, radius, limit = reach
    for i in range(kind.shape[0]):
        if kind[i] == FIXED:
            continue
        dx, dy = pos[i, 0] - anchor_pos[i, 0], pos[i, 1] - anchor_pos[i, 1]
        moved = math.sqrt(dx * dx + dy * dy) + abs(ang[i] - anchor_ang[i]) * radius[i]
        if moved + h * (speed[i] + turn[i] * radius[i]) > limit:
            return False
    return True


@jit
def guarded_step(h, pos, ang, speed, turn, cands, g, first, offset, gap_scale):
    """The largest step <= h over which no candidate corner can travel, relative to its piece,
    farther than its gap plus half the piece's minimum width (conservative advancement).

    A corner is at least its gap away from the piece, measured in the piece's frame, and must
    travel that far to reach it and then the piece's width to pass through it. Within such
    a step it can neither pass through a piece nor enter one deeper than a quarter of its
    width and leave again between the step's ends, where the events are tested. A corner far
    from every piece or slow does not shorten the step.

    ``speed`` and ``turn`` bound every body's translational speed (m/s) and turning rate
    (rad/s) over h; the candidates' event functions at the step start are ``g[first:]`` with
    ``offset[first:]`` added (see ``event_offsets``), in units of ``gap_scale`` (m)."""
    cv_body, cv_local, cp_body, _, _, _, cp_width = cands
    for i in range(cv_body.shape[0]):
        a, b = cv_body[i], cp_body[i]
        arm = math.sqrt(cv_local[i, 0] ** 2 + cv_local[i, 1] ** 2)
        # Speed of the corner in the piece's frame: its own, the piece's, and the piece's
        # turning at the corner's distance from the piece's origin, which grows in the step
        # (bounded without trigonometry: this runs every step).
        closing = speed[a] + turn[a] * arm + speed[b]
        reach = math.sqrt((pos[a, 0] - pos[b, 0]) ** 2 + (pos[a, 1] - pos[b, 1]) ** 2) + arm
        rel = closing + turn[b] * (reach + h * closing)
        travel = max(g[first + i] + offset[first + i], 0.0) * gap_scale + 0.5 * cp_width[i]
        if rel * h > travel:
            h = travel / rel
    return h


@jit
def guarded_integrator_step(h, pos, ang, vel, om, dydt, dyn, drive_acc, cands, g, first,
                            offset, gap_scale):
    """``guarded_step`` for an integrator step of h from (pos, ang, vel, om): speeds bounded
    from the step start's velocities and accelerations (``dydt`` of the dynamic bodies
    ``dyn``, ``drive_acc`` (m/s^2) for the others), as the candidates' reach is."""
    n, nd = pos.shape[0], dyn.shape[0]
    speed = np.empty(n)
    turn = np.empty(n)
    for i in range(n):
        speed[i] = math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2) + h * drive_acc[i]
        turn[i] = abs(om[i])
    for q in range(nd):
        i = dyn[q]
        speed[i] += h * math.sqrt(dydt[3 * nd + 2 * q] ** 2 + dydt[3 * nd + 2 * q + 1] ** 2)
        turn[i] += h * abs(dydt[5 * nd + q])
    return guarded_step(h, pos, ang, speed, turn, cands, g, first, offset, gap_scale)


@inner
def _guard_scales(pos, cands, limit):
    """Half the smallest piece width of the candidates (m) and a bound on any candidate
    corner's distance from its piece's origin (m) while no body moves farther than ``limit``
    (m) from where it is now."""
    cv_body, cv_local, cp_body, _, _, _, cp_width = cands
    half_width, reach = np.inf, 0.0
    for i in range(cv_body.shape[0]):
        a, b = cv_body[i], cp_body[i]
        arm = math.sqrt(cv_local[i, 0] ** 2 + cv_local[i, 1] ** 2)
        d = math.sqrt((pos[a, 0] - pos[b, 0]) ** 2 + (pos[a, 1] - pos[b, 1]) ** 2) + arm
        half_width, reach = min(half_width, 0.5 * cp_width[i]), max(reach, d + 4.0 * limit)
    return half_width, reach


@inner
def _slow(h, speed, turn, radius, half_width, reach):
    """True if no candidate corner can move half the thinnest candidate piece's width relative
    to it within h: then ``guarded_step`` cannot shorten the step, and this costs a pass over
    the bodies instead of one over the candidates."""
    fastest, turning = 0.0, 0.0
    for i in range(speed.shape[0]):
        fastest = max(fastest, speed[i] + turn[i] * radius[i])
        turning = max(turning, turn[i])
    return (2.0 * fastest + turning * (reach + 2.0 * h * fastest)) * h <= half_width


@inner
def advance_watching(t0, t_end, h, threshold, bodies, drives, contacts, cands, verts,
                     normals, scales, reach, pos, ang, vel, om, dvel_drive, g_hi):
    """Step a closed-form phase from t0 towards t_end in steps of h, watching the events.
    A step is shortened where a corner could otherwise pass through a piece unseen
    (``guarded_step``).

    An event fires when its function drops below ``-threshold`` during a step it started at or
    above it; the earliest crossing is then located by Illinois regula falsi to the last bit of
    t and the state just past it is returned. Stops early (REFRESH) before a step that could
    carry a body out of reach of the candidate collisions.

    Returns ``(status, t, steps, offset)``; ``pos, ang, vel, om`` hold the state at t,
    ``dvel_drive`` the drives' velocity change since t0 (the integral of their acceleration),
    ``g_hi`` the event functions at t (one per function) and ``offset`` what is added to each
    before testing it (``event_offsets``): the ones that fired are below ``-offset``.
    """
    nd = drives.amplitude.shape[0]
    n_events = g_hi.shape[0]
    acc_drive = np.empty(nd)
    dv_scratch = np.empty(nd)
    g_lo = np.empty(n_events)
    _events(t0, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang, vel, om,
            acc_drive, dv_scratch, g_lo)
    offset = event_offsets(g_lo, cands.vertex_body.shape[0], threshold)
    tp = t0
    steps = 0
    n_bodies = pos.shape[0]
    speed = np.empty(n_bodies)
    turn = np.empty(n_bodies)
    first = n_events - cands.vertex_body.shape[0]
    # Bodies stay within the reach's limit of the anchor, where they were at most that far.
    half_width, corner_reach = _guard_scales(pos, cands, reach.limit)
    while tp < t_end - 1e-15:
        dt = min(h, t_end - tp)
        _speed_bounds(dt, bodies, drives, vel, om, speed, turn)
        if not _slow(dt, speed, turn, reach.radius, half_width, corner_reach):
            dt = guarded_step(dt, pos, ang, speed, turn, cands, g_lo, first, offset, scales.gap)
        if not _within_reach(dt, bodies.kind, pos, ang, speed, turn, reach):
            _events(tp, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang,
                    vel, om, acc_drive, dvel_drive, g_hi)
            return REFRESH, tp, steps, offset
        t1 = tp + dt
        _events(t1, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang, vel,
                om, acc_drive, dvel_drive, g_hi)
        hit = (g_hi + offset < 0.0) & (g_lo + offset >= 0.0)
        if hit.any():
            t_ev = _locate(tp, dt, g_lo[hit] + offset[hit], g_hi[hit] + offset[hit], hit, t0,
                           offset[hit], bodies, drives, contacts, cands, verts, normals, scales,
                           pos, ang, vel, om, acc_drive, dvel_drive, n_events)
            _events(t_ev, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang,
                    vel, om, acc_drive, dvel_drive, g_hi)
            return EVENT, t_ev, steps, offset
        tp = t1
        g_lo[:] = g_hi
        steps += 1
    _events(tp, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang, vel, om,
            acc_drive, dvel_drive, g_hi)
    return DONE, tp, steps, offset


@jit
def advance(t0, t_end, h, threshold, n_events, bodies, drives, contacts, cands, verts,
            normals, scales, reach, pos, ang, vel, om, dvel_drive):
    """``advance_watching`` without the event functions: ``(status, t, steps)``."""
    status, t, steps, _ = advance_watching(t0, t_end, h, threshold, bodies, drives, contacts,
                                           cands, verts, normals, scales, reach, pos, ang,
                                           vel, om, dvel_drive, np.empty(n_events))
    return status, t, steps


@jit
def event_offsets(g_start, n_candidates, threshold):
    """Per event function, what is added to it before testing for a drop below zero.

    An event fires when its function drops below ``-threshold``. A collision candidate that
    starts a phase already below that (a corner that just bounced off, located just past the
    threshold) fires instead when it sinks ``threshold`` below where it started: otherwise a
    bounce that lands again within one step would never be seen and the part would fall
    through.
    """
    offset = np.full(g_start.shape[0], threshold)
    first = g_start.shape[0] - n_candidates
    for i in range(first, g_start.shape[0]):
        if g_start[i] < -threshold:
            offset[i] = threshold - g_start[i]
    return offset


@inner
def _locate(tp, h, g_lo, g_hi, hit, t0, offset, bodies, drives, contacts, cands, verts,
            normals, scales, pos, ang, vel, om, acc_drive, dvel_drive, n_events):
    """Earliest time past which a hit function is below its level (Illinois); ``g_lo``,
    ``g_hi`` and ``offset`` are those of the hit functions only."""
    lo, hi = 0.0, h
    best = h
    side = np.int64(0)   # typed as the Python callers pass it: one compile of illinois_narrow
    g_all = np.empty(n_events)
    for _ in range(100):
        if hi - lo <= 1e-15 * max(1.0, abs(tp)) + 1e-16:
            break
        tau = illinois_trial(lo, hi, g_lo, g_hi)
        _events(tp + tau, t0, bodies, drives, contacts, cands, verts, normals, scales, pos, ang,
                vel, om, acc_drive, dvel_drive, g_all)
        g_t = g_all[hit] + offset
        crossed, lo, hi, g_lo, g_hi, side = illinois_narrow(tau, g_t, lo, hi, g_lo, g_hi, side)
        if crossed:
            best = tau
    return tp + best


@jit
def illinois_trial(lo, hi, g_lo, g_hi):
    """The next trial point in [lo, hi] of Illinois regula falsi on the functions that cross
    below zero (``g_lo`` >= 0 at lo, ``g_hi`` at hi): the earliest linear crossing, kept off
    the ends, or the midpoint when none crosses."""
    f = np.inf
    for i in range(g_hi.shape[0]):
        if g_hi[i] < 0:
            f = min(f, g_lo[i] / (g_lo[i] - g_hi[i]))
    if np.isfinite(f):
        return lo + min(max(f, 1e-3), 1 - 1e-3) * (hi - lo)
    return 0.5 * (lo + hi)


@jit
def illinois_narrow(tau, g_t, lo, hi, g_lo, g_hi, side):
    """The bracket after a trial at tau with values ``g_t``: ``(crossed, lo, hi, g_lo, g_hi,
    side)``. The end kept twice in a row has its values halved (Illinois), so that the
    bracket shrinks from both sides."""
    if (g_t < 0).any():
        if side == -1:
            g_lo = g_lo * 0.5
        return True, lo, tau, g_lo, g_t, -1
    if side == 1:
        g_hi = np.where(g_hi < 0, g_hi * 0.5, g_hi)
    return False, tau, hi, g_t, g_hi, 1


# --------------------------------------------------------------------------------------------
# small contact systems


@jit
def contact_jacobian(normal, r_a, r_b, body_a, body_b, dynamic, inv_mass, inv_inertia, bodies):
    """Contact Jacobian (rows ``N_0..N_{k-1}, T_0..T_{k-1}``, columns (vx, vy, omega) of each of
    ``bodies``), the diagonal of M^-1 and the Delassus matrix, when every contact moves exactly
    one dynamic body; ``ok`` is False (and the rest empty) otherwise."""
    k, nb = normal.shape[0], bodies.shape[0]
    col = np.full(dynamic.shape[0], -1, np.int64)
    for i in range(nb):
        col[bodies[i]] = 3 * i
    minv = np.empty(3 * nb)
    for i in range(nb):
        minv[3 * i] = minv[3 * i + 1] = inv_mass[bodies[i]]
        minv[3 * i + 2] = inv_inertia[bodies[i]]
    J = np.zeros((2 * k, 3 * nb))
    for i in range(k):
        a, b = body_a[i], body_b[i]
        if dynamic[a] == dynamic[b] or col[a if dynamic[a] else b] < 0:
            return False, J, minv, np.zeros((0, 0))
        if dynamic[a]:
            c, s, rx, ry = col[a], 1.0, r_a[i, 0], r_a[i, 1]
        else:
            c, s, rx, ry = col[b], -1.0, r_b[i, 0], r_b[i, 1]
        nx, ny = normal[i, 0], normal[i, 1]
        tx, ty = -ny, nx
        J[i, c], J[i, c + 1], J[i, c + 2] = s * nx, s * ny, s * (rx * ny - ry * nx)
        J[k + i, c], J[k + i, c + 1], J[k + i, c + 2] = s * tx, s * ty, s * (rx * ty - ry * tx)
    W = (J * minv) @ J.T
    return True, J, minv, W


@jit
def closed_form_mode(normal, r_a, r_b, body_a, body_b, dynamic, inv_mass, inv_inertia,
                     friction, sigma, mu_d, omega, radius, spin_limit, alpha_limit, gravity,
                     drive_of, drive_u):
    """The held mode's response to gravity and to each drive's unit acceleration, for
    contacts of dynamic vertices (``body_a``) on non-dynamic edges (``body_b``):
    ``(ok, bodies, dv, f)`` with ``dv`` (nb, 3, 1 + nd) the bodies' accelerations
    (vx, vy, omega) and ``f`` (2k, 1 + nd) the stacked contact forces per source (column 0
    gravity, then the drives). ``ok`` is False when a body spins (``|omega| radius`` above
    ``spin_limit``, m/s) or the mode turns it (``|alpha|`` above ``alpha_limit * g / radius``);
    then the phase has no closed form. ``drive_of`` is each body's drive (-1: none)."""
    k = normal.shape[0]
    nd = drive_u.shape[0]
    bodies = sorted_unique(heap_arena(), body_a)
    nb = bodies.shape[0]
    dv = np.zeros((nb, 3, 1 + nd))
    f = np.zeros((2 * k, 1 + nd))
    for i in range(nb):
        if abs(omega[bodies[i]]) * radius[bodies[i]] > spin_limit:
            return False, bodies, dv, f
    ok, J, minv, W = contact_jacobian(normal, r_a, r_b, body_a, body_b, dynamic, inv_mass,
                                      inv_inertia, bodies)
    if not ok:
        return False, bodies, dv, f
    rows_of = np.empty(k, np.int64)
    slave = np.empty(k)
    for i in range(k):
        fr = friction[i]
        rows_of[i] = BOX_ROW if fr == STICK else (SLAVED_ROW if fr == SLIDE else 0)
        slave[i] = -sigma[i] * mu_d[i]
    zeros = np.zeros(k)
    A, P, rows, _, _, _ = reduce_lcp(W, rows_of, zeros, zeros, slave)
    # right-hand sides: the contacts' relative acceleration per unit source (a vertex under
    # gravity against an edge moved by -u per unit drive acceleration)
    rhs = np.zeros((2 * k, 1 + nd))
    for i in range(k):
        nx, ny = normal[i, 0], normal[i, 1]
        tx, ty = -ny, nx
        rhs[i, 0] = nx * gravity[0] + ny * gravity[1]
        rhs[k + i, 0] = tx * gravity[0] + ty * gravity[1]
        d = drive_of[body_b[i]]
        if d >= 0:
            ux, uy = -drive_u[d, 0], -drive_u[d, 1]
            rhs[i, 1 + d] = nx * ux + ny * uy
            rhs[k + i, 1 + d] = tx * ux + ty * uy
    m = rows.shape[0]
    B = np.empty((m, 1 + nd))
    for r in range(m):
        for c in range(1 + nd):
            B[r, c] = -rhs[rows[r], c]
    x = np.linalg.lstsq(A, B, 1e-12)[0]
    f = P @ x
    jf = np.ascontiguousarray(J.T) @ f
    for i in range(nb):
        limit = alpha_limit / radius[bodies[i]]
        for j in range(3):
            for c in range(1 + nd):
                dv[i, j, c] = minv[3 * i + j] * jf[3 * i + j, c]
        for c in range(1 + nd):
            if abs(dv[i, 2, c]) > limit:
                return False, bodies, dv, f
    return True, bodies, dv, f


@jit
def contact_groups(body_a, body_b, normal):
    """Group ids of contacts between the same two bodies along one line, numbered in order of
    each group's first contact.

    Along one line means that the friction of every contact of the group acts on each body
    along the same tangent: normals parallel with the bodies in the same order (the two
    corners of a box lying on a face), or opposite with the bodies swapped (a box overhanging
    a track's end rests on the track's corner, a vertex of the track on the box's face, and
    on its own corner on the track's face). Summed as they stand, the friction forces of a
    group are then its total along its first contact's tangent. Contacts on opposite faces
    of one body (a part between the jaws of a slot) press from two lines: they are not
    grouped."""
    k = body_a.shape[0]
    group = np.full(k, -1, np.int64)
    nxt = 0
    for i in range(k):
        if group[i] >= 0:
            continue
        lo_i, hi_i = min(body_a[i], body_b[i]), max(body_a[i], body_b[i])
        nx, ny = normal[i, 0], normal[i, 1]
        for j in range(k):
            if group[j] < 0 and min(body_a[j], body_b[j]) == lo_i and \
                    max(body_a[j], body_b[j]) == hi_i and \
                    abs(normal[j, 1] * nx - normal[j, 0] * ny) < 1e-9 and \
                    (normal[j, 0] * nx + normal[j, 1] * ny > 0.0) == (body_a[j] == body_a[i]):
                group[j] = nxt
        nxt += 1
    return group


@jit
def sticking_groups(group, friction):
    """Sticking contacts' groups renumbered 0.. in ascending group id (-1 for the others),
    and how many there are."""
    k = group.shape[0]
    compact = np.full(k, -1, np.int64)
    n = 0
    if k == 0:
        return compact, n
    top = group.max()
    new_id = np.full(top + 1, -1, np.int64)
    for i in range(k):
        if friction[i] == STICK:
            new_id[group[i]] = 0
    for g in range(top + 1):
        if new_id[g] == 0:
            new_id[g] = n
            n += 1
    for i in range(k):
        if friction[i] == STICK:
            compact[i] = new_id[group[i]]
    return compact, n


@jit
def held_mask(vertex, piece, held_vertex, held_piece):
    """Candidates (vertex against piece) that are not a held contact's vertex on an edge of
    that piece."""
    keep = np.ones(vertex.shape[0], np.bool_)
    for i in range(vertex.shape[0]):
        for j in range(held_vertex.shape[0]):
            if vertex[i] == held_vertex[j] and piece[i] == held_piece[j]:
                keep[i] = False
    return keep


# --------------------------------------------------------------------------------------------
# force LCP of the resting contacts (Baraff)


@jit
def force_problem(normal, r_a, r_b, body_a, body_b, omega, acc, v_n, v_t, sliding, mu_s, mu_d):
    """Right-hand side of the force LCP and each contact's friction row treatment.

    ``b`` is the contacts' relative acceleration without contact forces (Baraff 1989): the
    centripetal terms and the rotation of the edge's normal carry over from the velocities.
    Sliding contacts get their friction slaved to the normal force, others a box row, and
    frictionless ones none."""
    k = normal.shape[0]
    b_full = np.empty(2 * k)
    fr = np.empty(k, np.int64)
    for i in range(k):
        a, b = body_a[i], body_b[i]
        wa2, wb2 = omega[a] * omega[a], omega[b] * omega[b]
        dx = (acc[a, 0] - wa2 * r_a[i, 0]) - (acc[b, 0] - wb2 * r_b[i, 0])
        dy = (acc[a, 1] - wa2 * r_a[i, 1]) - (acc[b, 1] - wb2 * r_b[i, 1])
        nx, ny = normal[i, 0], normal[i, 1]
        b_full[i] = dx * nx + dy * ny + 2.0 * omega[b] * v_t[i]
        b_full[k + i] = -dx * ny + dy * nx - 2.0 * omega[b] * v_n[i]
        mu = mu_d[i] if sliding[i] else mu_s[i]
        fr[i] = 0 if mu <= 0.0 else (SLAVED_ROW if sliding[i] else BOX_ROW)
    return b_full, fr


@jit
def zeno_speed(normal, body_a, body_b, dynamic, gravity, touch_m):
    """Per contact, the normal speed (m/s) below which a corner leaving the body it rests on
    is brought back by gravity before it rises past ``touch_m``: ``sqrt(2 g_n touch_m)``, g_n
    the part of ``gravity`` (m/s^2) pressing along the contact ``normal``.

    That holds where the lower body does not fall with the upper one: a support (a static or
    driven body), or a part that rests, through contacts gravity presses, on a support (a box
    rocking on a box on the track). Two parts that touch in flight fall together, so gravity
    brings neither back to the other: 0 there, and on a wall or a ceiling."""
    k = normal.shape[0]
    out = np.zeros(k)
    g_n = np.empty(k)
    supported = ~dynamic
    for i in range(k):
        # from body_b into body_a: positive where gravity presses body_b onto body_a
        g_n[i] = normal[i, 0] * gravity[0] + normal[i, 1] * gravity[1]
    # a part rests on a support through a chain of pressed contacts: at most k links
    for _ in range(k):
        grew = False
        for i in range(k):
            a, b = body_a[i], body_b[i]
            if g_n[i] > 0.0 and supported[a] and not supported[b]:
                supported[b] = grew = True
            elif g_n[i] < 0.0 and supported[b] and not supported[a]:
                supported[a] = grew = True
        if not grew:
            break
    for i in range(k):
        a, b = body_a[i], body_b[i]
        if g_n[i] > 0.0 and supported[a] and dynamic[b]:
            out[i] = math.sqrt(2.0 * g_n[i] * touch_m)
        elif g_n[i] < 0.0 and supported[b] and dynamic[a]:
            out[i] = math.sqrt(-2.0 * g_n[i] * touch_m)
    return out


@jit
def mode_rows(f, a_rel, fr, mu_s, sigma, force_tol, acc_tol, body_a, body_b, normal):
    """The contact mode the force LCP solution implies: which contacts stay (they press, or
    they would accelerate into each other without a force), which stick and which slide
    (a sticking contact whose friction is at its bound while tangential acceleration remains
    starts to slide that way).

    The contacts of one body pair along one line (``contact_groups``) share their friction:
    only its sum is determined, and an LCP answer may squeeze them, the friction of one at
    +mu f_N and of another at -mu f_N. Such a contact slides only if the group's friction
    is at the group's bound too (the sum of its contacts' friction forces, each along its own
    tangent, which ``contact_groups`` makes the same on each body)."""
    k = fr.shape[0]
    keep = np.empty(k, np.bool_)
    friction = np.empty(k, np.int64)
    new_sigma = sigma.copy()
    group = contact_groups(body_a, body_b, normal)
    total_t = np.zeros(k)
    bound = np.zeros(k)
    for i in range(k):
        total_t[group[i]] += f[k + i]
        bound[group[i]] += mu_s[i] * f[i]
    for i in range(k):
        f_n, f_t, a_n, a_t = f[i], f[k + i], a_rel[i], a_rel[k + i]
        keep[i] = f_n > force_tol or a_n <= acc_tol
        g = group[i]
        at_bound = (abs(f_t) >= mu_s[i] * f_n * (1 - 1e-9) - force_tol
                    and abs(total_t[g]) >= bound[g] * (1 - 1e-9) - force_tol)
        if fr[i] == SLAVED_ROW:
            friction[i] = SLIDE
        elif fr[i] == BOX_ROW and at_bound and abs(a_t) > 1e-12:
            friction[i] = SLIDE
            new_sigma[i] = np.sign(a_t)
        elif fr[i] == BOX_ROW:
            friction[i] = STICK
        else:
            friction[i] = NO_FRICTION
    return keep, friction, new_sigma


@jit
def leaving(t, drives, f_lcp, f0, f1, force_tol, limit):
    """The held contacts a mode cannot keep: (k,) True where the force LCP gave the contact
    no force (``f_lcp[i] <= force_tol``, N: it stayed only because it does not accelerate
    away) while the mode's own normal force at t, ``f0[i] + f1[i] @ s(t)`` with ``s`` the
    drives' accelerations, is already below ``-limit`` (N).

    A normal-force event is located just past the level ``-limit`` at which it fires. At
    that instant the LCP is degenerate for the contact (force and separating acceleration
    both zero to first order, e.g. a block's rear corner when the platform's acceleration
    reaches g b / h) and keeps it; the mode holding it would then start with the event
    function below its level, which an event never sees, so the contact would press with a
    negative force for good (a tall block sticking flat on an accelerating platform never
    tips). It leaves instead: the force keeps falling, so that is the choice the next
    instant's LCP makes. ``f0`` (2k,) and ``f1`` (2k, nd) are the stacked forces of the
    phase's closed form (normal rows first); an integrated mode passes its forces at t as
    ``f0`` and zero ``f1``. ``drives`` as in a closed-form phase (:class:`Drives`)."""
    _, _, amp, w, phase, t_ref = drives
    k = f_lcp.shape[0]
    out = np.zeros(k, np.bool_)
    for i in range(k):
        f = f0[i]
        for d in range(amp.shape[0]):
            f -= f1[i, d] * amp[d] * w[d] * w[d] * math.sin(phase[d] + w[d] * (t - t_ref))
        out[i] = f_lcp[i] <= force_tol and f < -limit
    return out


# A sticking contact still slipping faster than this share of the slip tolerance is stopped
# by ``stick_closure`` (below it, the slip is the round-off of locating the event).
SLIP_LEFT = 1e-2


@jit
def slip_left(friction, v_t, slip_tol):
    """Whether a contact that sticks from now on still slips (``SLIP_LEFT``)."""
    for i in range(friction.shape[0]):
        if friction[i] == STICK and abs(v_t[i]) > SLIP_LEFT * slip_tol:
            return True
    return False


@jit
def stick_closure(W, v_n, v_t, friction):
    """Stacked impulses (normal, then tangential; N s) that bring the held contacts to rest
    along their normals and the sticking ones along their tangents too: the least-squares
    answer of ``W p = -v`` over those rows (W the contacts' Delassus matrix, J M^-1 J^T),
    which is the smallest change of velocity in the kinetic-energy norm.

    A slip stops where its event function has passed the event threshold, so the contact
    sticks from there with the slip reversed by up to ``EVENT_THRESHOLD`` times the speed
    scale (~3e-10 m/s for a 20 mm part), which sticking keeps for good: a stopped part would
    creep. The impulse stands for friction's over the time the stop was located late (at
    most mu N times that time)."""
    k = v_n.shape[0]
    rows = np.empty(2 * k, np.int64)
    m = 0
    for i in range(k):
        rows[m] = i
        m += 1
    for i in range(k):
        if friction[i] == STICK:
            rows[m] = k + i
            m += 1
    A = np.empty((m, m))
    # one column, as closed_form_mode's lstsq takes it: no second specialisation to compile
    rhs = np.empty((m, 1))
    for r in range(m):
        q = rows[r]
        rhs[r, 0] = -v_n[q] if q < k else -v_t[q - k]
        for c in range(m):
            A[r, c] = W[q, rows[c]]
    x = np.linalg.lstsq(A, rhs, 1e-12)[0]
    p = np.zeros(2 * k)
    for r in range(m):
        p[rows[r]] = x[r, 0]
    return p


@jit
def relative_velocity(normal, r_a, r_b, body_a, body_b, vel, omega):
    """Normal and tangential velocity of each contact's vertex relative to the edge's
    material point under it (m/s). Its sums run in another order than
    ``_island_kernels.contact_velocities``': each keeps the bits its method was validated with."""
    k = normal.shape[0]
    v_n = np.empty(k)
    v_t = np.empty(k)
    for i in range(k):
        a, b = body_a[i], body_b[i]
        rx = vel[a, 0] - omega[a] * r_a[i, 1] - vel[b, 0] + omega[b] * r_b[i, 1]
        ry = vel[a, 1] + omega[a] * r_a[i, 0] - vel[b, 1] - omega[b] * r_b[i, 0]
        nx, ny = normal[i, 0], normal[i, 1]
        v_n[i] = rx * nx + ry * ny
        v_t[i] = ry * nx - rx * ny
    return v_n, v_t


# --------------------------------------------------------------------------------------------
# integrated phases: the held mode's right-hand side and Dormand-Prince steps

# Dormand-Prince 5(4) (Dormand & Prince 1980); row 6 is the 5th-order solution (FSAL).
DP_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
DP_A = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [1 / 5, 0.0, 0.0, 0.0, 0.0, 0.0],
    [3 / 40, 9 / 40, 0.0, 0.0, 0.0, 0.0],
    [44 / 45, -56 / 15, 32 / 9, 0.0, 0.0, 0.0],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0.0, 0.0],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656, 0.0],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
])
DP_E = np.array([35 / 384 - 5179 / 57600, 0.0, 500 / 1113 - 7571 / 16695,
                  125 / 192 - 393 / 640, -2187 / 6784 + 92097 / 339200, 11 / 84 - 187 / 2100,
                  -1 / 40])


@inner
def _bodies_at(t, y, dyn, kind, index, pos_fixed, ang_fixed, drives, gravity, pos, ang, vel,
               om, acc):
    """Every body's state and free acceleration at t: dynamic bodies from y, driven ones from
    their sinusoid, the others fixed."""
    dr_u, dr_base, dr_amp, dr_w, dr_phase, t_ref = drives
    nd = dyn.shape[0]
    for i in range(kind.shape[0]):
        if kind[i] == FIXED:
            pos[i, 0], pos[i, 1], ang[i] = pos_fixed[i, 0], pos_fixed[i, 1], ang_fixed[i]
            vel[i, 0] = vel[i, 1] = om[i] = acc[i, 0] = acc[i, 1] = 0.0
        elif kind[i] == DRIVEN:
            d = index[i]
            a, w = dr_amp[d], dr_w[d]
            ph = dr_phase[d] + w * (t - t_ref)
            s, c = math.sin(ph), math.cos(ph)
            for j in range(2):
                pos[i, j] = dr_base[d, j] + a * s * dr_u[d, j]
                vel[i, j] = a * w * c * dr_u[d, j]
                acc[i, j] = -a * w * w * s * dr_u[d, j]
            ang[i], om[i] = ang_fixed[i], 0.0
    for q in range(nd):
        i = dyn[q]
        pos[i, 0], pos[i, 1] = y[2 * q], y[2 * q + 1]
        ang[i] = y[2 * nd + q]
        vel[i, 0], vel[i, 1] = y[3 * nd + 2 * q], y[3 * nd + 2 * q + 1]
        om[i] = y[5 * nd + q]
        acc[i, 0], acc[i, 1] = gravity[0], gravity[1]


@inner
def _mode_rhs(t, y, spec, pos, ang, vel, om, acc, dydt, g, f, events):
    """Time derivative of y under the held mode, its contact forces and, with ``events``,
    its event functions (a Dormand-Prince step needs them at its end only: the candidates'
    gaps cost more than the rest of the right-hand side in a scene of many pieces).

    The same equations as ``EventDriven._rhs`` and ``_event_values``: forces are the
    least-squares solution of the held mode's equations (pressing contacts have zero normal
    acceleration, sticking ones zero tangential acceleration, sliding ones friction
    ``-sigma mu_d f_N``)."""
    (dyn, col, kind, index, pos_fixed, ang_fixed, drives, gravity, inv_mass, inv_inertia,
     contacts, mu_d, cands, verts, normals, scales) = spec
    c_a, c_b, vloc, q0loc, q1loc, nloc, _, _, friction, sigma, mu_s, group, n_groups = contacts
    force_scale, speed_scale, gap_scale = scales
    _bodies_at(t, y, dyn, kind, index, pos_fixed, ang_fixed, drives, gravity, pos, ang, vel,
               om, acc)
    nd = dyn.shape[0]
    k = c_a.shape[0]
    n_cols = 3 * nd
    J = np.zeros((2 * k, n_cols))
    b_full = np.empty(2 * k)
    v_t = np.empty(k)
    params = np.empty(k)
    for i in range(k):
        a, b = c_a[i], c_b[i]
        param, vt, _, px, py, nx, ny = _contact_geometry(pos, ang, vel, om, a, b, vloc[i],
                                                         q0loc[i], q1loc[i], nloc[i])
        params[i], v_t[i] = param, vt
        tx, ty = -ny, nx
        rax, ray = px - pos[a, 0], py - pos[a, 1]
        rbx, rby = px - pos[b, 0], py - pos[b, 1]
        relx = (vel[a, 0] - om[a] * ray) - (vel[b, 0] - om[b] * rby)
        rely = (vel[a, 1] + om[a] * rax) - (vel[b, 1] + om[b] * rbx)
        # Relative acceleration without contact forces (Baraff 1989): the centripetal terms
        # and the rotation of the edge's normal carry over from the velocities.
        dx = (acc[a, 0] - om[a] * om[a] * rax) - (acc[b, 0] - om[b] * om[b] * rbx)
        dy = (acc[a, 1] - om[a] * om[a] * ray) - (acc[b, 1] - om[b] * om[b] * rby)
        b_full[i] = dx * nx + dy * ny + 2.0 * om[b] * (relx * tx + rely * ty)
        b_full[k + i] = dx * tx + dy * ty - 2.0 * om[b] * (relx * nx + rely * ny)
        for body, rx, ry, sign in ((a, rax, ray, 1.0), (b, rbx, rby, -1.0)):
            cc = col[body]
            if cc >= 0:
                J[i, cc] += sign * nx
                J[i, cc + 1] += sign * ny
                J[i, cc + 2] += sign * (rx * ny - ry * nx)
                J[k + i, cc] += sign * tx
                J[k + i, cc + 1] += sign * ty
                J[k + i, cc + 2] += sign * (rx * ty - ry * tx)
    minv = np.empty(n_cols)
    for q in range(nd):
        minv[3 * q] = minv[3 * q + 1] = inv_mass[dyn[q]]
        minv[3 * q + 2] = inv_inertia[dyn[q]]
    for q in range(nd):
        i = dyn[q]
        dydt[2 * q], dydt[2 * q + 1] = vel[i, 0], vel[i, 1]
        dydt[2 * nd + q] = om[i]
        dydt[3 * nd + 2 * q], dydt[3 * nd + 2 * q + 1] = acc[i, 0], acc[i, 1]
        dydt[5 * nd + q] = 0.0
    if k:
        rows_friction = np.empty(k, np.int64)
        slave = np.empty(k)
        for i in range(k):
            rows_friction[i] = (BOX_ROW if friction[i] == STICK else
                                SLAVED_ROW if friction[i] == SLIDE else 0)
            slave[i] = -sigma[i] * mu_d[i]
        W = (J * minv) @ J.T
        A, P, rows, _, _, _ = reduce_lcp(W, rows_friction, np.zeros(k), np.zeros(k), slave)
        x = np.linalg.lstsq(A, -b_full[rows], 1e-12)[0]
        f[:] = P @ x
        dv = minv * (J.T @ f)
        for q in range(nd):
            dydt[3 * nd + 2 * q] += dv[3 * q]
            dydt[3 * nd + 2 * q + 1] += dv[3 * q + 1]
            dydt[5 * nd + q] += dv[3 * q + 2]
    if not events:
        return
    j = _force_events(f, k, mu_s, group, n_groups, force_scale, g)
    for i in range(k):
        if friction[i] == SLIDE:
            g[j] = sigma[i] * v_t[i] / speed_scale
            j += 1
    _geometric_events(params, cands, pos, ang, verts, normals, gap_scale, g, j)


@jit
def mode_rhs(t, y, spec, n_events, pos, ang, vel, om):
    """``(dy/dt, event functions, stacked contact forces)`` of the held mode at (t, y);
    ``pos, ang, vel, om`` receive every body's state."""
    acc = np.empty((pos.shape[0], 2))
    dydt = np.empty(y.shape[0])
    g = np.empty(n_events)
    f = np.zeros(2 * spec.contacts.body_a.shape[0])
    _mode_rhs(t, y, spec, pos, ang, vel, om, acc, dydt, g, f, True)
    return dydt, g, f


@jit
def dopri_step(t, y, h, k0, spec, n_events, tol_scale, pos, ang, vel, om):
    """One Dormand-Prince 5(4) step of the held mode from (t, y) with derivative k0:
    ``(y_new, error norm, derivative at the end, event functions and forces at the end)``."""
    n = y.shape[0]
    acc = np.empty((pos.shape[0], 2))
    ks = np.empty((7, n))
    ks[0] = k0
    g = np.empty(n_events)
    f = np.zeros(2 * spec.contacts.body_a.shape[0])
    yi = np.empty(n)
    for i in range(1, 7):
        for q in range(n):
            s = 0.0
            for j in range(i):
                s += DP_A[i, j] * ks[j, q]
            yi[q] = y[q] + h * s
        _mode_rhs(t + DP_C[i] * h, yi, spec, pos, ang, vel, om, acc, ks[i], g, f, i == 6)
    err = 0.0
    for q in range(n):
        e = 0.0
        for j in range(7):
            e += DP_E[j] * ks[j, q]
        err += (h * e / tol_scale[q]) ** 2
    err = math.sqrt(err / n) if n else 0.0
    return yi.copy(), err, ks[6].copy(), g, f


@jit
def held_geometry(pos, ang, c_a, c_b, vloc, q0loc, q1loc, nloc):
    """World point, normal, gap and edge parameter of held contacts at (pos, ang)."""
    k = c_a.shape[0]
    point = np.empty((k, 2))
    normal = np.empty((k, 2))
    gap = np.empty(k)
    param = np.empty(k)
    for i in range(k):
        a, b = c_a[i], c_b[i]
        px, py = world_point(pos, ang, a, vloc[i])
        q0x, q0y = world_point(pos, ang, b, q0loc[i])
        q1x, q1y = world_point(pos, ang, b, q1loc[i])
        cb, sb = math.cos(ang[b]), math.sin(ang[b])
        nx, ny = cb * nloc[i, 0] - sb * nloc[i, 1], sb * nloc[i, 0] + cb * nloc[i, 1]
        ex, ey = q1x - q0x, q1y - q0y
        point[i, 0], point[i, 1], normal[i, 0], normal[i, 1] = px, py, nx, ny
        gap[i] = nx * (px - q0x) + ny * (py - q0y)
        param[i] = ((px - q0x) * ex + (py - q0y) * ey) / (ex * ex + ey * ey)
    return point, normal, gap, param


@jit
def impact_rhs(v_n, v_t, restitution, rest_speed):
    """Right-hand side of the impulse LCP: ``w_N = v'_N + e v_N`` (plastic below the rest
    speed, no restitution for separating contacts), ``w_T = v'_T``."""
    k = v_n.shape[0]
    b = np.empty(2 * k)
    for i in range(k):
        e = restitution[i] if -v_n[i] > rest_speed else 0.0
        b[i] = (1.0 + e) * v_n[i] if v_n[i] < 0.0 else v_n[i]
        b[k + i] = v_t[i]
    return b


@jit
def impulse_effect(J, minv, W, p, v_n, v_t):
    """Velocity change ``(nb, 3)`` of stacked impulses p, and the kinetic energy they add
    against its scale (gain, |p| . |v|)."""
    v_pre = np.concatenate((v_n, v_t))
    gain = p @ v_pre + 0.5 * p @ (W @ p)
    scale = np.abs(p) @ np.abs(v_pre)
    dv = (minv * (J.T @ p)).reshape(-1, 3)
    return dv, gain, scale
