"""``event_driven``: the paper's scheme (accuracy method).

Between events the bodies move smoothly under gravity, prescribed track motion and contact
forces. The contact *mode* — which contacts press (normal force, zero normal acceleration),
which stick (zero tangential acceleration) and which slide (friction ``-sigma mu_d f_N``) — is
chosen by Baraff's frictional force LCP at the start of a phase and then held. Each phase
watches event functions; the first one to cross zero ends the phase at the located time:

=====================  ============================================  =====================
event                  function that must stay >= 0                  what happens
=====================  ============================================  =====================
collision              distance of a corner outside a nearby piece   impulse LCP (Kawachi)
lift-off / tipping     normal force of a pressing contact            new force LCP
stick -> slip          mu_s sum f_N - |sum f_T| of a sticking group  new force LCP
slip -> stick/reverse  sigma v_T of a sliding contact                new force LCP
sliding off an edge    edge parameter in [0, 1]                      new contact detection
=====================  ============================================  =====================

Phases are followed in one of two ways:

* **Closed form**, when every dynamic body either flies free (no held contact) or translates
  without turning against static or sinusoidally driven bodies, touching them only with its
  own vertices (a box lying, sticking or sliding on a track). The held mode's equations are
  then linear with constant coefficients in gravity and the drives' accelerations ``s(t)``, so
  one least-squares solve at the phase start gives every body's acceleration
  ``phi0 + phi1 s(t)`` and every contact force ``f0 + f1 s(t)``; positions, velocities,
  forces and the transmitted impulses follow exactly from the drives' sinusoids. Nothing is
  integrated: the events are evaluated at the ends of steps of the largest step size (or
  shorter, see below) and a crossing is located by Illinois regula falsi on the exact state.
* **Integrated** otherwise (a body rotating on a corner, bodies pressing on each other): a
  Dormand–Prince 5(4) integrator with error control follows the held mode, and an event is
  located by Illinois regula falsi on full integrator steps from the step start. The
  right-hand side (contact geometry, Jacobian, the held mode's least-squares forces, event
  functions) and the steps are compiled; while a drive blends after a command it is not a
  plain sinusoid, and a Python right-hand side that asks the drives takes over.

The kernels are in :mod:`._kernels`. A single dynamic body's closed-form phases are chained in
compiled code (:mod:`._chain`) through the events its own contacts resolve (a slip stopping or
reversing, static friction giving way, a lift-off, a corner landing on a face): Python then sees
only the rest (a corner leaving its edge, touching near a corner, an LCP the pivoting misses, a
mode without closed form).

Candidate collisions are the active corners of every piece against every other piece whose
bounding box lay within a margin when they were detected; they are detected again only when a
body may have moved half that margin since (in closed form from a bound on the exact
velocities, when integrating from a heuristic reach per step). A collision is a candidate's gap
(the corner's largest signed distance from the piece's edge lines) dropping below zero; lines
the corner lies flush on with its own piece on their inner side are left out, or blocks meeting
face-on with aligned corners, every corner on the line of a side face of the other block, would
never show a negative gap. No step lets a corner travel, relative to a candidate piece, farther
than its gap plus half the piece's minimum width (conservative advancement): a fast part cannot
pass through a thin wall between two event tests, and a slow or distant one does not shorten
the step.

The impulse and force LCPs first try the final active set of the last pivoting solve of a
problem of the same shape and keep it when the LCP residual accepts it: the events of a
periodic motion pose nearly the same problems every cycle.

Parallel contacts between the same two bodies (an edge lying on an edge) share their loads in
a way rigid-body mechanics leaves open, so friction is tested on the group's totals. When the
force LCP has no solution (Painlevé configurations) the contact takes an impulse without
collision, as Baraff and the reference recommend.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from feeder_sim.contact import lcp
from feeder_sim.contact.candidates import corner_piece_candidates
from feeder_sim.contact.collision import Contacts, evaluate_gaps, find_contacts
from feeder_sim.contact.dynamics import (
    BOX,
    contact_set,
    ContactSet,
    friction_rows,
    island_jacobian,
    islands,
    NONE,
    SLAVED,
)
from feeder_sim.model.world import DRIVEN, FIXED, MOVING, perp, rot, State, World
from feeder_sim.stepping.event_driven import _chain as chain
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.protocol import StepContacts, StepperBase

STICK, SLIDE = kern.STICK, kern.SLIDE
assert (BOX, SLAVED) == (kern.BOX_ROW, kern.SLAVED_ROW)
# Event functions are scaled to O(1); one fires when it drops below -_EVENT_THRESHOLD, so a
# function that starts a phase at zero (a contact that just separated) does not fire on noise.
_EVENT_THRESHOLD = 1e-9
_GIVE_WAY_S = 1e-9            # first step past an event cascade (s)
_GAP_SCALE_M = 1e-3   # gaps fire at -1e-12 m
# A body counts as not turning when its rotation moves its points by less than this fraction of
# the slip tolerance (impacts on a flat leave ~1e-16 m/s of round-off spin) and the held mode
# gives it no angular acceleration beyond round-off (relative to g over its radius).
_SPIN_FRACTION = 1e-3
_ALPHA_REL = 1e-12
# Rows of contact impulses a compiled chain of phases can record; near full, it hands the next
# event back to the general path.
_CHAIN_ROWS = 512

# The Dormand–Prince 5(4) tableau of the compiled integrator, as the Python path reads it:
# stage i's coefficients, the 5th-order (FSAL) weights and the error weights.
_C = kern.DP_C
_A = [[float(a) for a in kern.DP_A[i, :i]] for i in range(7)]
_B5 = np.array(_A[6] + [0.0])
_E = kern.DP_E


@dataclass
class EventSettings:
    touch_m: float = 1e-9        # a vertex this close to an edge is in contact
    slip_tol_mps: float = 1e-9   # |v_T| below this is sticking
    rest_speed_mps: float = 1e-4  # impacts slower than this are plastic (no Zeno bouncing)
    lcp_tol: float = 1e-9
    max_events_at_one_time: int = 50
    cascade_window_s: float = 1e-6   # events closer than this in time count as one cascade
    max_give_way_s: float = 1e-5     # longest step taken past a persisting cascade
    # One dynamic body: follow its closed-form phases through the events its own contacts
    # resolve in compiled code (:mod:`._chain`); False takes each event through the general
    # path (the same answers to round-off, several times slower).
    chained: bool = True


@dataclass
class _Candidates:
    """Active corners that may enter a nearby piece of another body (collision events)."""

    vertex: np.ndarray        # (c,) global vertex index
    piece: np.ndarray         # (c,) piece the vertex may enter
    arrays: tuple             # kernel arrays (see _candidate_arrays)
    anchor_pos: np.ndarray    # (n, 2) poses at detection
    anchor_ang: np.ndarray    # (n,)
    margin: float             # bounding boxes farther apart than this were left out
    t: float                  # detection time
    # candidates without each held contact set met so far (see without)
    reduced: dict = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        return len(self.vertex)

    def without(self, held: Contacts) -> _Candidates:
        """Leave out the corners held on an edge of the piece: they stay on its boundary,
        watched by their own events."""
        if not held.n or not self.n:
            return self
        # The modes of a periodic motion hold the same few contact sets again and again.
        key = (held.vertex_a.tobytes(), held.piece_b.tobytes())
        out = self.reduced.get(key)
        if out is None:
            keep = kern.held_mask(self.vertex, self.piece, held.vertex_a, held.piece_b)
            out = self.reduced[key] = _Candidates(
                self.vertex[keep], self.piece[keep], tuple(x[keep] for x in self.arrays),
                self.anchor_pos, self.anchor_ang, self.margin, self.t)
        return out


@dataclass
class _Phase:
    """Kernel arrays of a closed-form phase (see :mod:`._kernels`)."""

    kind: np.ndarray          # (n,) FIXED / DRIVEN / MOVING
    index: np.ndarray         # (n,) drive of a DRIVEN body
    phi0: np.ndarray          # (n, 2) acceleration without drive terms
    phi1: np.ndarray          # (n, 2, nd) acceleration per unit drive acceleration
    drives: tuple             # (u, base position, amplitude, omega, phase at t_ref, t_ref)
    contacts: tuple           # held contacts: geometry, force coefficients, friction state
    f0: np.ndarray            # (2k,) contact forces without drive terms
    f1: np.ndarray            # (2k, nd)


@dataclass
class _Mode:
    """The contact mode held during one smooth phase."""

    features: Contacts        # active contacts (geometry at the phase start)
    friction: np.ndarray      # (k,) NONE / STICK / SLIDE
    sigma: np.ndarray         # (k,) slip direction of sliding contacts
    group: np.ndarray         # (k,) parallel-contact group id
    material: tuple           # (mu_static, mu_dynamic, restitution) of each contact
    held: tuple               # kernel arrays of the held contacts (forces filled by a phase)
    n_events: int             # event functions besides the candidate collisions
    candidates: _Candidates | None = None
    phase: _Phase | None = None   # closed-form description, if the mode has one
    spec: tuple | None = None     # compiled right-hand side, when integrated and supported
    drive_acc: np.ndarray | None = None   # (n,) largest drive acceleration (m/s^2), once used


def _with_geometry(world: World, features: Contacts, state: State) -> ContactSet:
    """The same vertex-edge features re-evaluated at another configuration."""
    sh = world.shapes
    a, b = features.body_a, features.body_b
    point = state.position[a] + np.einsum('kij,kj->ki', rot(state.angle[a]),
                                          sh.vertices[features.vertex_a])
    normal = np.einsum('kij,kj->ki', rot(state.angle[b]), sh.normals[features.edge_b])
    gap, param = evaluate_gaps(sh, features, state.position, state.angle) if features.n else (
        np.zeros(0), np.zeros(0))
    moved = Contacts(features.body_a, features.piece_a, features.vertex_a, features.body_b,
                     features.piece_b, features.edge_b, point, normal, gap, param)
    return contact_set(world, state, moved)


def _relative_velocity(cs: ContactSet, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Normal and tangential relative velocity of every contact, as
    :func:`feeder_sim.contact.dynamics.relative_velocity` gives them."""
    c = cs.contacts
    return kern.relative_velocity(c.normal, cs.r_a, cs.r_b, c.body_a, c.body_b, state.velocity,
                                  state.omega)


