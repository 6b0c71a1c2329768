"""``event_driven``: the paper's scheme (accuracy method).

Between events the bodies move smoothly under gravity, prescribed track motion and contact
forces. The contact *mode* — which contacts press (normal force, zero normal acceleration),
which stick (zero tangential acceleration) and which slide (friction ``-sigma mu_d f_N``) — is
chosen by Baraff's frictional force LCP at the start of a phase and then held, so the motion is
smooth and a Dormand–Prince 5(4) integrator with error control follows it accurately. Each
phase watches event functions; the first one to cross zero ends the phase at the located time:

======================  ==========================================  ========================
event                   function that must stay >= 0                 what happens
======================  ==========================================  ========================
collision               gap of a nearby vertex-edge pair             impulse LCP (Kawachi)
lift-off / tipping      normal force of a pressing contact           new force LCP
stick -> slip           mu_s sum f_N - |sum f_T| of a sticking group new force LCP
slip -> stick/reverse   sigma v_T of a sliding contact              new force LCP
sliding off an edge     edge parameter in [0, 1]                    new contact detection
======================  ==========================================  ========================

Parallel contacts between the same two bodies (an edge lying on an edge) share their loads in a
way rigid-body mechanics leaves open, so friction is tested on the group's totals. When the
force LCP has no solution (Painlevé configurations) the contact takes an impulse without
collision, as Baraff and the reference recommend.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from feeder_sim import lcp
from feeder_sim.collision import Contacts, evaluate_gaps, find_contacts
from feeder_sim.dynamics import (
    assemble,
    BOX,
    contact_set,
    ContactSet,
    island_jacobian,
    islands,
    NONE,
    relative_velocity,
    SLAVED,
    SolverStats,
)
from feeder_sim.scene import SolverSpec
from feeder_sim.time_stepping import friction_rows, StepContacts
from feeder_sim.world import perp, rot, State, World

STICK, SLIDE = 1, 2
# Event functions are scaled to O(1); one fires when it drops below -_EVENT_THRESHOLD, so a
# function that starts a phase at zero (a contact that just separated) does not fire on noise.
_EVENT_THRESHOLD = 1e-9
_GAP_SCALE_M = 1e-3   # gaps fire at -1e-12 m

# Dormand–Prince 5(4) tableau (Dormand & Prince 1980); the 5th-order row is also the FSAL row.
_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_A = [
    [],
    [1 / 5],
    [3 / 40, 9 / 40],
    [44 / 45, -56 / 15, 32 / 9],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
]
_B5 = np.array(_A[6] + [0.0])
_B4 = np.array([5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100,
                1 / 40])
_E = _B5 - _B4


@dataclass
class EventSettings:
    touch_m: float = 1e-9        # a vertex this close to an edge is in contact
    slip_tol_mps: float = 1e-9   # |v_T| below this is sticking
    rest_speed_mps: float = 1e-4  # impacts slower than this are plastic (no Zeno bouncing)
    lcp_tol: float = 1e-9
    max_events_at_one_time: int = 50


@dataclass
class _Mode:
    """The contact mode held during one smooth phase."""

    features: Contacts        # active contacts (geometry at the phase start)
    friction: np.ndarray      # (k,) NONE / STICK / SLIDE
    sigma: np.ndarray         # (k,) slip direction of sliding contacts
    group: np.ndarray         # (k,) parallel-contact group id
    candidates: Contacts      # nearby inactive vertex-edge pairs (collision events)


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


def _select(c: Contacts, idx: np.ndarray) -> Contacts:
    return Contacts(*(getattr(c, f)[idx] for f in (
        'body_a', 'piece_a', 'vertex_a', 'body_b', 'piece_b', 'edge_b', 'point', 'normal',
        'gap', 'edge_param')))


def _groups(cs: ContactSet) -> np.ndarray:
    """Group ids of contacts between the same two bodies along one line (parallel normals)."""
    c = cs.contacts
    group = np.full(c.n, -1)
    nxt = 0
    for i in range(c.n):
        if group[i] >= 0:
            continue
        same = (np.minimum(c.body_a, c.body_b) == min(c.body_a[i], c.body_b[i])) & \
            (np.maximum(c.body_a, c.body_b) == max(c.body_a[i], c.body_b[i])) & \
            (np.abs(c.normal @ perp(c.normal[i])) < 1e-9) & (group < 0)
        group[same] = nxt
        nxt += 1
    return group


class EventDriven:
    """Advances a state to any requested time, stopping at every contact event."""

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: EventSettings | None = None) -> None:
        self.world = world
        self.spec = spec
        self.stats = stats
        self.settings = settings or EventSettings()
        self.rtol = spec.tolerance
        dyn = np.flatnonzero(world.dynamic)
        self._dyn = dyn
        radius = np.zeros(world.n)
        np.maximum.at(radius, world.shapes.piece_body, world.shapes.radius)
        length = float(np.max(radius[dyn], initial=1e-2))
        g = float(np.linalg.norm(world.gravity)) or 9.81
        speed = math.sqrt(g * length)
        for i in world.driven:
            d = world.drives[i]
            speed = max(speed, 2 * math.pi * d.frequency_hz * d.amplitude_m)
        nd = len(dyn)
        self._scale = np.concatenate([np.full(2 * nd, length), np.ones(nd),
                                      np.full(2 * nd, speed), np.full(nd, speed / length)])
        self._force_scale = float(np.max(world.mass[dyn] * g, initial=1.0))
        self._speed = speed
        self._mode: _Mode | None = None
        self._h = spec.time_step
        self._pending: list[StepContacts] = []

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

    def _contact_forces(self, cs: ContactSet, s: State, acc: np.ndarray,
                        alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forces of the held mode; adds their effect to acc and alpha in place."""
        w, mode = self.world, self._mode
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
        bodies = np.unique(np.concatenate([a, b]))
        bodies = bodies[w.dynamic[bodies]]
        jac = island_jacobian(w, cs, bodies)
        W = jac.delassus()
        friction = np.where(mode.friction == STICK, BOX,
                            np.where(mode.friction == SLIDE, SLAVED, NONE))
        slave = -mode.sigma * cs.mu_dynamic
        asm = assemble(W, np.concatenate([b_n, b_t]), friction, np.zeros(k), np.zeros(k),
                       slave)
        x = np.linalg.lstsq(asm.problem.A, -asm.problem.b, rcond=1e-12)[0]
        f = asm.full(x)
        dv = jac.velocity_change(f)
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
        if not cand.n:
            return np.zeros(0)
        gap, param = evaluate_gaps(self.world.shapes, cand, s.position, s.angle)
        # Only a vertex over its edge can hit it; elsewhere the line's extension is irrelevant.
        on_edge = (param > -1e-9) & (param < 1 + 1e-9)
        return np.where(on_edge, gap, np.maximum(gap, 0.0)) / _GAP_SCALE_M

    def _all_events(self, t: float, y: np.ndarray, scratch: State) -> tuple[np.ndarray, dict]:
        _, aux = self._rhs(t, y, scratch)
        return np.concatenate([self._event_values(aux), self._gap_values(scratch)]), aux

    # ------------------------------------------------------------------ integration
    def _dopri_step(self, t: float, y: np.ndarray, h: float, k0: np.ndarray,
                    scratch: State) -> tuple[np.ndarray, float, np.ndarray]:
        ks = [k0]
        for i in range(1, 7):
            yi = y + h * sum(a * k for a, k in zip(_A[i], ks))
            ks.append(self._rhs(t + _C[i] * h, yi, scratch)[0])
        y_new = y + h * sum(b * k for b, k in zip(_B5[:6], ks[:6]))
        err_vec = h * sum(e * k for e, k in zip(_E, ks))
        err = float(np.sqrt(np.mean((err_vec / (self.rtol * self._scale)) ** 2))) \
            if len(y) else 0.0
        return y_new, err, ks[6]

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Integrate ``state`` in place to ``t_end``; returns the contact impulses transmitted."""
        scratch = state.copy()
        events_here, last_event_t = 0, -math.inf
        while state.t < t_end - 1e-15:
            if self._mode is None:
                self._settle(state)
            t_stop = t_end
            for i in self.world.driven:
                t_stop = min(t_stop, self.world.drives[i].next_change_after(state.t))
            h = min(self._h, self.h_max(), t_stop - state.t)
            t0 = state.t
            y0 = self._pack(state)
            self._refresh_candidates(state, h)
            k0, aux0 = self._rhs(t0, y0, scratch)
            g0 = np.concatenate([self._event_values(aux0), self._gap_values(scratch)])
            while True:
                y1, err, k1 = self._dopri_step(t0, y0, h, k0, scratch)
                if err <= 1.0 or h < 1e-14:
                    break
                h *= max(0.2, 0.9 * err ** -0.2)
            g1, aux1 = self._all_events(t0 + h, y1, scratch)
            hit = (g1 < -_EVENT_THRESHOLD) & (g0 >= -_EVENT_THRESHOLD)
            factor = 5.0 if err == 0 else min(5.0, max(0.2, 0.9 * err ** -0.2))
            if hit.any():
                tau, y_ev, aux_ev = self._locate(t0, y0, k0, h, g0, g1, aux1, y1, hit, scratch)
                self._accumulate_forces(aux0, aux_ev, tau)
                self._unpack(t0 + tau, y_ev, state)
                self._mode = None
                self.stats.events += 1
                events_here = events_here + 1 if state.t - last_event_t < 1e-12 else 0
                last_event_t = state.t
                if events_here > self.settings.max_events_at_one_time:
                    self._give_way(state, scratch)
                    events_here = 0
                self._h = max(h, 1e-9)
                continue
            self._accumulate_forces(aux0, aux1, h)
            self._unpack(t0 + h, y1, state)
            self._h = min(h * factor, self.h_max())
            self.stats.steps += 1
            if state.t >= t_stop - 1e-15 and t_stop < t_end:
                self._mode = None   # the drive's acceleration has a kink here
        out, self._pending = self._pending, []
        return out

    def _locate(self, t0: float, y0: np.ndarray, k0: np.ndarray, h: float, g0: np.ndarray,
                g1: np.ndarray, aux1: dict, y1: np.ndarray, hit: np.ndarray,
                scratch: State) -> tuple[float, np.ndarray, dict]:
        """Earliest time in (0, h] at which a hit event function reaches its threshold.

        Illinois regula falsi on tau -> g(step(y0, tau)), bracketing the earliest crossing of
        any hit function: every trial is a full integrator step from the phase start, so the
        event state is as accurate as a normal step. Returns the state just past the crossing.
        """
        lo, hi = 0.0, h
        g_lo = g0[hit] + _EVENT_THRESHOLD
        g_hi = g1[hit] + _EVENT_THRESHOLD
        best = (h, y1, aux1)
        side = 0
        for _ in range(100):
            if hi - lo <= 1e-15 * max(1.0, abs(t0)) + 1e-16:
                break
            with np.errstate(divide='ignore', invalid='ignore'):
                frac = np.where(g_hi < 0, g_lo / (g_lo - g_hi), np.inf)
            f = float(np.min(frac))
            tau = lo + min(max(f, 1e-3), 1 - 1e-3) * (hi - lo) if np.isfinite(f) else \
                0.5 * (lo + hi)
            y_t, _, _ = self._dopri_step(t0, y0, tau, k0, scratch)
            g_t_all, aux_t = self._all_events(t0 + tau, y_t, scratch)
            g_t = g_t_all[hit] + _EVENT_THRESHOLD
            if (g_t < 0).any():
                hi, g_hi, best = tau, g_t, (tau, y_t, aux_t)
                if side == -1:
                    g_lo = g_lo * 0.5
                side = -1
            else:
                lo, g_lo = tau, g_t
                if side == 1:
                    g_hi = np.where(g_hi < 0, g_hi * 0.5, g_hi)
                side = 1
        return best

    def _give_way(self, state: State, scratch: State) -> None:
        """Many events at one instant: let the mode run a tiny step to break the tie."""
        self.stats.messages.append(f'event cascade at t={state.t:.9f}s; stepped past it')
        self._settle(state)
        y = self._pack(state)
        k0, _ = self._rhs(state.t, y, scratch)
        y1, _, _ = self._dopri_step(state.t, y, 1e-9, k0, scratch)
        self._unpack(state.t + 1e-9, y1, state)
        self._mode = None

    def _accumulate_forces(self, aux0: dict, aux1: dict, h: float) -> None:
        if not aux0 or not aux1:
            return
        p_n = 0.5 * h * (aux0['f_n'] + aux1['f_n'])
        p_t = 0.5 * h * (aux0['f_t'] + aux1['f_t'])
        self._pending.append(StepContacts(aux1['cs'], p_n, p_t))

    def _refresh_candidates(self, state: State, h: float) -> None:
        w = self.world
        reach = 2.0 * h * (self._speed * 4 + float(np.max(
            np.linalg.norm(state.velocity, axis=1), initial=0.0))) + 1e-6
        found = find_contacts(w.shapes, state.position, state.angle, w.dynamic, margin=reach)
        active = self._mode.features
        key_active = set(zip(active.vertex_a.tolist(), active.edge_b.tolist()))
        keep = np.array([(va, eb) not in key_active for va, eb in
                         zip(found.vertex_a.tolist(), found.edge_b.tolist())], dtype=bool)
        self._mode.candidates = _select(found, np.flatnonzero(keep)) if found.n else found

    # ------------------------------------------------------------------ events
    def _settle(self, state: State) -> None:
        """Resolve collisions at the current instant, then choose the next contact mode."""
        w, st = self.world, self.settings
        for _ in range(20):
            contacts = find_contacts(w.shapes, state.position, state.angle, w.dynamic,
                                     margin=st.touch_m)
            if not contacts.n:
                break
            self.stats.max_penetration_m = max(self.stats.max_penetration_m,
                                               float(np.max(-contacts.gap, initial=0.0)))
            cs = contact_set(w, state, contacts)
            v_n, v_t = relative_velocity(cs, state)
            if not (v_n < -st.slip_tol_mps * 10).any():
                break
            self._impact(cs, state, v_n, v_t)
        self._choose_mode(state)

    def _impact(self, cs: ContactSet, state: State, v_n: np.ndarray, v_t: np.ndarray) -> None:
        """Simultaneous frictional impulse LCP (Kawachi) over every touching contact."""
        w, st = self.world, self.settings
        colliding = v_n < -st.slip_tol_mps * 10
        e = np.where(-v_n > st.rest_speed_mps, cs.restitution, 0.0)
        for bodies, idx in islands(w, cs):
            if not colliding[idx].any():
                continue
            sub = cs.subset(idx)
            jac = island_jacobian(w, sub, bodies)
            W = jac.delassus()
            vn, vt = v_n[idx], v_t[idx]
            b_full = np.concatenate([(1.0 + e[idx]) * np.minimum(vn, 0.0) +
                                     np.maximum(vn, 0.0), vt])
            friction, mu_lo, mu_hi = friction_rows(sub, vt, colliding[idx],
                                                   self.spec.friction_impulse,
                                                   st.slip_tol_mps)
            if not self.spec.friction_impulse:
                friction[:] = NONE
            asm = assemble(W, b_full, friction, mu_lo, mu_hi)
            result = lcp.solve(asm.problem, tol=st.lcp_tol)
            self.stats.record(result)
            p = asm.full(result.x)
            v_pre = np.concatenate([vn, vt])
            gain = float(p @ v_pre + 0.5 * p @ (W @ p))
            if gain > 1e-9 * max(1e-12, float(np.abs(p) @ np.abs(v_pre))):
                # Never let a collision create kinetic energy: fall back to the frictionless
                # impulse, which cannot.
                self.stats.energy_fixes += 1
                asm = assemble(W, b_full, np.full(len(idx), NONE), mu_lo, mu_hi)
                result = lcp.solve(asm.problem, tol=st.lcp_tol)
                self.stats.record(result)
                p = asm.full(result.x)
            dv = jac.velocity_change(p)
            state.velocity[bodies] += dv[:, :2]
            state.omega[bodies] += dv[:, 2]
            k = len(idx)
            self._pending.append(StepContacts(sub, p[:k], p[k:]))
            self.stats.impacts += 1

    def _choose_mode(self, state: State) -> None:
        """Baraff's frictional force LCP over resting contacts decides the next phase."""
        w, st = self.world, self.settings
        contacts = find_contacts(w.shapes, state.position, state.angle, w.dynamic,
                                 margin=st.touch_m)
        empty = Contacts.empty()
        if not contacts.n:
            self._mode = _Mode(empty, np.zeros(0, int), np.zeros(0), np.zeros(0, int), empty)
            return
        cs = contact_set(w, state, contacts)
        v_n, v_t = relative_velocity(cs, state)
        resting = np.flatnonzero(np.abs(v_n) <= st.slip_tol_mps * 10)
        cs = cs.subset(resting)
        v_t = v_t[resting]
        k = cs.n
        keep = np.zeros(k, bool)
        friction = np.zeros(k, int)
        sigma = np.sign(v_t)
        acc = np.zeros((w.n, 2))
        acc[w.dynamic] = w.gravity
        acc[~w.dynamic] = w.prescribed_acceleration(state.t)[~w.dynamic]
        sliding = np.abs(v_t) > st.slip_tol_mps
        for bodies, idx in islands(w, cs):
            sub = cs.subset(idx)
            result, a_n, a_t, f_n, f_t, fr = self._force_lcp(sub, state, acc, bodies,
                                                             sliding[idx], sigma[idx])
            if not result.converged:
                # No consistent contact forces (Painlevé): impulse without collision.
                self.stats.messages.append(
                    f'force LCP failed at t={state.t:.9f}s ({result.message}); impulse applied')
                self._impact_without_collision(sub, state, bodies)
                result, a_n, a_t, f_n, f_t, fr = self._force_lcp(
                    sub, state, acc, bodies, np.zeros(len(idx), bool), sigma[idx])
            fscale = self._force_scale * 1e-12
            active = (f_n > fscale) | (a_n <= 1e-9 * np.linalg.norm(w.gravity))
            keep[idx] = active
            mu_s = sub.mu_static
            at_bound = np.abs(f_t) >= mu_s * f_n * (1 - 1e-9) - fscale
            starts = (fr == BOX) & at_bound & (np.abs(a_t) > 1e-12)
            friction[idx] = np.where(fr == SLAVED, SLIDE,
                                     np.where(starts, SLIDE, np.where(fr == BOX, STICK, NONE)))
            sigma[idx] = np.where(starts, np.sign(a_t), sigma[idx])
        sel = np.flatnonzero(keep)
        active = cs.subset(sel)
        self._mode = _Mode(active.contacts, friction[sel], sigma[sel], _groups(active), empty)

    def _force_lcp(self, cs: ContactSet, state: State, acc: np.ndarray, bodies: np.ndarray,
                   sliding: np.ndarray, sigma: np.ndarray):
        w = self.world
        c = cs.contacts
        a, b = c.body_a, c.body_b
        rel = (state.velocity[a] + state.omega[a][:, None] * perp(cs.r_a)) - \
            (state.velocity[b] + state.omega[b][:, None] * perp(cs.r_b))
        pa = acc[a] - (state.omega[a] ** 2)[:, None] * cs.r_a
        pb = acc[b] - (state.omega[b] ** 2)[:, None] * cs.r_b
        b_n = np.sum((pa - pb) * c.normal, 1) + 2 * state.omega[b] * np.sum(rel * cs.tangent, 1)
        b_t = np.sum((pa - pb) * cs.tangent, 1) - 2 * state.omega[b] * np.sum(rel * c.normal, 1)
        jac = island_jacobian(w, cs, bodies)
        W = jac.delassus()
        k = c.n
        mu = np.where(sliding, cs.mu_dynamic, cs.mu_static)
        fr = np.where(mu > 0, np.where(sliding, SLAVED, BOX), NONE)
        asm = assemble(W, np.concatenate([b_n, b_t]), fr, cs.mu_static, cs.mu_static,
                       -sigma * cs.mu_dynamic)
        result = lcp.solve(asm.problem, tol=self.settings.lcp_tol)
        self.stats.record(result)
        f = asm.full(result.x)
        a_rel = W @ f + np.concatenate([b_n, b_t])
        return result, a_rel[:k], a_rel[k:], f[:k], f[k:], fr

    def _impact_without_collision(self, cs: ContactSet, state: State,
                                  bodies: np.ndarray) -> None:
        v_n, v_t = relative_velocity(cs, state)
        jac = island_jacobian(self.world, cs, bodies)
        W = jac.delassus()
        friction, mu_lo, mu_hi = friction_rows(cs, v_t, np.zeros(cs.n, bool), True,
                                               self.settings.slip_tol_mps)
        asm = assemble(W, np.concatenate([np.minimum(v_n, 0.0), v_t]), friction, mu_lo, mu_hi)
        result = lcp.solve(asm.problem, tol=self.settings.lcp_tol)
        self.stats.record(result)
        p = asm.full(result.x)
        dv = jac.velocity_change(p)
        state.velocity[bodies] += dv[:, :2]
        state.omega[bodies] += dv[:, 2]
        self.stats.impacts += 1
        self._pending.append(StepContacts(cs, p[:cs.n], p[cs.n:]))

    def reset(self) -> None:
        self._mode = None
        self._h = self.spec.time_step
        self._pending = []
