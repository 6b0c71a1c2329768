"""Compiled work of the impulse-based method: a step's collisions resolved one contact point at
a time (Routh's frictional impulse at each), the time-of-impact search and the run of steps to
a stop time. :mod:`.stepper` prepares the arrays and reads the counters back.

The kernels take the world's constants as :class:`~feeder_sim.model.arrays.BodyArrays` and
:class:`~feeder_sim.model.arrays.ShapeArrays`, and the method's own arrays and numbers as the
named tuples below: :class:`ImpulseParams` (settings), :class:`Candidates` (the contacts
looked at), :class:`Motion` (the state, and the trial step's copy of it) and :class:`Outputs`
(counters, float outputs, impulses summed per feature)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.compiled.jit import inner, jit
from feeder_sim.contact.routh import JAM, REVERSE, routh_collision, STICK
from feeder_sim.model.vibration import segment_motion
from feeder_sim.model.world import DRIVEN, MOVING

# kernel return codes
DONE, REFRESH = 0, 1
# kernel counters
(C_STEPS, C_COLLISIONS, C_MICRO, C_SWEEPS, C_MOST_SWEEPS, C_SWEEP_CAP, C_TOI_CUTS,
 C_TOI_GIVE_UP, C_JAMS, C_STICKS, C_REVERSALS) = range(11)
COUNTER_NAMES = ('steps', 'collisions', 'micro_collisions', 'sweeps', 'most_sweeps_at_once',
                 'sweep_cap_hits', 'toi_cuts', 'toi_give_ups', 'jams', 'sticks', 'reversals')
# float outputs of the kernel
F_MAX_PEN, F_CAP_T, F_GIVE_UP_T = 0, 1, 2


class ImpulseParams(NamedTuple):
    """The method's settings and derived numbers (SI units), see ``ImpulseSettings``."""

    margin_m: float        # candidate margin: the candidates are detected again past half of it
    width_m: float         # thinnest piece (against tunnelling)
    h_max: float           # largest step
    eps: float             # collision envelope
    eps_pen: float         # deepest sink of a step (time-of-impact floor)
    v_sep: float           # bounce speed
    micro_speed: float     # approach speed below which a collision is a micro-collision
    friction_on: bool      # friction impulse in real collisions
    law: int               # restitution law (``routh.LAWS``)
    max_sweeps: int        # sequential sweeps of one instant before giving up
    max_toi: int           # step shortenings before a step is taken anyway
    h_min: float           # shortest step


class Candidates(NamedTuple):
    """Active corners (of body ``body``) against convex pieces of other bodies (of body
    ``piece_body``, edges ``start`` to ``end``), one row each, and the poses at detection."""

    body: np.ndarray          # (c,) int64 body of the corner
    local: np.ndarray         # (c, 2) corner in its body's frame
    sides: np.ndarray         # (c, 4) body-frame unit vectors to the corner's two neighbours
    piece_body: np.ndarray    # (c,) int64 body of the piece
    start: np.ndarray         # (c,) int64 first edge of the piece
    end: np.ndarray           # (c,) int64 one past its last edge
    mu_static: np.ndarray     # (c,) of the pair
    mu_dynamic: np.ndarray    # (c,)
    restitution: np.ndarray   # (c,)
    anchor_pos: np.ndarray    # (n, 2) positions at detection
    anchor_ang: np.ndarray    # (n,) angles at detection


class Motion(NamedTuple):
    """Poses and velocities of every body: the state, or a trial step's copy of it."""

    pos: np.ndarray    # (n, 2)
    ang: np.ndarray    # (n,)
    vel: np.ndarray    # (n, 2)
    om: np.ndarray     # (n,)


class Outputs(NamedTuple):
    """What the kernels write besides the state."""

    acc_n: np.ndarray      # (c, max piece size) normal impulse summed per feature
    acc_t: np.ndarray      # (c, max piece size) tangential impulse summed per feature
    acc_geo: np.ndarray    # (c, max piece size, 5) point, normal, gap of its latest contact
    counters: np.ndarray   # (len(COUNTER_NAMES),) int64, C_*
    fout: np.ndarray       # (3,) float outputs, F_*


