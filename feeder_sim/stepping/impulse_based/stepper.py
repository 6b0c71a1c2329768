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
  second, and with them the cost of a simulated second, grow as ``eps^-1/2``
  (``benchmarks/methods.py`` times one part at the default envelope).
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

from feeder_sim.contact.candidates import corner_piece_candidates
from feeder_sim.contact.collision import Contacts
from feeder_sim.contact.dynamics import contact_set, MAX_MESSAGES
from feeder_sim.contact.routh import collide, CollisionResult, LAWS
from feeder_sim.model.arrays import body_arrays, shape_arrays
from feeder_sim.model.world import State
from feeder_sim.stepping.impulse_based._kernels import (
    C_COLLISIONS,
    C_STEPS,
    C_SWEEP_CAP,
    C_TOI_GIVE_UP,
    Candidates,
    COUNTER_NAMES,
    DONE,
    F_CAP_T,
    F_GIVE_UP_T,
    F_MAX_PEN,
    ImpulseParams,
    Motion,
    Outputs,
    run_steps,
)
from feeder_sim.stepping.protocol import CheckedSettings, StepContacts, StepperBase

__all__ = ['CollisionResult', 'ImpulseBased', 'ImpulseSettings', 'collide', 'LAWS']


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


# ------------------------------------------------------------------------ the stepper
@dataclass
class _Candidates:
    """Active corners against convex pieces of other bodies, near when detected."""

    vertex: np.ndarray      # (c,) global vertex index
    piece: np.ndarray       # (c,) piece index
    arrays: Candidates      # the kernels' arrays, with the poses at detection
    stroke: np.ndarray      # (n,) widening of driven bodies' boxes used


class ImpulseBased(StepperBase):
    """Mirtich & Canny's impulse-based method: collisions only, one contact point at a time."""

    settings_type = ImpulseSettings
    name = 'impulse_based'
    fixed_steps = True
    error_setting = 'time_step'
    order = None          # its steps adapt below time_step: no known power of it

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
        self._bodies = body_arrays(world)
        self._shapes = shape_arrays(world)
        self._verts = self._shapes.vertices
        self._vertex_body = topo.vertex_body.astype(np.int64)
        self._vertex_piece = topo.vertex_piece.astype(np.int64)
        self._active = np.flatnonzero(topo.vertex_active)
        self._piece_start = sh.piece_start.astype(np.int64)
        self._piece_body = sh.piece_body.astype(np.int64)
        self._max_piece = int(np.max(np.diff(self._piece_start), initial=3))
        dyn_radius = self._bodies.radius_m[world.dynamic]
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
            arrays = Candidates(none, np.zeros((0, 2)), np.zeros((0, 4)), none, none, none,
                                *(np.zeros(0),) * 3, state.position.copy(),
                                state.angle.copy())
            return _Candidates(none, none, arrays, stroke.copy())
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
        arrays = Candidates(a, np.ascontiguousarray(v[vertex]), sides, b, ps[piece],
                            ps[piece + 1], np.ascontiguousarray(mu_s),
                            np.ascontiguousarray(mu_d), np.ascontiguousarray(e),
                            state.position.copy(), state.angle.copy())
        return _Candidates(vertex, piece, arrays, stroke.copy())

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
        prm = ImpulseParams(
            float(self.margin_m), float(self._width), float(self.max_step_s),
            float(self.envelope_m), float(self.penetration_m), float(self.bounce_speed_mps),
            float(st.micro_speed_factor * self.bounce_speed_mps),
            bool(self.spec.friction_impulse), int(LAWS[self.spec.restitution_law]),
            int(st.max_sweeps), int(st.max_toi_iterations), float(st.min_step_s))
        pos = np.ascontiguousarray(state.position, dtype=float)
        ang = np.ascontiguousarray(state.angle, dtype=float)
        vel = np.ascontiguousarray(state.velocity, dtype=float)
        om = np.ascontiguousarray(state.omega, dtype=float)
        now = Motion(pos, ang, vel, om)
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
            out_arrays = Outputs(acc_n, acc_t, acc_geo, self.counters, self._fout)
            t, code = run_steps(t, t_end, now, self._bodies, self._shapes, drives, drive_speed,
                                prm, cand.arrays, out_arrays)
            report = self._report(cand, acc_n, acc_t, acc_geo, State(t, pos, ang, vel, om))
            if report is not None:
                out.append(report)
            if code == DONE:
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
        stats.steps += int(d[C_STEPS])
        stats.impacts += int(d[C_COLLISIONS])
        stats.max_penetration_m = max(stats.max_penetration_m, float(self._fout[F_MAX_PEN]))
        for k, t_idx, what in ((C_SWEEP_CAP, F_CAP_T, 'sequential sweeps hit the cap of '
                                f'{self.settings.max_sweeps}'),
                               (C_TOI_GIVE_UP, F_GIVE_UP_T, 'time-of-impact search gave up')):
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