def _groups(cs: ContactSet) -> np.ndarray:
    """Group ids of contacts between the same two bodies along one line (parallel normals)."""
    c = cs.contacts
    return kern.contact_groups(c.body_a, c.body_b, c.normal)


class EventDriven(StepperBase):
    """Advances a state to any requested time, stopping at every contact event."""

    settings_type = EventSettings

    def prepare(self) -> None:
        world, spec = self.world, self.spec
        self.rtol = spec.tolerance
        dyn = np.flatnonzero(world.dynamic)
        self._dyn = dyn
        sh = world.shapes
        radius = self._radius = world.radius
        length = float(np.max(radius[dyn], initial=1e-2))
        g = float(np.linalg.norm(world.gravity)) or 9.81
        self._g = g
        speed = math.sqrt(g * length)
        for i in world.driven:
            d = world.drives[i]
            speed = max(speed, 2 * math.pi * d.frequency_hz * d.amplitude_m)
        nd = len(dyn)
        self._scale = np.concatenate([np.full(2 * nd, length), np.ones(nd),
                                      np.full(2 * nd, speed), np.full(nd, speed / length)])
        self._force_scale = float(np.max(world.mass[dyn] * g, initial=1.0))
        self._speed = speed
        self._length = length
        # A slip event fires once sigma v_T / speed is below -_EVENT_THRESHOLD, i.e. with the
        # slip already reversed by up to _EVENT_THRESHOLD * speed. Below that speed a contact
        # must count as not sliding, or a part too large for the default (metre-sized:
        # speed ~ 3 m/s) is seen sliding back at every reversal, and the mode flips between
        # the two directions every nanosecond without ever testing for sticking.
        self._slip_tol = max(self.settings.slip_tol_mps, 2.0 * _EVENT_THRESHOLD * speed)
        self._mode: _Mode | None = None
        self._h = spec.time_step
        self._pending: list[StepContacts] = []
        self._patterns: dict[tuple, np.ndarray] = {}
        # Candidate collisions of closed-form phases before the held contacts are left out;
        # kept across events while no body can have moved half their margin.
        self._near: _Candidates | None = None
        self._drives: tuple | None = None     # (drive parameters, _drive_model's answer)
        topo = sh.derived
        self._verts = np.ascontiguousarray(sh.vertices, dtype=float)
        self._normals = np.ascontiguousarray(sh.normals, dtype=float)
        self._next_vertex = topo.next_vertex
        self._prev_vertex = topo.prev_vertex
        self._piece_width = np.ascontiguousarray(topo.piece_width, dtype=float)
        self._vertex_body = topo.vertex_body
        self._vertex_piece = topo.vertex_piece
        self._active_vertex = np.flatnonzero(topo.vertex_active)
        self._piece_start = sh.piece_start
        self._piece_body = sh.piece_body
        self._materials = world.pair_materials
        none_i, none_f, none_v = np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2))
        self._no_contacts = (none_i, none_i, none_v, none_v, none_v, none_v, none_f,
                             np.zeros((0, 0)), none_i, none_f, none_f, none_i, 0)
        self._out = (np.zeros((world.n, 2)), np.zeros(world.n), np.zeros((world.n, 2)),
                     np.zeros(world.n))
        # One dynamic body: its closed-form phases run chained through its events (_ed_chain).
        self._chained = nd == 1 and self.settings.chained
        self._chain_world = chain.BodyArrays(
            np.asarray(world.dynamic, dtype=np.bool_), world.inv_mass, world.inv_inertia, radius,
            np.asarray(world.gravity, dtype=float))
        covered = topo.edge_internal | (np.diff(topo.cover_start) > 0)
        self._chain_geometry = (self._verts, self._normals,
                                self._next_vertex.astype(np.int64),
                                self._prev_vertex.astype(np.int64),
                                np.asarray(self._piece_start, dtype=np.int64),
                                np.asarray(topo.edge_length, dtype=float),
                                np.ascontiguousarray(covered, dtype=np.bool_))
        st = self.settings
        self._chain_tols = chain.ChainTolerances(
            event_threshold=_EVENT_THRESHOLD, slip_tol_mps=self._slip_tol, touch_m=st.touch_m,
            lcp_tol=st.lcp_tol, cascade_window_s=st.cascade_window_s,
            spin_limit=_SPIN_FRACTION * self._slip_tol, alpha_limit=_ALPHA_REL * g,
            force_tol=self._force_scale * 1e-12, acc_tol=1e-9 * g, near_m=1e3 * st.touch_m,
            rest_speed_mps=st.rest_speed_mps,
            friction_impulse=1.0 if spec.friction_impulse else 0.0)

    # ----------------------------------------------------------------- state <-> vector
    def _pack(self, s: State) -> np.ndarray:
        d = self._dyn
        return np.concatenate([s.position[d].ravel(), s.angle[d], s.velocity[d].ravel(),
                               s.omega[d]])

    def _unpack(self, t: float, y: np.ndarray, into: State) -> State:
        d, nd = self._dyn, len(self._dyn)
        into.t = t
        into.position[d] = y[:2 * nd].reshape(nd, 2)
        into.angle[d] = y[2 * nd:3 * nd]
        into.velocity[d] = y[3 * nd:5 * nd].reshape(nd, 2)
        into.omega[d] = y[5 * nd:]
        self.world.apply_prescribed_motion(into)
        return into

    def h_max(self) -> float:
        h = self.spec.time_step
        for i in self.world.driven:
            f = self.world.drives[i].frequency_hz
            if f > 0:
                h = min(h, 1.0 / (16.0 * f))
        return h

    # ------------------------------------------------------------------ smooth dynamics
    def _rhs(self, t: float, y: np.ndarray, scratch: State) -> tuple[np.ndarray, dict]:
        """Time derivative of y under the held mode, and the values the events watch."""
        w, mode = self.world, self._mode
        s = self._unpack(t, y, scratch)
        nd = len(self._dyn)
        acc = np.zeros((w.n, 2))
        acc[w.dynamic] = w.gravity
        kin_acc = w.prescribed_acceleration(t)
        acc[~w.dynamic] = kin_acc[~w.dynamic]
        alpha = np.zeros(w.n)
        aux: dict = {}
        if mode is not None and mode.features.n:
            cs = _with_geometry(w, mode.features, s)
            f_n, f_t, v_t = self._contact_forces(cs, s, acc, alpha)
            aux = {'cs': cs, 'f_n': f_n, 'f_t': f_t, 'v_t': v_t}
        dydt = np.concatenate([y[3 * nd:5 * nd], y[5 * nd:], acc[self._dyn].ravel(),
                               alpha[self._dyn]])
        return dydt, aux

    def _mode_system(self, cs: ContactSet):
        """The held mode's equations: bodies, J, M^-1 and the square system A x = -b[rows]
        whose solution x gives the stacked contact forces P x."""
        w, mode = self.world, self._mode
        c = cs.contacts
        k = c.n
        bodies = np.unique(np.concatenate([c.body_a, c.body_b]))
        bodies = bodies[w.dynamic[bodies]]
        J, minv, W = self._jacobian(cs, bodies)
        friction = np.where(mode.friction == STICK, BOX,
                            np.where(mode.friction == SLIDE, SLAVED, NONE))
        slave = -mode.sigma * cs.mu_dynamic
        A, P, rows, _, _, _ = kern.reduce_lcp(W, friction.astype(np.int64), np.zeros(k),
                                              np.zeros(k), slave)
        return bodies, J, minv, A, P, rows

    def _contact_forces(self, cs: ContactSet, s: State, acc: np.ndarray,
                        alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forces of the held mode; adds their effect to acc and alpha in place."""
        c = cs.contacts
        k = c.n
        a, b = c.body_a, c.body_b
        rel = (s.velocity[a] + s.omega[a][:, None] * perp(cs.r_a)) - \
            (s.velocity[b] + s.omega[b][:, None] * perp(cs.r_b))
        v_t = np.sum(rel * cs.tangent, 1)
        # Relative acceleration of the contact without contact forces (Baraff 1989): the
        # centripetal terms and the rotation of the edge's normal carry over from velocities.
        pa = acc[a] - (s.omega[a] ** 2)[:, None] * cs.r_a
        pb = acc[b] - (s.omega[b] ** 2)[:, None] * cs.r_b
        b_n = np.sum((pa - pb) * c.normal, 1) + 2 * s.omega[b] * np.sum(rel * cs.tangent, 1)
        b_t = np.sum((pa - pb) * cs.tangent, 1) - 2 * s.omega[b] * np.sum(rel * c.normal, 1)
        bodies, J, minv, A, P, rows = self._mode_system(cs)
        x = np.linalg.lstsq(A, -np.concatenate([b_n, b_t])[rows], rcond=1e-12)[0]
        f = P @ x
        dv = (minv * (J.T @ f)).reshape(-1, 3)
        acc[bodies] += dv[:, :2]
        alpha[bodies] += dv[:, 2]
        return f[:k], f[k:], v_t

    def _event_values(self, aux: dict) -> np.ndarray:
        """Event functions of the held mode (each must stay >= 0), scaled to be comparable."""
        mode = self._mode
        if not aux:
            return np.zeros(0)
        f_n, f_t, v_t = aux['f_n'], aux['f_t'], aux['v_t']
        cs = aux['cs']
        fs, vs = self._force_scale, self._speed
        out = [f_n / fs]
        stick = mode.friction == STICK
        if stick.any():
            g = mode.group[stick]
            sum_n = np.bincount(g, f_n[stick] * cs.mu_static[stick], minlength=g.max() + 1)
            sum_t = np.bincount(g, f_t[stick], minlength=g.max() + 1)
            present = np.bincount(g, minlength=g.max() + 1) > 0
            out.append(((sum_n - np.abs(sum_t)) / fs)[present])
        slide = mode.friction == SLIDE
        out.append(mode.sigma[slide] * v_t[slide] / vs)
        p = cs.contacts.edge_param
        out.append(p)
        out.append(1.0 - p)
        return np.concatenate(out)

    def _gap_values(self, s: State) -> np.ndarray:
        cand = self._mode.candidates
        out = np.empty(cand.n)
        if cand.n:
            kern.candidate_gaps(s.position, s.angle, *cand.arrays, self._verts, self._normals,
                                out)
        return out / _GAP_SCALE_M

    def _events_of(self, aux: dict, scratch: State) -> tuple[np.ndarray, np.ndarray]:
        """Event functions and stacked forces of a Python right-hand side evaluation."""
        g = np.concatenate([self._event_values(aux), self._gap_values(scratch)])
        return g, (np.concatenate([aux['f_n'], aux['f_t']]) if aux else np.zeros(0))

    def _evaluate(self, t: float, y: np.ndarray,
                  scratch: State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dy/dt, event functions, stacked contact forces)`` of the held mode at (t, y)."""
        mode = self._mode
        if mode.spec is not None:
            return kern.mode_rhs(t, y, self._spec(), mode.n_events + mode.candidates.n,
                                 *self._out)
        dydt, aux = self._rhs(t, y, scratch)
        return (dydt, *self._events_of(aux, scratch))

    # ------------------------------------------------------------------ integration
    def _dopri_step(self, t: float, y: np.ndarray, h: float, k0: np.ndarray, scratch: State):
        """Dormand–Prince step: ``(y_new, error norm, dy/dt, events, forces)``, the last three
        at the step's end (first same as last)."""
        mode = self._mode
        if mode.spec is not None:
            return kern.dopri_step(t, y, h, k0, self._spec(), mode.n_events + mode.candidates.n,
                                   self.rtol * self._scale, *self._out)
        ks = [k0]
        aux: dict = {}
        for i in range(1, 7):
            yi = y + h * sum(a * k for a, k in zip(_A[i], ks))
            k, aux = self._rhs(t + _C[i] * h, yi, scratch)
            ks.append(k)
        y_new = y + h * sum(b * k for b, k in zip(_B5[:6], ks[:6]))
        err_vec = h * sum(e * k for e, k in zip(_E, ks))
        err = float(np.sqrt(np.mean((err_vec / (self.rtol * self._scale)) ** 2))) \
            if len(y) else 0.0
        return (y_new, err, ks[6], *self._events_of(aux, scratch))

    def _spec(self) -> tuple:
        """The compiled right-hand side's arguments with the current candidates."""
        mode = self._mode
        return mode.spec[:12] + (mode.candidates.arrays,) + mode.spec[12:]

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Integrate ``state`` in place to ``t_end``; returns the contact impulses transmitted."""
        scratch = state.copy()
        events_here, last_event_t = 0, -math.inf
        give_way_s = _GIVE_WAY_S
        while state.t < t_end - 1e-15:
            if self._mode is None:
                self._settle(state)
            t_stop = t_end
            for i in self.world.driven:
                t_stop = min(t_stop, self.world.drives[i].next_change_after(state.t))
            if self._mode.phase is not None:
                hit = (self._follow_chain if self._chained else self._follow_closed_form)(
                    state, t_stop)
            else:
                hit = self._integrate_step(state, t_stop, scratch)
            if hit:
                self._mode = None
                self.stats.events += 1
                dense = state.t - last_event_t < self.settings.cascade_window_s
                events_here = events_here + 1 if dense else 0
                last_event_t = state.t
                if events_here > self.settings.max_events_at_one_time:
                    # A cascade: events at one instant, or a mode that chatters between two
                    # choices every few nanoseconds (a contact at its friction bound touched by
                    # a corner). Step past it, twice as far each time it persists.
                    self._give_way(state, scratch, give_way_s)
                    give_way_s = min(2.0 * give_way_s, self.settings.max_give_way_s)
                    events_here = 0
                continue
            give_way_s = _GIVE_WAY_S
            if state.t >= t_stop - 1e-15 and t_stop < t_end:
                self._mode = None   # the drive's acceleration has a kink here
        out, self._pending = self._pending, []
        return out

    def _integrate_step(self, state: State, t_stop: float, scratch: State) -> bool:
        """One Dormand–Prince step of the held mode (or up to its first event)."""
        h = min(self._h, self.h_max(), t_stop - state.t)
        t0 = state.t
        y0 = self._pack(state)
        self._refresh_candidates(state, h)
        k0, g0, f0 = self._evaluate(t0, y0, scratch)
        offset = kern.event_offsets(g0, self._mode.candidates.n, _EVENT_THRESHOLD)
        h = self._guarded_step(state, k0, h, g0, offset)
        while True:
            y1, err, k1, g1, f1 = self._dopri_step(t0, y0, h, k0, scratch)
            if err <= 1.0 or h < 1e-14:
                break
            h *= max(0.2, 0.9 * err ** -0.2)
        hit = (g1 + offset < 0.0) & (g0 + offset >= 0.0)
        factor = 5.0 if err == 0 else min(5.0, max(0.2, 0.9 * err ** -0.2))
        if hit.any():
            tau, y_ev, f_ev = self._locate(t0, y0, k0, h, g0 + offset, g1 + offset, f1, y1,
                                           hit, offset, scratch)
            self._unpack(t0 + tau, y_ev, state)
            self._accumulate_forces(f0, f_ev, tau, state)
            self._h = max(h, 1e-9)
            return True
        self._unpack(t0 + h, y1, state)
        self._accumulate_forces(f0, f1, h, state)
        self._h = min(h * factor, self.h_max())
        self.stats.steps += 1
        return False

    def _guarded_step(self, state: State, k0: np.ndarray, h: float, g0: np.ndarray,
                      offset: np.ndarray) -> float:
        """``h`` shortened so that no corner can pass through a piece within the step
        (:func:`feeder_sim.stepping.event_driven._kernels.guarded_step`)."""
        mode = self._mode
        cand = mode.candidates
        if not cand.n:
            return h
        if mode.drive_acc is None:
            mode.drive_acc = self._drive_accelerations()
        return kern.guarded_integrator_step(h, state.position, state.angle, state.velocity,
                                            state.omega, k0, self._dyn, mode.drive_acc,
                                            cand.arrays, g0, len(g0) - cand.n, offset,
                                            _GAP_SCALE_M)

    def _drive_accelerations(self) -> np.ndarray:
        """(n,) every body's largest drive acceleration A (2 pi f)^2 (m/s^2), 0 undriven."""
        w = self.world
        acc = np.zeros(w.n)
        for i in w.driven:
            drive = w.drives[i]
            acc[i] = drive.amplitude_m * (2.0 * math.pi * drive.frequency_hz) ** 2
        return acc

    def _locate(self, t0: float, y0: np.ndarray, k0: np.ndarray, h: float, g0: np.ndarray,
                g1: np.ndarray, f1: np.ndarray, y1: np.ndarray, hit: np.ndarray,
                offset: np.ndarray, scratch: State) -> tuple[float, np.ndarray, np.ndarray]:
        """Earliest time in (0, h] at which a hit event function reaches its level.

        ``g0``, ``g1`` are the event functions with ``offset`` added (see
        ``kern.event_offsets``): a function fires when that sum drops below zero.

        Illinois regula falsi on tau -> g(step(y0, tau)), bracketing the earliest crossing of
        any hit function: every trial is a full integrator step from the phase start, so the
        event state is as accurate as a normal step. Returns the state just past the crossing
        and the contact forces there.
        """
        lo, hi = 0.0, h
        g_lo = g0[hit]
        g_hi = g1[hit]
        best = (h, y1, f1)
        side = 0
        for _ in range(100):
            if hi - lo <= 1e-15 * max(1.0, abs(t0)) + 1e-16:
                break
            with np.errstate(divide='ignore', invalid='ignore'):
                frac = np.where(g_hi < 0, g_lo / (g_lo - g_hi), np.inf)
            f = float(np.min(frac))
            tau = lo + min(max(f, 1e-3), 1 - 1e-3) * (hi - lo) if np.isfinite(f) else \
                0.5 * (lo + hi)
            y_t, _, _, g_t_all, f_t = self._dopri_step(t0, y0, tau, k0, scratch)
            g_t = g_t_all[hit] + offset[hit]
            if (g_t < 0).any():
                hi, g_hi, best = tau, g_t, (tau, y_t, f_t)
                if side == -1:
                    g_lo = g_lo * 0.5
                side = -1
            else:
                lo, g_lo = tau, g_t
                if side == 1:
                    g_hi = np.where(g_hi < 0, g_hi * 0.5, g_hi)
                side = 1
        return best

    def _give_way(self, state: State, scratch: State, h: float) -> None:
        """Many events in a moment: let the mode run a step of ``h`` (s) without watching its
        events, to break the tie; a collision it leads into is resolved at the next settle."""
        self.stats.cascades += 1
        if self.stats.cascades <= 20:
            self.stats.messages.append(f'event cascade at t={state.t:.9f}s; stepped {h:.1e} s '
                                       'past it')
        self._settle(state)
        self._refresh_candidates(state, h)
        y = self._pack(state)
        k0 = self._evaluate(state.t, y, scratch)[0]
        y1 = self._dopri_step(state.t, y, h, k0, scratch)[0]
        self._unpack(state.t + h, y1, state)
        self._mode = None

    def _accumulate_forces(self, f0: np.ndarray, f1: np.ndarray, h: float,
                           state: State) -> None:
        """Impulses of the held contacts over a step (trapezoid rule), ending at ``state``."""
        if not f0.size or not f1.size:
            return
        k = len(f0) // 2
        p = 0.5 * h * (f0 + f1)
        self._pending.append(StepContacts(self._contacts_at(state.position, state.angle),
                                          p[:k], p[k:]))

    # ------------------------------------------------------------------ closed-form phases
    def _follow_closed_form(self, state: State, t_stop: float) -> bool:
        """Move the state along the held mode's exact motion to t_stop or its first event."""
        mode, ph = self._mode, self._mode.phase
        if self._near is None:
            self._near = self._find_candidates(state, self._closed_form_margin())
        if mode.candidates is None:
            mode.candidates = self._near.without(mode.features)
        pos, ang, vel, om = self._out
        dvel = np.zeros(len(ph.drives[2]))
        t0 = state.t
        for _ in range(64):
            cand = mode.candidates
            bodies = (ph.kind, ph.index, state.position, state.angle, state.velocity,
                      state.omega, ph.phi0, ph.phi1)
            reach = (cand.anchor_pos, cand.anchor_ang, self._radius, 0.5 * cand.margin)
            status, t_new, steps = kern.advance(
                t0, t_stop, self.h_max(), _EVENT_THRESHOLD, mode.n_events + cand.n, bodies,
                ph.drives, ph.contacts, cand.arrays, self._verts, self._normals,
                (self._force_scale, self._speed, _GAP_SCALE_M), reach, pos, ang, vel, om,
                dvel)
            self.stats.steps += steps
            if status == kern.REFRESH and t_new == t0:
                # Detected at another configuration, or a single step can outrun the margin.
                grow = 2.0 if cand.t == t0 else 1.0
                self._near = self._find_candidates(state, grow * cand.margin)
                mode.candidates = self._near.without(mode.features)
                continue
            break
        else:
            mode.phase = None    # no finite speed bound: integrate instead
            mode.spec = self._compiled_rhs(state)
            return False
        if ph.f0.size:
            impulse = ph.f0 * (t_new - t0) + ph.f1 @ dvel
            k = len(impulse) // 2
            self._pending.append(StepContacts(self._contacts_at(pos, ang), impulse[:k],
                                              impulse[k:]))
        d = self._dyn
        state.t = t_new
        state.position[d] = pos[d]
        state.angle[d] = ang[d]
        state.velocity[d] = vel[d]
        state.omega[d] = om[d]
        self.world.apply_prescribed_motion(state)
        if status == kern.REFRESH:
            self._near = self._find_candidates(state, cand.margin)
            mode.candidates = self._near.without(mode.features)
        return status == kern.EVENT

    def _follow_chain(self, state: State, t_stop: float) -> bool:
        """``_follow_closed_form`` for a single dynamic body, carried on through the events its
        own contacts resolve (:mod:`feeder_sim.stepping.event_driven._chain`)."""
        mode, ph = self._mode, self._mode.phase
        if self._near is None:
            self._near = self._find_candidates(state, self._closed_form_margin())
        near, f = self._near, mode.features
        t0 = state.t
        out = (state.position.copy(), state.angle.copy(), state.velocity.copy(),
               state.omega.copy())
        size = max(_CHAIN_ROWS, 64 * f.n)
        record = (np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.int64),
                  np.empty(size, np.int64), np.empty((size, 2)), np.empty((size, 2)),
                  np.empty(size), np.empty(size))
        held = (f.vertex_a.astype(np.int64), f.edge_b.astype(np.int64),
                f.piece_b.astype(np.int64), *mode.held[:6],
                *(np.ascontiguousarray(m, dtype=float) for m in mode.material))
        status, t_new, steps, events, rows, held, friction, sigma, phi0, phi1, f0, f1, sums = \
            chain.follow(
                t0, t_stop, self.h_max(), out,
                chain.PhaseModel(ph.kind, ph.index, self._drives[1][2].phi0, ph.drives),
                self._chain_world,
                held, (mode.friction.astype(np.int64), mode.sigma.astype(float), ph.phi0,
                       ph.phi1, ph.f0, ph.f1),
                (near.vertex.astype(np.int64), near.piece.astype(np.int64), near.arrays,
                 near.anchor_pos, near.anchor_ang, near.margin),
                self._chain_geometry, self._materials,
                (self._force_scale, self._speed, _GAP_SCALE_M), self._chain_tols, record)
        if status == kern.REFRESH and t_new == t0 and not events:
            return self._follow_closed_form(state, t_stop)   # it widens the candidates' margin
        self._count_chain(steps, events, sums)
        d = self._dyn
        state.t = t_new
        state.position[d] = out[0][d]
        state.angle[d] = out[1][d]
        state.velocity[d] = out[2][d]
        state.omega[d] = out[3][d]
        self.world.apply_prescribed_motion(state)
        if rows:
            self._pending.append(self._recorded(state, record, rows))
        if status == kern.EVENT:
            return True
        if events:
            point, normal, gap, param = kern.held_geometry(state.position, state.angle,
                                                           *held[3:9])
            features = Contacts(held[3], self._vertex_piece[held[0]], held[0], held[4],
                                held[2], held[1], point, normal, gap, param)
            material = held[9:]
            group = kern.contact_groups(features.body_a, features.body_b, normal)
            kernel_held, n_events = self._held(features, friction, sigma, group, material[0])
            mode = self._mode = _Mode(features, friction, sigma, group, material, kernel_held,
                                      n_events)
            mode.phase = _Phase(ph.kind, ph.index, phi0, phi1, ph.drives,
                                kernel_held[:6] + (f0, f1) + kernel_held[8:], f0, f1)
            mode.candidates = near.without(features)
        if status == kern.REFRESH:
            self._near = self._find_candidates(state, near.margin)
            mode.candidates = self._near.without(mode.features)
        return False

    def _count_chain(self, steps: int, events: int, sums: np.ndarray) -> None:
        """A chain of phases' statistics (``_ed_chain.follow``) into ``self.stats``."""
        st = self.stats
        st.steps += steps
        st.events += events
        st.lcp_solves += int(sums[chain.N_LCPS])
        st.trivial_solves += int(sums[chain.N_TRIVIAL])
        st.lcp_rows += int(sums[chain.LCP_ROWS])
        st.max_lcp_rows = max(st.max_lcp_rows, int(sums[chain.MAX_ROWS]))
        st.max_residual = max(st.max_residual, float(sums[chain.MAX_RESIDUAL]))
        st.max_penetration_m = max(st.max_penetration_m, float(sums[chain.MAX_PENETRATION]))
        st.pivots += int(sums[chain.PIVOTS])
        st.impacts += int(sums[chain.IMPACTS])
        st.energy_fixes += int(sums[chain.ENERGY_FIXES])

    def _recorded(self, state: State, record: tuple, rows: int) -> StepContacts:
        """The contact impulses a chain of phases recorded, as one report."""
        vertex, edge, a, b, point, normal, p_n, p_t = (x[:rows] for x in record)
        piece = self._vertex_piece
        mu_s, mu_d, e = self._materials
        c = Contacts(a, piece[vertex], vertex, b, piece[edge], edge, point, normal,
                     np.zeros(rows), np.full(rows, np.nan))
        return StepContacts(ContactSet(c, normal[:, ::-1] * (-1.0, 1.0),
                                       point - state.position[a], point - state.position[b],
                                       mu_s[a, b], mu_d[a, b], e[a, b]), p_n, p_t)

    def _contacts_at(self, pos: np.ndarray, ang: np.ndarray) -> ContactSet:
        """The held contacts at the configuration (pos, ang), built without re-detection."""
        mode = self._mode
        f = mode.features
        point, normal, gap, param = kern.held_geometry(pos, ang, *mode.held[:6])
        c = Contacts(f.body_a, f.piece_a, f.vertex_a, f.body_b, f.piece_b, f.edge_b, point,
                     normal, gap, param)
        return ContactSet(c, normal[:, ::-1] * (-1.0, 1.0), point - pos[f.body_a],
                          point - pos[f.body_b], *mode.material)

    def _closed_form_margin(self) -> float:
        amplitude = max((self.world.drives[i].amplitude_m for i in self.world.driven),
                        default=0.0)
        return 4.0 * self._length + 4.0 * amplitude

    def _drive_model(self, t: float) -> tuple | None:
        """Body kinds and drive arrays of closed-form phases, or None while a drive blends.

        Kept while the drives' amplitudes and frequencies stay, so that every phase follows
        one and the same sinusoid per drive (a command resets the stepper)."""
        w = self.world
        key = tuple((w.drives[i].amplitude_m, w.drives[i].frequency_hz) for i in w.driven)
        if any(w.drives[i].next_change_after(t) < math.inf for i in w.driven):
            return None   # a command blend: not a plain sinusoid
        if self._drives is not None and self._drives[0] == key:
            return self._drives[1]
        n = w.n
        kind = np.where(w.dynamic, MOVING, FIXED).astype(np.int64)
        index = np.full(n, -1, dtype=np.int64)
        u, base, amp, omega, phase = [], [], [], [], []
        for i in w.driven:
            drive = w.drives[i]
            d, v, _ = drive.motion(t)
            a, om = drive.amplitude_m, 2.0 * math.pi * drive.frequency_hz
            if a == 0.0 or om == 0.0:
                continue      # at rest
            # The drive is A sin(phase + omega (t - t_ref)) from its current phase on.
            sn, cs = d / a, v / (a * om)
            if abs(math.hypot(sn, cs) - 1.0) > 1e-9:
                return None
            kind[i], index[i] = DRIVEN, len(amp)
            u.append(drive.direction)
            base.append(w.base_position[i])
            amp.append(a)
            omega.append(om)
            phase.append(math.atan2(sn, cs))
        nd = len(amp)
        drives = (np.array(u, dtype=float).reshape(nd, 2),
                  np.array(base, dtype=float).reshape(nd, 2), np.array(amp, dtype=float),
                  np.array(omega, dtype=float), np.array(phase, dtype=float), float(t))
        phi0 = np.zeros((n, 2))
        phi0[w.dynamic] = w.gravity
        none_i, none_f = np.zeros(0, np.int64), np.zeros(0)
        none_v = np.zeros((0, 2))
        f1 = np.zeros((0, nd))
        free = _Phase(kind, index, phi0, np.zeros((n, 2, nd)), drives,
                      (none_i, none_i, none_v, none_v, none_v, none_v, none_f, f1, none_i,
                       none_f, none_f, none_i, 0), none_f, f1)
        self._drives = (key, (index, drives, free))
        return self._drives[1]

    def _closed_form(self, state: State, cs: ContactSet | None) -> _Phase | None:
        """The held mode's exact motion, if it has the closed form (module docstring).

        ``cs`` are the held contacts at ``state`` (None when there are none)."""
        w, mode = self.world, self._mode
        model = self._drive_model(state.t)
        if model is None:
            return None
        index, drives, free = model
        c = mode.features
        k = c.n
        if not k:
            return free
        a, b = c.body_a, c.body_b
        if not (w.dynamic[a].all() and not w.dynamic[b].any()):
            return None
        ok, bodies, dv, f = kern.closed_form_mode(
            c.normal, cs.r_a, cs.r_b, a, b, w.dynamic, w.inv_mass, w.inv_inertia,
            mode.friction, mode.sigma, cs.mu_dynamic, state.omega, self._radius,
            _SPIN_FRACTION * self._slip_tol, _ALPHA_REL * self._g, np.asarray(w.gravity,
                                                                          dtype=float),
            index, drives[0])
        if not ok:
            return None
        phi0, phi1 = free.phi0.copy(), free.phi1.copy()
        phi0[bodies] += dv[:, :2, 0]
        phi1[bodies] = dv[:, :2, 1:]
        f0, f1 = f[:, 0].copy(), np.ascontiguousarray(f[:, 1:])
        contacts = mode.held[:6] + (f0, f1) + mode.held[8:]
        return _Phase(free.kind, index, phi0, phi1, drives, contacts, f0, f1)

    def _compiled_rhs(self, state: State) -> tuple | None:
        """Arguments of the compiled right-hand side of the held mode, None while a drive
        blends (then the Python one, which asks the drives, integrates)."""
        model = self._drive_model(state.t)
        if model is None:
            return None
        w, mode = self.world, self._mode
        index, drives, free = model
        col = np.full(w.n, -1, dtype=np.int64)
        col[self._dyn] = 3 * np.arange(len(self._dyn))
        return (self._dyn.astype(np.int64), col, free.kind, index, state.position.copy(),
                state.angle.copy(), drives, np.asarray(w.gravity, dtype=float),
                w.inv_mass, w.inv_inertia, mode.held, mode.material[1], self._verts,
                self._normals, (self._force_scale, self._speed, _GAP_SCALE_M))

    def _held(self, features: Contacts, friction: np.ndarray, sigma: np.ndarray,
              group: np.ndarray, mu_s: np.ndarray) -> tuple[tuple, int]:
        """Kernel arrays of held contacts, and how many event functions they watch."""
        k = features.n
        if not k:
            return self._no_contacts, 0
        compact, n_groups = kern.sticking_groups(group, friction)
        n_slide = int(np.sum(friction == SLIDE))
        v, e = self._verts, features.edge_b
        none = np.zeros(0)
        held = (features.body_a.astype(np.int64), features.body_b.astype(np.int64),
                v[features.vertex_a], v[e], v[self._next_vertex[e]], self._normals[e], none,
                np.zeros((0, 0)), friction.astype(np.int64), sigma.astype(float), mu_s,
                compact, n_groups)
        return held, 3 * k + n_groups + n_slide

    # ------------------------------------------------------------------ candidates
    def _refresh_candidates(self, state: State, h: float) -> None:
        """Candidates of an integrator step: every pair within a heuristic reach of the step.

        The pairs detected earlier within a wider margin still contain them while no body has
        moved more than half the difference."""
        mode, near = self._mode, self._near
        reach = 2.0 * h * (self._speed * 4 + float(np.max(
            np.linalg.norm(state.velocity, axis=1), initial=0.0))) + 1e-6
        if near is not None:
            moved = float(np.max(np.linalg.norm(state.position - near.anchor_pos, axis=1) +
                                 np.abs(state.angle - near.anchor_ang) * self._radius))
            if 2.0 * moved + reach > near.margin:
                near = None
        if near is None:
            near = self._near = self._find_candidates(
                state, max(2.0 * reach, self._closed_form_margin()))
            mode.candidates = None
        if mode.candidates is None:
            mode.candidates = near.without(mode.features)

    def _find_candidates(self, state: State, margin: float) -> _Candidates:
        """Active corners against pieces of other bodies whose boxes are within ``margin``."""
        if len(self._piece_body) < 2:
            none = np.zeros(0, dtype=np.int64)
            return _Candidates(none, none, self._candidate_arrays(none, none),
                               state.position.copy(), state.angle.copy(), margin, state.t)
        vertex, piece = corner_piece_candidates(self.world, state, self._active_vertex,
                                                margin)[:2]
        return _Candidates(vertex, piece, self._candidate_arrays(vertex, piece),
                           state.position.copy(), state.angle.copy(), margin, state.t)

    def _candidate_arrays(self, vertex: np.ndarray, piece: np.ndarray) -> tuple:
        """Kernel arrays of candidate corners against pieces (see :mod:`._kernels`)."""
        v, ps = self._verts, self._piece_start
        wedge = np.stack([v[self._next_vertex[vertex]] - v[vertex],
                          v[self._prev_vertex[vertex]] - v[vertex]], axis=1).reshape(-1, 2, 2)
        return (self._vertex_body[vertex].astype(np.int64), v[vertex],
                self._piece_body[piece].astype(np.int64), ps[piece].astype(np.int64),
                ps[piece + 1].astype(np.int64), np.ascontiguousarray(wedge),
                self._piece_width[piece])

    # ------------------------------------------------------------------ events
    def _settle(self, state: State) -> None:
        """Resolve collisions at the current instant, then choose the next contact mode."""
        w, st = self.world, self.settings
        # Impacts change velocities only, so the contacts found once hold throughout.
        contacts = find_contacts(w.shapes, state.position, state.angle, w.dynamic,
                                 margin=st.touch_m)
        if not contacts.n:
            self._choose_mode(state, None, None, None)
            return
        self.stats.max_penetration_m = max(self.stats.max_penetration_m,
                                           float(np.max(-contacts.gap, initial=0.0)))
        cs = self._contact_set(state, contacts)
        v_n, v_t = _relative_velocity(cs, state)
        for _ in range(20):
            if not (v_n < -self._slip_tol * 10).any():
                break
            self._impact(cs, state, v_n, v_t)
            v_n, v_t = _relative_velocity(cs, state)
        self._choose_mode(state, cs, v_n, v_t)

    def _impact(self, cs: ContactSet, state: State, v_n: np.ndarray, v_t: np.ndarray) -> None:
        """Simultaneous frictional impulse LCP (Kawachi) over every touching contact."""
        st = self.settings
        colliding = v_n < -self._slip_tol * 10
        for bodies, idx in self._islands(cs):
            whole = len(idx) == cs.n
            if not (colliding if whole else colliding[idx]).any():
                continue
            sub = cs if whole else cs.subset(idx)
            J, minv, W = self._jacobian(sub, bodies)
            vn, vt, hit = (v_n, v_t, colliding) if whole else (v_n[idx], v_t[idx], colliding[idx])
            b_full = kern.impact_rhs(vn, vt, sub.restitution, st.rest_speed_mps)
            friction, mu_lo, mu_hi = friction_rows(sub, vt, hit, self.spec.friction_impulse,
                                                   self._slip_tol)
            if not self.spec.friction_impulse:
                friction[:] = NONE
            p, _, _ = self._solve_lcp('impact', W, b_full, friction, mu_lo, mu_hi)
            dv, gain, scale = kern.impulse_effect(J, minv, W, p, vn, vt)
            if gain > 1e-9 * max(1e-12, scale):
                # Never let a collision create kinetic energy: fall back to the frictionless
                # impulse, which cannot.
                self.stats.energy_fixes += 1
                p, _, _ = self._solve_lcp('impact', W, b_full, np.full(len(idx), NONE), mu_lo,
                                          mu_hi)
                dv = kern.impulse_effect(J, minv, W, p, vn, vt)[0]
            state.velocity[bodies] += dv[:, :2]
            state.omega[bodies] += dv[:, 2]
            k = len(idx)
            self._pending.append(StepContacts(sub, p[:k], p[k:]))
            self.stats.impacts += 1

    def _choose_mode(self, state: State, cs: ContactSet | None, v_n: np.ndarray | None,
                     v_t: np.ndarray | None) -> None:
        """Baraff's frictional force LCP over resting contacts decides the next phase.

        ``cs`` are the touching contacts (None if there are none), ``v_n, v_t`` their
        relative velocities."""
        if cs is None:
            self._set_mode(state, Contacts.empty(), np.zeros(0, int), np.zeros(0),
                           np.zeros(0, int), (np.zeros(0), np.zeros(0), np.zeros(0)), None)
            return
        resting = np.flatnonzero(np.abs(v_n) <= self._slip_tol * 10)
        if len(resting) < cs.n:
            cs = cs.subset(resting)
            v_n, v_t = v_n[resting], v_t[resting]
        k = cs.n
        keep = np.zeros(k, bool)
        friction = np.zeros(k, np.int64)
        sigma = np.sign(v_t)
        acc = self._free_acceleration(state.t)
        sliding = np.abs(v_t) > self._slip_tol
        for bodies, idx in self._islands(cs):
            whole = len(idx) == k
            sub = cs if whole else cs.subset(idx)
            vn, vt, sig = (v_n, v_t, sigma) if whole else (v_n[idx], v_t[idx], sigma[idx])
            ok, message, a_rel, f, fr = self._force_lcp(sub, state, acc, bodies, vn, vt,
                                                        sliding[idx], sig)
            if not ok:
                # No consistent contact forces (Painlevé): impulse without collision.
                self.stats.messages.append(
                    f'force LCP failed at t={state.t:.9f}s ({message}); impulse applied')
                self._impact_without_collision(sub, state, bodies)
                vn, vt = _relative_velocity(sub, state)
                ok, message, a_rel, f, fr = self._force_lcp(
                    sub, state, acc, bodies, vn, vt, np.zeros(len(idx), bool), sig)
            keep[idx], friction[idx], sigma[idx] = kern.mode_rows(
                f, a_rel, fr, sub.mu_static, sig, self._force_scale * 1e-12, 1e-9 * self._g)
        sel = np.flatnonzero(keep)
        active = cs if len(sel) == k else cs.subset(sel)
        self._set_mode(state, active.contacts, friction[sel], sigma[sel], _groups(active),
                       (active.mu_static, active.mu_dynamic, active.restitution), active)

    def _set_mode(self, state: State, features: Contacts, friction: np.ndarray,
                  sigma: np.ndarray, group: np.ndarray, material: tuple,
                  cs: ContactSet | None) -> None:
        """Hold a mode from ``state`` on: closed form if it has one, else integrated."""
        held, n_events = self._held(features, friction, sigma, group, material[0])
        self._mode = _Mode(features, friction, sigma, group, material, held, n_events)
        self._mode.phase = self._closed_form(state, cs)
        if self._mode.phase is None:
            self._mode.spec = self._compiled_rhs(state)

    def _force_lcp(self, cs: ContactSet, state: State, acc: np.ndarray, bodies: np.ndarray,
                   v_n: np.ndarray, v_t: np.ndarray, sliding: np.ndarray, sigma: np.ndarray):
        """Baraff's force LCP of one island: converged, message, relative accelerations,
        forces (both stacked normal then tangential) and the friction row treatment."""
        c = cs.contacts
        b_full, fr = kern.force_problem(c.normal, cs.r_a, cs.r_b, c.body_a, c.body_b,
                                        state.omega, acc, v_n, v_t, sliding, cs.mu_static,
                                        cs.mu_dynamic)
        if b_full[:c.n].min() >= 0.0:
            # Every contact would separate by itself: no force (LCP answer x = 0).
            self.stats.record_trivial(1)
            return True, '', b_full, np.zeros(2 * c.n), fr
        _, _, W = self._jacobian(cs, bodies)
        f, ok, message = self._solve_lcp('force', W, b_full, fr, cs.mu_static, cs.mu_static,
                                         -sigma * cs.mu_dynamic)
        return ok, message, W @ f + b_full, f, fr

    def _free_acceleration(self, t: float) -> np.ndarray:
        """(n, 2) accelerations without contact forces: gravity, or the prescribed motion."""
        w = self.world
        acc = w.prescribed_acceleration(t)
        acc[w.dynamic] = w.gravity
        return acc

    def _impact_without_collision(self, cs: ContactSet, state: State,
                                  bodies: np.ndarray) -> None:
        v_n, v_t = _relative_velocity(cs, state)
        J, minv, W = self._jacobian(cs, bodies)
        friction, mu_lo, mu_hi = friction_rows(cs, v_t, np.zeros(cs.n, bool), True,
                                               self._slip_tol)
        p, _, _ = self._solve_lcp('impact', W,
                                  np.concatenate([np.minimum(v_n, 0.0), v_t]), friction, mu_lo,
                                  mu_hi)
        dv = (minv * (J.T @ p)).reshape(-1, 3)
        state.velocity[bodies] += dv[:, :2]
        state.omega[bodies] += dv[:, 2]
        self.stats.impacts += 1
        self._pending.append(StepContacts(cs, p[:cs.n], p[cs.n:]))

    # ------------------------------------------------------------------ contact systems
    def _contact_set(self, state: State, contacts: Contacts) -> ContactSet:
        """:func:`contact_set`, with the body pairs' materials looked up."""
        a, b = contacts.body_a, contacts.body_b
        mu_s, mu_d, e = self._materials
        return ContactSet(contacts, contacts.normal[:, ::-1] * (-1.0, 1.0),
                          contacts.point - state.position[a], contacts.point - state.position[b],
                          mu_s[a, b], mu_d[a, b], e[a, b])

    def _islands(self, cs: ContactSet) -> list[tuple[np.ndarray, np.ndarray]]:
        if len(self._dyn) == 1:
            return [(self._dyn, np.arange(cs.n))] if cs.n else []
        return islands(self.world, cs)

    def _jacobian(self, cs: ContactSet,
                  bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contact Jacobian over the (ascending) bodies' (vx, vy, omega) columns, the diagonal
        of M^-1 (as :func:`island_jacobian` gives them) and the Delassus matrix."""
        w = self.world
        c = cs.contacts
        ok, J, minv, W = kern.contact_jacobian(c.normal, cs.r_a, cs.r_b, c.body_a, c.body_b,
                                               w.dynamic, w.inv_mass, w.inv_inertia, bodies)
        if not ok:
            jac = island_jacobian(w, cs, bodies)
            J, minv = jac.J, jac.inv_mass
            W = (J * minv) @ J.T
        return J, minv, W

    def _solve_lcp(self, kind: str, W: np.ndarray, b_full: np.ndarray, friction: np.ndarray,
                   mu_lo: np.ndarray, mu_hi: np.ndarray,
                   slave: np.ndarray | None = None) -> tuple[np.ndarray, bool, str]:
        """A contact LCP posed as for :func:`feeder_sim.contact.dynamics.assemble`: stacked
        solution (2k,), converged, message.

        The rows' final states (active set) of the last pivoting solve of each problem shape
        are tried first and kept when the LCP residual accepts them: events of a periodic
        motion pose nearly the same problem every cycle, so the pivoting solver then runs only
        when the contact situation changes.
        """
        k = len(friction)
        if k == 0 or b_full[:k].min() >= 0.0:
            self.stats.record_trivial(1)
            return np.zeros(2 * k), True, ''
        friction = friction.astype(np.int64)
        slave = np.zeros(k) if slave is None else slave
        tol = self.settings.lcp_tol
        key = (kind, friction.tobytes(), (mu_lo > 0).tobytes(), (mu_hi > 0).tobytes())
        pattern = self._patterns.get(key)
        if pattern is not None:
            f, x, w, res = kern.lcp_known_pattern(W, b_full, friction, mu_lo, mu_hi, slave,
                                                  pattern)
            if res <= tol:
                self.stats.record(lcp.LCPResult(x, w, 'active set', 0, 0, res, True, ''))
                return f, True, ''
        # The compiled Dantzig takes lcp.solve's pivots ~100x faster; an answer that misses
        # the tolerance goes to lcp.solve and its fallback ladder, as in time_stepping.
        f, x, w, res, pivots, codes, (A, P, b, normal_of, lo, hi) = kern.lcp_dantzig(
            W, b_full, friction, mu_lo, mu_hi, slave)
        if res <= tol:
            result = lcp.LCPResult(x, w, 'dantzig', pivots, 0, res, True, '')
        else:
            self.stats.fallbacks += 1
            if len(self.stats.messages) < 20:
                self.stats.messages.append(lcp.dantzig_message(res, codes))
            result = lcp.solve(lcp.FrictionalLCP(A, b, normal_of, lo, hi), tol=tol)
            f = P @ result.x
        self.stats.record(result)
        if result.converged:
            self._patterns[key] = kern.lcp_pattern(result.x, normal_of, lo, hi)
        return f, result.converged, result.message

    def reset(self) -> None:
        self._mode = None
        self._near = None
        self._drives = None
        self._h = self.spec.time_step
        self._pending = []