# ------------------------------------------------------------------------ kernel geometry
# A side of a corner pointing into a face by more than this angle (rad) marks a face the
# corner cannot touch (another corner's end face). Resting parts and trial steps tilt far
# less: a step turns no part by more than a quarter candidate margin over its radius
# (0.025 rad by default); the faces of a vertex-vertex contact meet at tens of degrees.
_SIDE_ANGLE = 0.25
_SIN_SIDE_ANGLE = math.sin(_SIDE_ANGLE)
# deepest sink, in penetration bands, that an approach left by capped sweeps may reach
_CAPPED_SINK = 8


@jit
def _poses(t1, h, bodies, drives, now, work):
    """Free flight from t1 - h to t1 (``now`` to ``work``): ballistic dynamic bodies, driven
    bodies on their drives."""
    kind, drive_row, gravity = bodies.kind, bodies.drive_row, bodies.gravity
    pos, ang, vel, om = now
    pos1, ang1, vel1, om1 = work
    for i in range(kind.shape[0]):
        k = kind[i]
        if k == MOVING:
            for j in range(2):
                pos1[i, j] = pos[i, j] + h * (vel[i, j] + 0.5 * h * gravity[j])
                vel1[i, j] = vel[i, j] + h * gravity[j]
            ang1[i] = ang[i] + h * om[i]
            om1[i] = om[i]
        elif k == DRIVEN:
            row = drive_row[i]
            d, v, _ = segment_motion(t1, drives, row)
            for j in range(2):
                pos1[i, j] = drives.base_m[row, j] + d * drives.direction[row, j]
                vel1[i, j] = v * drives.direction[row, j]
            ang1[i] = ang[i]
            om1[i] = om[i]
        else:
            pos1[i, 0], pos1[i, 1] = pos[i, 0], pos[i, 1]
            vel1[i, 0], vel1[i, 1] = vel[i, 0], vel[i, 1]
            ang1[i], om1[i] = ang[i], om[i]


@inner
def _corner_gap(now, shapes, cand, k, eps):
    """World point of candidate k's corner (``local`` of body a), its gap to body b's piece
    and the face.

    Outside the envelope the gap is the largest signed distance from the piece's outer edge
    lines (a lower bound of the true distance). Within it, the face is the least-penetrated
    one the corner can touch: neither of its sides (``sides``, body-frame unit vectors
    towards its neighbours) may point into the face by more than ``_SIDE_ANGLE`` (the
    supporting-vertex test of ``collision.find_contacts``). A corner meeting a corner is
    otherwise taken against the end face beside it, whose normal stops every slide along the
    other face."""
    pos, ang = now.pos, now.ang
    verts, normals, internal = shapes.vertices, shapes.normals, shapes.edge_internal
    a, b = cand.body[k], cand.piece_body[k]
    start, end = cand.start[k], cand.end[k]
    local = cand.local[k]
    sides = cand.sides[k]
    c, s = math.cos(ang[a]), math.sin(ang[a])
    px = pos[a, 0] + c * local[0] - s * local[1]
    py = pos[a, 1] + s * local[0] + c * local[1]
    ux, uy = c * sides[0] - s * sides[1], s * sides[0] + c * sides[1]
    wx, wy = c * sides[2] - s * sides[3], s * sides[2] + c * sides[3]
    cb, sb = math.cos(ang[b]), math.sin(ang[b])
    best, face = -math.inf, -1
    touch, touch_face = -math.inf, -1
    for j in range(start, end):
        if internal[j]:
            continue
        qx = pos[b, 0] + cb * verts[j, 0] - sb * verts[j, 1]
        qy = pos[b, 1] + sb * verts[j, 0] + cb * verts[j, 1]
        nx = cb * normals[j, 0] - sb * normals[j, 1]
        ny = sb * normals[j, 0] + cb * normals[j, 1]
        d = nx * (px - qx) + ny * (py - qy)
        if face < 0 or d > best:
            best, face = d, j
        if (d > touch and ux * nx + uy * ny >= -_SIN_SIDE_ANGLE
                and wx * nx + wy * ny >= -_SIN_SIDE_ANGLE):
            touch, touch_face = d, j
    if best <= eps and touch_face >= 0:
        return px, py, touch, touch_face
    return px, py, best, face


