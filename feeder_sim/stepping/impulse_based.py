"""``impulse_based``: the impulse-based method of Mirtich & Canny (comparison method).

Every contact interaction is a collision: bodies fly freely under gravity between collisions,
kinematic bodies follow their drives, and any vertex within the *collision envelope* of another
body's piece whose normal relative velocity approaches (``u_N < 0``) takes a single-point
collision impulse. A resting contact is a train of *micro-collisions*; static friction is what
sticking in each of them gives. This is the method the paper compares its simultaneous impulse
LCP against (Fig. 8); physics reference section 2 is the account followed here.

Single-point collision
----------------------
Each collision is the closed-form Routh/Mirtich walk of :mod:`feeder_sim.contact.routh`
(``collide``), with the restitution law of ``spec.restitution_law``.

Sequential multi-point collisions
---------------------------------
Contacts are the active corners of every body against every convex piece of other bodies,
with the gap of a corner = its largest signed distance from the piece's (non-internal) edge
lines and the normal of that edge (the least-penetrated face); within the envelope, only
among the faces the corner can touch (neither of its sides points into the face, as in
``collision.find_contacts``), so a corner meeting a corner takes the face it lies on, not
the end face beside it that would stop every slide along it. At an instant, the contacts
within the envelope are swept in order of most negative ``u_N`` (ties: lower candidate index),
one collision each, re-reading each contact's velocity just before it is processed; sweeps
repeat until no contact approaches. ``max_sweeps`` caps them; hitting the cap is counted in
``stats.fallbacks`` (with a message) and the leftover approach is met at the next step, which
may sink that contact one more ``penetration_m`` (a jam the sweeps never clear, such as a
part wedged between two walls, must not hold the clock).

Micro-collisions
----------------
A collision whose restitution law would leave the contact separating slower than the *bounce
speed* ``v_b`` ends at ``u_N = v_b`` instead (restitution raised for low-speed impacts), with
the incremental friction still acting. ``v_b = sqrt(2 g eps)`` by default: a part resting on a
floor bounces back exactly to the envelope ``eps`` and never rests at zero separation, so the
number of collisions per second stays finite (about ``g / (2 v_b)`` per contact). The raised
restitution is the one place where energy can be added: at most ``K_NN^-1 v_b^2 / 2`` per
collision, i.e. a lift of ``eps``.

``friction_impulse: false`` (the paper's comparison) forces the tangential impulse to zero in
real collisions, those approaching faster than ``micro_speed_factor * v_b``; micro-collisions
keep their friction because they stand for contact forces, which the paper's method keeps too.

Time stepping
-------------
Free flight is exact (ballistic bodies, drives from their sinusoids), so the step size costs no
accuracy; it only has to catch every collision inside the envelope. Each step is at most
``spec.time_step`` and short enough that no body moves more than a quarter of the candidate
margin or of the thinnest piece (no tunnelling). After a trial step every candidate's gap must
stay above its floor ``min(-penetration_m, gap at the step start)`` (one band lower for an
approach left by capped sweeps); otherwise the step is shortened (time of impact) to where
the first failing gap, modelled as a quadratic in time from its value and rate at the start
and its value at the end, comes down to the middle of the band ``[-penetration_m, eps]``,
and tried again; a model that does not shrink the step is replaced by halving. A resting part
is therefore caught a quarter envelope above the surface, rises ``eps`` and is caught again.

Choices, with their reasons:

* ``envelope_m`` = 10 nm. The envelope must be a small fraction of the 0.05-5 mm vibration
  amplitudes, but what decides it is the bounce speed ``v_b = sqrt(2 g eps)``: it is the
  velocity noise of resting contact, which shifts lift-off and landing of a hopping part and
  the stick-slip switches, so it must be small against the conveying speed scale ``g/omega``
  (31 mm/s at 50 Hz). Measured on the 50 Hz conveyor (psi 20 deg, mu 0.5, Gamma 1.2, 60
  cycles, 8-32 steps per period) the mean speed is off the exact point mass by +4.2 % at
  1 um (v_b 4.4 mm/s), +1.5...+2.3 % at 0.2 um, +0.4...+1.2 % at 50 nm and -0.1...+0.6 % at
  10 nm (v_b 0.44 mm/s); the spread is the chaotic order of micro-collisions. Collisions per
  second grow as ``eps^-1/2``: 10 nm costs ~0.1 s of wall time per simulated second for one
  part.
* ``penetration_m`` = half the envelope: the floor the time-of-impact search keeps every gap
  above; the resting part's worst sink.
* ``bounce_speed_mps`` = ``sqrt(2 |g| eps)`` (0.44 mm/s): bounce back to the envelope.
* ``max_sweeps`` = 100: a flat box landing on two corners needs a few (the coupling of the two
  corners shrinks the leftover approach by about ``(K_AB/K_AA)^2`` per sweep).
* largest step ``spec.time_step`` (the builders give 1/16 of the vibration period): the step
  does not enter the accuracy, the envelope does.

Known artefact (of the method, not of this code): between two micro-collisions nothing holds a
resting part, so on a slope it slips by ``g sin(theta) T^2 / 2`` per bounce of length
``T = 2 v_b / g_n``; the next micro-collision stops the slip but not the displacement. A part
that should stick on an incline creeps at about ``tan(theta) v_b`` (0.15 mm/s at 20 deg with the
default envelope); it vanishes only as ``sqrt(eps)``. Where sticking at a corner is unstable
(``|K_TN| > mu_static K_TT``, e.g. 0.75 for the corner of a 2:1 box) each micro-collision ends
with a small reversed slip as well.

Restick
-------
A part that comes to rest on a slope steeper than ``atan(mu_dynamic)`` but within
``atan(mu_static)`` is held by static friction. Between two micro-collisions nothing holds it,
so it arrives at each one slipping by what gravity and the drives built up in the flight
(about ``2 tan(theta) v_b``). Met with dynamic friction, that slip is only partly taken back
and grows until the part slides off at ``g (sin - mu_d cos)``. A micro-collision of a resting
contact therefore uses ``mu_static`` on its sliding ray while the slip is at most
``2 mu_static`` times the micro-collision speed ``micro_speed_factor * v_b`` (the slip a holdable
slope can build in one hop, with a factor 2 for hops that start late): the part sticks and only
creeps as above. The price is bounded by the same speed: a part that really slides at less
than ``4 mu_static v_b`` (1 mm/s at mu_static = 0.6) is stopped by static friction, and a slip
that must reverse (a slope static friction cannot hold) starts that much late.

The whole loop (contacts, sweeps, time of impact, free flight) runs in one compiled kernel per
set of candidates; Python re-detects candidates (bounding boxes within the candidate margin,
driven bodies widened by their stroke) only when a dynamic body has moved half that margin.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import ClassVar

import numpy as np

from feeder_sim._jit import inner, jit
from feeder_sim.contact.candidates import corner_piece_candidates
from feeder_sim.contact.collision import Contacts
from feeder_sim.contact.dynamics import contact_set, MAX_MESSAGES
from feeder_sim.contact.routh import (
    collide,
    CollisionResult,
    JAM,
    LAWS,
    REVERSE,
    routh_collision,
    STICK,
)
from feeder_sim.model.vibration import segment_motion
from feeder_sim.model.world import DRIVEN, FIXED, MOVING, State
from feeder_sim.stepping.protocol import CheckedSettings, StepContacts, StepperBase

__all__ = ['CollisionResult', 'ImpulseBased', 'ImpulseSettings', 'collide', 'LAWS']


# kinds of bodies in the kernel
# kernel return codes
_DONE, _REFRESH = 0, 1
# kernel counters
(_C_STEPS, _C_COLLISIONS, _C_MICRO, _C_SWEEPS, _C_MOST_SWEEPS, _C_SWEEP_CAP, _C_TOI_CUTS,
 _C_TOI_GIVE_UP, _C_JAMS, _C_STICKS, _C_REVERSALS) = range(11)
COUNTER_NAMES = ('steps', 'collisions', 'micro_collisions', 'sweeps', 'most_sweeps_at_once',
                 'sweep_cap_hits', 'toi_cuts', 'toi_give_ups', 'jams', 'sticks', 'reversals')
# float outputs of the kernel
_F_MAX_PEN, _F_CAP_T, _F_GIVE_UP_T = 0, 1, 2


@dataclass
class ImpulseSettings(CheckedSettings):
    """Tuning of the impulse-based method (SI units). ``None`` means derived, as documented;
    every value is checked when set."""

    LIMITS: ClassVar[dict[str, str]] = {
        'envelope_m': '> 0', 'penetration_m': '> 0', 'bounce_speed_mps': '>= 0',
        'micro_speed_factor': '>= 0', 'max_step_s': '> 0', 'max_sweeps': '>= 1',
        'max_toi_iterations': '>= 0', 'min_step_s': '> 0', 'candidate_margin_m': '>= 0'}

    envelope_m: float = 1e-8
    """Collision envelope eps: corners closer than this to a piece are in contact."""
    penetration_m: float | None = None
    """Deepest sink a step may cause (time-of-impact floor); default ``envelope_m / 2``."""
    bounce_speed_mps: float | None = None
    """Least separation speed after a collision; default ``sqrt(2 |g| envelope_m)``."""
    micro_speed_factor: float = 2.0
    """Collisions approaching slower than this times the bounce speed are micro-collisions
    (resting contact): they keep friction when ``friction_impulse`` is off."""
    max_step_s: float | None = None
    """Largest step; default (and upper bound) ``spec.time_step``."""
    max_sweeps: int = 100
    """Sequential sweeps over the contacts of one instant before giving up (counted)."""
    max_toi_iterations: int = 60
    """Step shortenings tried before a step is taken anyway (counted)."""
    min_step_s: float = 1e-12
    """Shortest step the time-of-impact search takes."""
    candidate_margin_m: float | None = None
    """Broad-phase margin; default max(0.1 x smallest dynamic body radius, 100 envelopes)."""


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
def _poses(t1, h, kind, drive_row, drives, gravity, pos, ang, vel, om, pos1, ang1, vel1, om1):
    """Free flight from t1 - h to t1: ballistic dynamic bodies, driven bodies on their drives."""
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
def _corner_gap(pos, ang, a, local, sides, b, start, end, verts, normals, internal, eps):
    """World point of corner ``local`` of body a, its gap to body b's piece and the face.

    Outside the envelope the gap is the largest signed distance from the piece's outer edge
    lines (a lower bound of the true distance). Within it, the face is the least-penetrated
    one the corner can touch: neither of its sides (``sides``, body-frame unit vectors
    towards its neighbours) may point into the face by more than ``_SIDE_ANGLE`` (the
    supporting-vertex test of ``collision.find_contacts``). A corner meeting a corner is
    otherwise taken against the end face beside it, whose normal stops every slide along the
    other face."""
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
def _face_frame(ang, body, normals, face):
    c, s = math.cos(ang[body]), math.sin(ang[body])
    return c * normals[face, 0] - s * normals[face, 1], s * normals[face, 0] + c * normals[face, 1]


@inner
def _relative(vel, om, a, b, rax, ray, rbx, rby, nx, ny):
    """(u_T, u_N) of a's corner against b's material point, tangent = normal rotated +90."""
    relx = (vel[a, 0] - om[a] * ray) - (vel[b, 0] - om[b] * rby)
    rely = (vel[a, 1] + om[a] * rax) - (vel[b, 1] + om[b] * rbx)
    return -ny * relx + nx * rely, nx * relx + ny * rely


@inner
def _gap_rate(pos, ang, vel, om, a, b, px, py, nx, ny):
    _, un = _relative(vel, om, a, b, px - pos[a, 0], py - pos[a, 1], px - pos[b, 0],
                      py - pos[b, 1], nx, ny)
    return un


# ------------------------------------------------------------------------ kernel: collisions
@inner
def _resolve(t, pos, ang, vel, om, inv_mass, inv_inertia, cv_body, cv_local, cv_sides, cp_body,
             cp_start, cp_end, c_mu_s, c_mu_d, c_e, verts, normals, internal, eps, v_sep,
             micro_speed, friction_on, law, max_sweeps, acc_n, acc_t, acc_geo, counters, fout):
    """Sequential collisions of every approaching contact within the envelope at time t;
    returns whether the sweeps hit their cap (some contact may still approach)."""
    nc = cv_body.shape[0]
    idx = np.empty(nc, np.int64)
    geo = np.empty((nc, 9))     # rax, ray, rbx, rby, nx, ny, ktt, ktn, knn
    face_of = np.empty(nc, np.int64)
    m = 0
    for c in range(nc):
        a, b = cv_body[c], cp_body[c]
        px, py, gap, face = _corner_gap(pos, ang, a, cv_local[c], cv_sides[c], b, cp_start[c],
                                        cp_end[c], verts, normals, internal, eps)
        if face < 0 or gap > eps:
            continue
        if -gap > fout[_F_MAX_PEN]:
            fout[_F_MAX_PEN] = -gap
        nx, ny = _face_frame(ang, b, normals, face)
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
            _, un_now[k] = _relative(vel, om, a, b, geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 3],
                                     geo[k, 4], geo[k, 5])
        if un_now.min() >= 0.0:
            return False
        if sweeps >= max_sweeps:
            counters[_C_SWEEP_CAP] += 1
            fout[_F_CAP_T] = t
            return True
        sweeps += 1
        counters[_C_SWEEPS] += 1
        counters[_C_MOST_SWEEPS] = max(counters[_C_MOST_SWEEPS], sweeps)
        order = np.argsort(un_now, kind='mergesort')
        for o in range(m):
            k = order[o]
            if un_now[k] >= 0.0:
                break
            c = idx[k]
            a, b = cv_body[c], cp_body[c]
            rax, ray, rbx, rby, nx, ny = (geo[k, 0], geo[k, 1], geo[k, 2], geo[k, 3], geo[k, 4],
                                          geo[k, 5])
            ut, un = _relative(vel, om, a, b, rax, ray, rbx, rby, nx, ny)
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
            counters[_C_COLLISIONS] += 1
            counters[_C_MICRO] += 1 if micro else 0
            counters[_C_JAMS] += 1 if phases & JAM else 0
            counters[_C_STICKS] += 1 if phases & STICK else 0
            counters[_C_REVERSALS] += 1 if phases & REVERSE else 0


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
def _run(t, t_stop, pos, ang, vel, om, kind, drive_row, drives, drive_speed, gravity,
         inv_mass, inv_inertia, radius, cv_body, cv_local, cv_sides, cp_body, cp_start, cp_end,
         c_mu_s, c_mu_d, c_e, verts, normals, internal, anchor_pos, anchor_ang, margin, width,
         h_max, eps, eps_pen, v_sep, micro_speed, friction_on, law, max_sweeps, max_toi, h_min,
         acc_n, acc_t, acc_geo, counters, fout):
    """Collisions and free flight from t to t_stop (state arrays in place); returns
    (t, _DONE) or (t, _REFRESH) when a dynamic body has moved half the candidate margin."""
    n = kind.shape[0]
    nc = cv_body.shape[0]
    pos1, ang1, vel1, om1 = pos.copy(), ang.copy(), vel.copy(), om.copy()
    g0 = np.empty(nc)
    u0 = np.empty(nc)
    floor = np.empty(nc)
    center = 0.5 * (eps - eps_pen)
    # a step must still move the clock at late times
    h_floor = max(h_min, 4.0 * np.finfo(np.float64).eps * abs(t_stop))
    while True:
        capped = _resolve(t, pos, ang, vel, om, inv_mass, inv_inertia, cv_body, cv_local,
                          cv_sides, cp_body,
                 cp_start, cp_end, c_mu_s, c_mu_d, c_e, verts, normals, internal, eps, v_sep,
                 micro_speed, friction_on, law, max_sweeps, acc_n, acc_t, acc_geo, counters,
                 fout)
        if t >= t_stop:
            return t, _DONE
        moved = speed = 0.0
        for i in range(n):
            if kind[i] == MOVING:
                d = (math.hypot(pos[i, 0] - anchor_pos[i, 0], pos[i, 1] - anchor_pos[i, 1])
                     + abs(ang[i] - anchor_ang[i]) * radius[i])
                moved = max(moved, d)
                speed = max(speed, math.hypot(vel[i, 0], vel[i, 1]) + abs(om[i]) * radius[i])
        if 2.0 * moved > margin:
            return t, _REFRESH
        h = min(h_max, t_stop - t)
        # Per step, no dynamic body moves more than a quarter of the candidate margin, and no
        # corner more than a quarter of the thinnest piece relative to any body (tunnelling).
        g = math.hypot(gravity[0], gravity[1])
        h = _reach_step(h, speed, g, 0.25 * margin, h_floor)
        h = _reach_step(h, speed + drive_speed, g, 0.25 * width, h_floor)
        for c in range(nc):
            a, b = cv_body[c], cp_body[c]
            px, py, gap, face = _corner_gap(pos, ang, a, cv_local[c], cv_sides[c], b,
                                            cp_start[c], cp_end[c], verts, normals, internal,
                                            eps)
            g0[c] = gap
            if face < 0:
                u0[c] = 0.0
                floor[c] = -math.inf
                continue
            nx, ny = _face_frame(ang, b, normals, face)
            u0[c] = _gap_rate(pos, ang, vel, om, a, b, px, py, nx, ny)
            floor[c] = min(-eps_pen, gap)
            if capped and u0[c] < 0.0 and -_CAPPED_SINK * eps_pen < gap <= eps:
                # An approach the capped sweeps left may sink the gap one more band: held at
                # its floor, a jam the sweeps never clear (a part wedged between two walls)
                # shrinks every step to h_floor and the clock stalls. Not below a few bands:
                # sweeps that converge too slowly for the cap (a stack of mass ratio 1e4) would
                # sink a part millimetres; there, short steps give them more sweeps.
                floor[c] -= eps_pen
        for it in range(max_toi):
            _poses(t + h, h, kind, drive_row, drives, gravity, pos, ang, vel, om, pos1, ang1,
                   vel1, om1)
            h_new = h
            ok = True
            for c in range(nc):
                _, _, gh, face = _corner_gap(pos1, ang1, cv_body[c], cv_local[c], cv_sides[c],
                                             cp_body[c], cp_start[c], cp_end[c], verts,
                                             normals, internal, eps)
                if face >= 0 and gh < floor[c]:
                    ok = False
                    h_new = min(h_new, _toi(g0[c], u0[c], gh, h, center, floor[c]))
            if ok:
                break
            counters[_C_TOI_CUTS] += 1
            if h_new >= h or it >= max_toi // 2:
                h_new = 0.5 * h       # the quadratic model does not hold: bisect
            if h_new <= h_floor or it == max_toi - 1:
                h = max(h_new, h_floor)
                _poses(t + h, h, kind, drive_row, drives, gravity, pos, ang, vel, om, pos1,
                       ang1, vel1, om1)
                counters[_C_TOI_GIVE_UP] += 1
                fout[_F_GIVE_UP_T] = t
                break
            h = h_new
        # land exactly on t_stop when the step was not shortened
        t = t_stop if h >= t_stop - t else t + h
        pos[:] = pos1
        ang[:] = ang1
        vel[:] = vel1
        om[:] = om1
        counters[_C_STEPS] += 1
        for c in range(nc):
            _, _, gap, face = _corner_gap(pos, ang, cv_body[c], cv_local[c], cv_sides[c],
                                          cp_body[c], cp_start[c], cp_end[c], verts, normals,
                                          internal, eps)
            if face >= 0 and -gap > fout[_F_MAX_PEN]:
                fout[_F_MAX_PEN] = -gap


# ------------------------------------------------------------------------ the stepper
@dataclass
class _Candidates:
    """Active corners against convex pieces of other bodies, near when detected."""

    vertex: np.ndarray      # (c,) global vertex index
    piece: np.ndarray       # (c,) piece index
    arrays: tuple           # kernel arrays (see ImpulseBased._find_candidates)
    anchor_pos: np.ndarray  # (n, 2) positions at detection
    anchor_ang: np.ndarray  # (n,)
    stroke: np.ndarray      # (n,) widening of driven bodies' boxes used


class ImpulseBased(StepperBase):
    """Mirtich & Canny's impulse-based method: collisions only, one contact point at a time."""

    settings_type = ImpulseSettings

    def prepare(self) -> None:
        world, spec = self.world, self.spec
        st = self.settings
        if spec.restitution_law not in LAWS:
            raise ValueError(f'restitution_law must be one of {", ".join(LAWS)}, got '
                             f'{spec.restitution_law!r}')
        if not st.envelope_m > 0:
            raise ValueError('envelope_m must be > 0')
        g = float(np.linalg.norm(world.gravity))
        self.envelope_m = st.envelope_m
        self.penetration_m = (st.penetration_m if st.penetration_m is not None
                              else 0.5 * st.envelope_m)
        # with no gravity the bounce speed of the envelope under 1 g keeps micro-collisions finite
        self.bounce_speed_mps = (st.bounce_speed_mps if st.bounce_speed_mps is not None
                                 else math.sqrt(2.0 * (g or 9.81) * st.envelope_m))
        self.max_step_s = min(spec.time_step, st.max_step_s or math.inf)
        sh = world.shapes
        topo = sh.derived
        self._verts = np.ascontiguousarray(sh.vertices, dtype=float)
        self._normals = np.ascontiguousarray(sh.normals, dtype=float)
        self._internal = np.ascontiguousarray(topo.edge_internal, dtype=np.bool_)
        self._vertex_body = topo.vertex_body.astype(np.int64)
        self._vertex_piece = topo.vertex_piece.astype(np.int64)
        self._active = np.flatnonzero(topo.vertex_active)
        self._piece_start = sh.piece_start.astype(np.int64)
        self._piece_body = sh.piece_body.astype(np.int64)
        self._max_piece = int(np.max(np.diff(self._piece_start), initial=3))
        dyn = world.dynamic
        self._kind = np.where(dyn, MOVING, FIXED).astype(np.int64)
        self._kind[world.driven] = DRIVEN
        self._drive_row = np.full(world.n, -1, np.int64)
        self._drive_row[world.driven] = np.arange(len(world.driven))
        self._radius = world.radius.astype(float)
        dyn_radius = self._radius[dyn]
        small = float(dyn_radius.min()) if dyn_radius.size else 1e-2
        self.margin_m = (st.candidate_margin_m if st.candidate_margin_m is not None
                         else max(0.1 * small, 100.0 * st.envelope_m))
        # thinnest piece, against tunnelling
        self._width = float(topo.piece_width.min()) if topo.piece_width.size else math.inf
        self._materials = world.pair_materials
        self.counters = np.zeros(len(COUNTER_NAMES), np.int64)
        self._fout = np.zeros(3)
        self._cand: _Candidates | None = None

    @property
    def counts(self) -> dict[str, int]:
        """Kernel counters since construction (steps, collisions, sweeps, ...)."""
        return {k: int(v) for k, v in zip(COUNTER_NAMES, self.counters, strict=True)}

    def reset(self) -> None:
        """Forget the candidates (after a vibration command or a reset)."""
        self._cand = None

    # ------------------------------------------------------------------ candidates
    def _find_candidates(self, state: State, stroke: np.ndarray) -> _Candidates:
        """Active corners against pieces of other bodies whose boxes are within the margin;
        a driven body's box is widened by its whole stroke (it never leaves it)."""
        vb, ps, pb = self._vertex_body, self._piece_start, self._piece_body
        if len(pb) < 2:
            none = np.zeros(0, np.int64)
            arrays = (none, np.zeros((0, 2)), np.zeros((0, 4)), none, none, none,
                      *(np.zeros(0),) * 3)
            return _Candidates(none, none, arrays, state.position.copy(), state.angle.copy(),
                               stroke.copy())
        margin = self.margin_m
        cand = corner_piece_candidates(self.world, state, self._active, margin, stroke)
        vertex, piece, wx, wy, lo, hi = cand
        v = self._verts
        # the corner itself must lie within the margin of the piece's (widened) box
        px, py = wx[vertex], wy[vertex]
        reach = margin + stroke[vb[vertex]]
        inside = ((px >= lo[piece, 0] - reach) & (px <= hi[piece, 0] + reach) &
                  (py >= lo[piece, 1] - reach) & (py <= hi[piece, 1] + reach))
        vertex, piece = vertex[inside], piece[inside]
        a, b = vb[vertex], pb[piece]
        mu_s, mu_d, e = (m[a, b] for m in self._materials)
        topo = self.world.shapes.derived
        prev = topo.prev_vertex[vertex]
        sides = np.concatenate([(v[prev] - v[vertex]) / topo.edge_length[prev, None],
                                (v[topo.next_vertex[vertex]] - v[vertex])
                                / topo.edge_length[vertex, None]], axis=1)
        arrays = (a, np.ascontiguousarray(v[vertex]), sides, b, ps[piece], ps[piece + 1],
                  np.ascontiguousarray(mu_s), np.ascontiguousarray(mu_d),
                  np.ascontiguousarray(e))
        return _Candidates(vertex, piece, arrays, state.position.copy(), state.angle.copy(),
                           stroke.copy())

    # ------------------------------------------------------------------ stepping
    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Integrate ``state`` in place to ``t_end``; returns the impulses transmitted."""
        w, st = self.world, self.settings
        out: list[StepContacts] = []
        if not state.t < t_end:
            return out
        drives = w.drive_segments(state.t)
        drive_speed = drives.speed_bound_mps()
        stroke = np.zeros(w.n)
        stroke[w.driven] = drives.stroke_m()
        if self._cand is not None and np.any(stroke > self._cand.stroke):
            self._cand = None      # a drive command widened the stroke
        law = LAWS[self.spec.restitution_law]
        pos = np.ascontiguousarray(state.position, dtype=float)
        ang = np.ascontiguousarray(state.angle, dtype=float)
        vel = np.ascontiguousarray(state.velocity, dtype=float)
        om = np.ascontiguousarray(state.omega, dtype=float)
        before = self.counters.copy()
        t = state.t
        while True:
            if self._cand is None:
                self._cand = self._find_candidates(
                    State(t, pos, ang, vel, om), stroke)
            cand = self._cand
            nc = len(cand.vertex)
            acc_n = np.zeros((nc, self._max_piece))
            acc_t = np.zeros((nc, self._max_piece))
            acc_geo = np.zeros((nc, self._max_piece, 5))
            t, code = _run(
                t, t_end, pos, ang, vel, om, self._kind, self._drive_row, drives, drive_speed,
                w.gravity, w.inv_mass, w.inv_inertia, self._radius, *cand.arrays, self._verts,
                self._normals, self._internal, cand.anchor_pos, cand.anchor_ang, self.margin_m,
                self._width, self.max_step_s, self.envelope_m, self.penetration_m,
                self.bounce_speed_mps, st.micro_speed_factor * self.bounce_speed_mps,
                bool(self.spec.friction_impulse), law, st.max_sweeps, st.max_toi_iterations,
                st.min_step_s, acc_n, acc_t, acc_geo, self.counters, self._fout)
            report = self._report(cand, acc_n, acc_t, acc_geo, State(t, pos, ang, vel, om))
            if report is not None:
                out.append(report)
            if code == _DONE:
                break
            self._cand = None
        state.t = t
        state.position[:] = pos
        state.angle[:] = ang
        state.velocity[:] = vel
        state.omega[:] = om
        w.apply_prescribed_motion(state)
        self._record(before)
        return out

    def _record(self, before: np.ndarray) -> None:
        d = self.counters - before
        stats = self.stats
        stats.steps += int(d[_C_STEPS])
        stats.impacts += int(d[_C_COLLISIONS])
        stats.max_penetration_m = max(stats.max_penetration_m, float(self._fout[_F_MAX_PEN]))
        for k, t_idx, what in ((_C_SWEEP_CAP, _F_CAP_T, 'sequential sweeps hit the cap of '
                                f'{self.settings.max_sweeps}'),
                               (_C_TOI_GIVE_UP, _F_GIVE_UP_T, 'time-of-impact search gave up')):
            if d[k]:
                stats.fallbacks += int(d[k])
                if len(stats.messages) < MAX_MESSAGES:
                    stats.messages.append(f'impulse_based: {what} {int(d[k])} time(s), last at '
                                          f't = {self._fout[t_idx]:.6f} s')

    def _report(self, cand: _Candidates, acc_n: np.ndarray, acc_t: np.ndarray,
                acc_geo: np.ndarray, state: State) -> StepContacts | None:
        """Impulses summed per vertex-edge feature over one kernel run (point, normal and gap
        of the feature's latest contact; edge parameter at the end of the run)."""
        ci, fi = np.nonzero(acc_n > 0.0)
        if not len(ci):
            return None
        topo = self.world.shapes.derived
        vertex = cand.vertex[ci]
        edge = self._piece_start[cand.piece[ci]] + fi
        geo = acc_geo[ci, fi]
        q0 = self._verts[edge]
        q1 = self._verts[topo.next_vertex[edge]]
        b = self._vertex_body[edge]
        c, s = np.cos(state.angle[b]), np.sin(state.angle[b])
        p0 = state.position[b] + np.stack([c * q0[:, 0] - s * q0[:, 1],
                                           s * q0[:, 0] + c * q0[:, 1]], 1)
        e = np.stack([c * (q1 - q0)[:, 0] - s * (q1 - q0)[:, 1],
                      s * (q1 - q0)[:, 0] + c * (q1 - q0)[:, 1]], 1)
        param = np.sum((geo[:, :2] - p0) * e, 1) / np.sum(e * e, 1)
        contacts = Contacts(
            body_a=self._vertex_body[vertex], piece_a=self._vertex_piece[vertex],
            vertex_a=vertex, body_b=b, piece_b=cand.piece[ci], edge_b=edge,
            point=geo[:, :2].copy(), normal=geo[:, 2:4].copy(), gap=geo[:, 4].copy(),
            edge_param=param)
        return StepContacts(contact_set(self.world, state, contacts), acc_n[ci, fi].copy(),
                            acc_t[ci, fi].copy())