@inner
def _face_frame(now, shapes, body, face):
    ang, normals = now.ang, shapes.normals
    c, s = math.cos(ang[body]), math.sin(ang[body])
    return c * normals[face, 0] - s * normals[face, 1], s * normals[face, 0] + c * normals[face, 1]


@inner
def _relative(now, a, b, rax, ray, rbx, rby, nx, ny):
    """(u_T, u_N) of a's corner against b's material point, tangent = normal rotated +90."""
    vel, om = now.vel, now.om
    relx = (vel[a, 0] - om[a] * ray) - (vel[b, 0] - om[b] * rby)
    rely = (vel[a, 1] + om[a] * rax) - (vel[b, 1] + om[b] * rbx)
    return -ny * relx + nx * rely, nx * relx + ny * rely


@inner
def _gap_rate(now, a, b, px, py, nx, ny):
    pos = now.pos
    _, un = _relative(now, a, b, px - pos[a, 0], py - pos[a, 1], px - pos[b, 0],
                      py - pos[b, 1], nx, ny)
    return un


# ------------------------------------------------------------------------ kernel: collisions
@inner
def _resolve(t, now, bodies, shapes, cand, prm, out):
    """Sequential collisions of every approaching contact within the envelope at time t;
    returns whether the sweeps hit their cap (some contact may still approach)."""
    pos, vel, om = now.pos, now.vel, now.om
    inv_mass, inv_inertia = bodies.inv_mass, bodies.inv_inertia
    cv_body, cp_body, cp_start = cand.body, cand.piece_body, cand.start
    c_mu_s, c_mu_d, c_e = cand.mu_static, cand.mu_dynamic, cand.restitution
    eps, v_sep, micro_speed = prm.eps, prm.v_sep, prm.micro_speed
    friction_on, law, max_sweeps = prm.friction_on, prm.law, prm.max_sweeps
    acc_n, acc_t, acc_geo, counters, fout = out
    nc = cv_body.shape[0]
    idx = np.empty(nc, np.int64)
    geo = np.empty((nc, 9))     # rax, ray, rbx, rby, nx, ny, ktt, ktn, knn
    face_of = np.empty(nc, np.int64)
    m = 0
    for c in range(nc):
        a, b = cv_body[c], cp_body[c]
        px, py, gap, face = _corner_gap(now, shapes, cand, c, eps)
        if face < 0 or gap > eps:
            continue
        if -gap > fout[F_MAX_PEN]:
            fout[F_MAX_PEN] = -gap
        nx, ny = _face_frame(now, shapes, b, face)
        tx, ty = -ny, nx
        rax, ray = px - pos[a, 0], py - pos[a, 1]
        rbx, rby = px - pos[b, 0], py - pos[b, 1]
        # collision matrix in (t, n): sum over bodies of 1/m I + 1/I (r x e_i)(r x e_j)
        at, an = rax * ty - ray * tx, rax * ny - ray * nx
        bt, bn = rbx * ty - rby * tx, rbx * ny - rby * nx
        im = inv_mass[a] + inv_mass[b]
        ia, ib = inv_inertia[a], inv_inertia[b]
        geo[m, 0], geo[m, 1], geo[m, 2], geo[m, 3] = rax, ray, rbx, rby
        geo[m, 4], geo[m, 5] = nx, ny
        geo[m, 6] = im + ia * at * at + ib * bt * bt
        geo[m, 7] = ia * at * an + ib * bt * bn
        geo[m, 8] = im + ia * an * an + ib * bn * bn
        idx[m] = c
        face_of[m] = face
        # geometry of the latest contact of this feature, for the impulse log
        k = face - cp_start[c]
        acc_geo[c, k, 0], acc_geo[c, k, 1] = px, py
        acc_geo[c, k, 2], acc_geo[c, k, 3] = nx, ny
        acc_geo[c, k, 4] = gap
        m += 1
    if m == 0:
        return False
    un_now = np.empty(m)
    sweeps = 0
    while True:
        for k in range(m):
            a, b = cv_body[idx[k]], cp_body[idx[k]]
            _, un_now[k] = _relative(now, a, b, geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 3],
                                     geo[k, 4], geo[k, 5])
        if un_now.min() >= 0.0:
            return False
        if sweeps >= max_sweeps:
            counters[C_SWEEP_CAP] += 1
            fout[F_CAP_T] = t
            return True
        sweeps += 1
        counters[C_SWEEPS] += 1
        counters[C_MOST_SWEEPS] = max(counters[C_MOST_SWEEPS], sweeps)
        order = np.argsort(un_now, kind='mergesort')
        for o in range(m):
            k = order[o]
            if un_now[k] >= 0.0:
                break
            c = idx[k]
            a, b = cv_body[c], cp_body[c]
            rax, ray, rbx, rby, nx, ny = (geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 3], geo[k, 4],
                                          geo[k, 5])
            ut, un = _relative(now, a, b, rax, ray, rbx, rby, nx, ny)
            if un >= 0.0:
                continue
            micro = -un <= micro_speed
            if friction_on or micro:
                mu_d, mu_s = c_mu_d[c], c_mu_s[c]
                if micro and abs(ut) <= 2.0 * mu_s * micro_speed:
                    # a resting contact: the slip is what gravity and the drives built up
                    # in the flight since the last micro-collision, which static friction
                    # would have held (see "Restick" in the module docstring)
                    mu_d = max(mu_d, mu_s)
            else:
                mu_d = mu_s = 0.0
            pt, pn, _, _, phases, _ = routh_collision(geo[k, 6], geo[k, 7], geo[k, 8], ut, un,
                                                      mu_d, mu_s, c_e[c], law, v_sep)
            px, py = pt * -ny + pn * nx, pt * nx + pn * ny
            vel[a, 0] += inv_mass[a] * px
            vel[a, 1] += inv_mass[a] * py
            om[a] += inv_inertia[a] * (rax * py - ray * px)
            vel[b, 0] -= inv_mass[b] * px
            vel[b, 1] -= inv_mass[b] * py
            om[b] -= inv_inertia[b] * (rbx * py - rby * px)
            f = face_of[k] - cp_start[c]
            acc_n[c, f] += pn
            acc_t[c, f] += pt
            counters[C_COLLISIONS] += 1
            counters[C_MICRO] += 1 if micro else 0
            counters[C_JAMS] += 1 if phases & JAM else 0
            counters[C_STICKS] += 1 if phases & STICK else 0
            counters[C_REVERSALS] += 1 if phases & REVERSE else 0


# ------------------------------------------------------------------------ kernel: stepping
@inner
def _toi(g0, u0, gh, h, center, floor):
    """Time in (0, h] at which a gap, quadratic in time through g0 (rate u0) and gh at h,
    comes down to the middle of the contact band (or half way to its floor)."""
    c = (gh - g0 - u0 * h) / (h * h)
    peak = g0 - u0 * u0 / (4.0 * c) if (c < 0.0 and u0 > 0.0) else g0
    level = center if max(g0, peak) > center else 0.5 * (g0 + floor)
    # smallest root of c tau^2 + u0 tau + (g0 - level) = 0 in (0, h] where the gap falls
    q = g0 - level
    best = math.inf
    if abs(c) * h * h <= 1e-12 * (abs(u0) * h + abs(q)):
        if u0 < 0.0:
            best = -q / u0
    else:
        disc = u0 * u0 - 4.0 * c * q
        if disc >= 0.0:
            sq = math.sqrt(disc)
            r = -0.5 * (u0 + sq) if u0 >= 0.0 else -0.5 * (u0 - sq)
            roots = (r / c, q / r if r != 0.0 else math.inf)
            for tau in roots:
                if 0.0 < tau < best and u0 + 2.0 * c * tau <= 0.0:
                    best = tau
    if not best <= h:
        return 0.5 * h
    return best


@inner
def _reach_step(h, speed, g, reach, h_min):
    """Largest step <= h over which speed * h + g h^2 / 2 stays within reach."""
    if speed * h + 0.5 * g * h * h <= reach:
        return h
    return max(h_min, 2.0 * reach / (speed + math.sqrt(speed * speed + 2.0 * g * reach)))


@jit
def run_steps(t, t_stop, now, bodies, shapes, drives, drive_speed, prm, cand, out):
    """Collisions and free flight from t to t_stop (the state ``now`` in place, drives at up
    to ``drive_speed``); returns (t, DONE) or (t, REFRESH) when a dynamic body has moved half
    the candidate margin."""
    pos, ang, vel, om = now
    kind, gravity, radius = bodies.kind, bodies.gravity, bodies.radius_m
    cv_body, cp_body = cand.body, cand.piece_body
    anchor_pos, anchor_ang = cand.anchor_pos, cand.anchor_ang
    margin, width, h_max = prm.margin_m, prm.width_m, prm.h_max
    eps, eps_pen, max_toi, h_min = prm.eps, prm.eps_pen, prm.max_toi, prm.h_min
    counters, fout = out.counters, out.fout
    n = kind.shape[0]
    nc = cv_body.shape[0]
    work = Motion(pos.copy(), ang.copy(), vel.copy(), om.copy())
    pos1, ang1, vel1, om1 = work
    g0 = np.empty(nc)
    u0 = np.empty(nc)
    floor = np.empty(nc)
    center = 0.5 * (eps - eps_pen)
    # a step must still move the clock at late times
    h_floor = max(h_min, 4.0 * np.finfo(np.float64).eps * abs(t_stop))
    while True:
        capped = _resolve(t, now, bodies, shapes, cand, prm, out)
        if t >= t_stop:
            return t, DONE
        moved = speed = 0.0
        for i in range(n):
            if kind[i] == MOVING:
                d = (math.hypot(pos[i, 0] - anchor_pos[i, 0], pos[i, 1] - anchor_pos[i, 1])
                     + abs(ang[i] - anchor_ang[i]) * radius[i])
                moved = max(moved, d)
                speed = max(speed, math.hypot(vel[i, 0], vel[i, 1]) + abs(om[i]) * radius[i])
        if 2.0 * moved > margin:
            return t, REFRESH
        h = min(h_max, t_stop - t)
        # Per step, no dynamic body moves more than a quarter of the candidate margin, and no
        # corner more than a quarter of the thinnest piece relative to any body (tunnelling).
        g = math.hypot(gravity[0], gravity[1])
        h = _reach_step(h, speed, g, 0.25 * margin, h_floor)
        h = _reach_step(h, speed + drive_speed, g, 0.25 * width, h_floor)
        for c in range(nc):
            a, b = cv_body[c], cp_body[c]
            px, py, gap, face = _corner_gap(now, shapes, cand, c, eps)
            g0[c] = gap
            if face < 0:
                u0[c] = 0.0
                floor[c] = -math.inf
                continue
            nx, ny = _face_frame(now, shapes, b, face)
            u0[c] = _gap_rate(now, a, b, px, py, nx, ny)
            floor[c] = min(-eps_pen, gap)
            if capped and u0[c] < 0.0 and -_CAPPED_SINK * eps_pen < gap <= eps:
                # An approach the capped sweeps left may sink the gap one more band: held at
                # its floor, a jam the sweeps never clear (a part wedged between two walls)
                # shrinks every step to h_floor and the clock stalls. Not below a few bands:
                # sweeps that converge too slowly for the cap (a stack of mass ratio 1e4) would
                # sink a part millimetres; there, short steps give them more sweeps.
                floor[c] -= eps_pen
        for it in range(max_toi):
            _poses(t + h, h, bodies, drives, now, work)
            h_new = h
            ok = True
            for c in range(nc):
                _, _, gh, face = _corner_gap(work, shapes, cand, c, eps)
                if face >= 0 and gh < floor[c]:
                    ok = False
                    h_new = min(h_new, _toi(g0[c], u0[c], gh, h, center, floor[c]))
            if ok:
                break
            counters[C_TOI_CUTS] += 1
            if h_new >= h or it >= max_toi // 2:
                h_new = 0.5 * h       # the quadratic model does not hold: bisect
            if h_new <= h_floor or it == max_toi - 1:
                h = max(h_new, h_floor)
                _poses(t + h, h, bodies, drives, now, work)
                counters[C_TOI_GIVE_UP] += 1
                fout[F_GIVE_UP_T] = t
                break
            h = h_new
        # land exactly on t_stop when the step was not shortened
        t = t_stop if h >= t_stop - t else t + h
        pos[:] = pos1
        ang[:] = ang1
        vel[:] = vel1
        om[:] = om1
        counters[C_STEPS] += 1
        for c in range(nc):
            _, _, gap, face = _corner_gap(now, shapes, cand, c, eps)
            if face >= 0 and -gap > fout[F_MAX_PEN]:
                fout[F_MAX_PEN] = -gap
