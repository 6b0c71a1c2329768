"""Contact modes of the event-driven method: what happens at an event.

Collisions at the current instant take Kawachi's simultaneous frictional impulse LCP
(:meth:`ContactModes.impact`); then Baraff's frictional force LCP over the resting contacts
chooses which contacts press, stick and slide (:meth:`ContactModes.choose`), or, where it has no
solution (Painlevé), an impulse without collision is applied first. :func:`held_arrays` gives
the chosen mode's contacts as the kernels take them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feeder_sim.contact import lcp
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
    SolverStats,
)
from feeder_sim.contact.routh import routh_collision, STRONGE
from feeder_sim.model.world import rot, State, World
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.event_driven.bookkeeping import (
    ContactMaterial,
    EventSettings,
    FORCE_TOL_REL,
    Setup,
)
from feeder_sim.stepping.protocol import StepContacts

STICK, SLIDE = kern.STICK, kern.SLIDE
assert (BOX, SLAVED) == (kern.BOX_ROW, kern.SLAVED_ROW)


@dataclass
class ModeChoice:
    """The contact mode an event leads to, before it is held."""

    features: Contacts        # active contacts
    friction: np.ndarray      # (k,) NONE / STICK / SLIDE
    sigma: np.ndarray         # (k,) slip direction of sliding contacts
    group: np.ndarray         # (k,) parallel-contact group id
    material: ContactMaterial
    cs: ContactSet | None     # the active contacts' system (None when there are none)
    force_n: np.ndarray       # (k,) the force LCP's normal forces of the active contacts, N

    def without(self, leave: np.ndarray) -> ModeChoice:
        """The same choice without the contacts where ``leave`` (k,) is True."""
        stay = np.flatnonzero(~leave)
        cs = self.cs.subset(stay)
        return ModeChoice(cs.contacts, self.friction[stay], self.sigma[stay], groups(cs),
                          ContactMaterial(cs.mu_static, cs.mu_dynamic, cs.restitution), cs,
                          self.force_n[stay])


def with_geometry(world: World, features: Contacts, state: State) -> ContactSet:
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


def relative_velocity(cs: ContactSet, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Normal and tangential velocity (m/s) of every contact's vertex relative to the edge's
    material point under it."""
    c = cs.contacts
    return kern.relative_velocity(c.normal, cs.r_a, cs.r_b, c.body_a, c.body_b, state.velocity,
                                  state.omega)


def groups(cs: ContactSet) -> np.ndarray:
    """Group ids of contacts between the same two bodies along one line (parallel normals)."""
    c = cs.contacts
    return kern.contact_groups(c.body_a, c.body_b, c.normal)


def jacobian(world: World, cs: ContactSet,
             bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact Jacobian over the (ascending) bodies' (vx, vy, omega) columns, the diagonal
    of M^-1 (as :func:`island_jacobian` gives them) and the Delassus matrix."""
    c = cs.contacts
    ok, J, minv, W = kern.contact_jacobian(c.normal, cs.r_a, cs.r_b, c.body_a, c.body_b,
                                           world.dynamic, world.inv_mass, world.inv_inertia,
                                           bodies)
    if not ok:
        jac = island_jacobian(world, cs, bodies)
        J, minv = jac.J, jac.inv_mass
        W = (J * minv) @ J.T
    return J, minv, W


def held_arrays(setup: Setup, features: Contacts, friction: np.ndarray, sigma: np.ndarray,
                group: np.ndarray, mu_s: np.ndarray) -> tuple[kern.HeldContacts, int]:
    """Kernel arrays of held contacts, and how many event functions they watch."""
    k = features.n
    if not k:
        return setup.no_contacts, 0
    compact, n_groups = kern.sticking_groups(group, friction)
    n_slide = int(np.sum(friction == SLIDE))
    v, e = setup.verts, features.edge_b
    none = np.zeros(0)
    held = kern.HeldContacts(
        features.body_a.astype(np.int64), features.body_b.astype(np.int64),
        v[features.vertex_a], v[e], v[setup.next_vertex[e]], setup.normals[e], none,
        np.zeros((0, 0)), friction.astype(np.int64), sigma.astype(float), mu_s, compact,
        n_groups)
    return held, 3 * k + n_groups + n_slide


class ContactModes:
    """Impacts and force LCPs of the touching contacts at an event.

    Keeps the final active set of the last pivoting solve of each LCP shape: the impulse and
    force LCPs first try it and keep it when the LCP residual accepts it, since the events of a
    periodic motion pose nearly the same problems every cycle."""

    def __init__(self, world: World, setup: Setup, settings: EventSettings,
                 friction_impulse: bool, stats: SolverStats) -> None:
        self.world = world
        self.setup = setup
        self.settings = settings
        self.friction_impulse = friction_impulse
        self.stats = stats
        self.patterns: dict[tuple, np.ndarray] = {}

    def settle(self, state: State, pending: list[StepContacts]) -> ModeChoice:
        """Resolve collisions at the current instant (impulses into ``pending``), then choose
        the next contact mode."""
        w, st = self.world, self.settings
        # Impacts change velocities only, so the contacts found once hold throughout.
        contacts = find_contacts(w.shapes, state.position, state.angle, w.dynamic,
                                 margin=st.touch_m)
        if contacts.n and contacts.gap.min() < -st.touch_m:
            contacts = self.move_out(state, contacts)
        if not contacts.n:
            return self.choose(state, None, None, None, pending)
        self.stats.max_penetration_m = max(self.stats.max_penetration_m,
                                           float(np.max(-contacts.gap, initial=0.0)))
        cs = self.contact_set(state, contacts)
        v_n, v_t = relative_velocity(cs, state)
        slip_tol = self.setup.slip_tol
        for _ in range(20):
            if not (v_n < -slip_tol * 10).any():
                break
            self.impact(cs, state, v_n, v_t, pending)
            v_n, v_t = relative_velocity(cs, state)
        # a contact moving along its normal slower than 10 slip_tol counts as resting and is
        # held at the acceleration level only, so that velocity too is closed, not kept
        # (below 1e-2 slip_tol it is the round-off of locating the event)
        zeno = self.zeno_speed(cs)
        if ((np.abs(v_n) > slip_tol * 1e-2) & (np.abs(v_n) < zeno)).any():
            self.close_accumulation(cs, state, v_n, v_t, zeno, pending)
            v_n, v_t = relative_velocity(cs, state)
        return self.choose(state, cs, v_n, v_t, pending)

    def move_out(self, state: State, contacts: Contacts) -> Contacts:
        """Move the parts that lie inside other bodies out of them; the contacts there.

        Nothing in this method's own motion sinks a corner (a held contact keeps its gap),
        but a part may be placed up to a quarter of its thinner piece inside another body (a
        scene's start, a part added or moved while the world runs). Held there, its corner
        stays that deep, and the event functions and the contact search disagree about its
        neighbours: a box standing on a corner 0.56 mm deep, tipping, brought its other
        corner to the surface, a collision event the contact search could not confirm (its
        neighbour lies below the face), and the same event came back every few picoseconds.
        The move is the smallest mass-weighted one that brings every contact of an island
        with a corner deeper than ``touch_m`` back to the surface (a frictionless LCP on the
        normal rows, ``lcp.solve``; the contact geometry found again after each move, at most
        eight times); velocities are kept. Counted as ``overlaps_moved_out``."""
        w, st = self.world, self.settings
        for _ in range(8):
            cs = self.contact_set(state, contacts)
            for bodies, idx in self.islands(cs):
                gap = contacts.gap[idx]
                if gap.min() >= -st.touch_m:
                    continue
                part = cs.subset(idx)
                J, minv, W = jacobian(w, part, bodies)
                k = part.n
                result = lcp.solve(lcp.FrictionalLCP(W[:k, :k], gap, np.full(k, -1),
                                                     np.zeros(k), np.zeros(k)),
                                   tol=st.lcp_tol)
                self.stats.record(result)
                move = (minv * (J.T @ np.concatenate([result.x, np.zeros(k)]))).reshape(-1, 3)
                state.position[bodies] += move[:, :2]
                state.angle[bodies] += move[:, 2]
            contacts = find_contacts(w.shapes, state.position, state.angle, w.dynamic,
                                     margin=st.touch_m)
            if not contacts.n or contacts.gap.min() >= -st.touch_m:
                break
        self.stats.overlaps_moved_out += 1
        if self.stats.overlaps_moved_out == 1:
            self.stats.messages.append(
                f'event driven: at t={state.t:.9f}s a part lay inside another body and was '
                'moved out (counted as overlaps_moved_out)')
        return contacts

    def zeno_speed(self, cs: ContactSet) -> np.ndarray:
        """``kern.zeno_speed`` of the contacts (m/s)."""
        c = cs.contacts
        return kern.zeno_speed(c.normal, c.body_a, c.body_b, self.world.dynamic,
                               self.world.gravity, self.settings.touch_m)

    def close_accumulation(self, cs: ContactSet, state: State, v_n: np.ndarray,
                           v_t: np.ndarray, zeno: np.ndarray,
                           pending: list[StepContacts]) -> None:
        """End an accumulation of impacts (Zeno) where it converges.

        A block rocking to rest with e < 1 hits one corner and then the other at intervals
        that shrink geometrically: infinitely many impacts in a finite time, after which it
        rests on the face. Near the end a touching corner leaves so slowly
        (``v_N < zeno_speed``) that gravity brings it back before it rises past the contact
        band; a corner that returns slower than the impact threshold would not be met by an
        impact. Such a corner and every touching contact slower than that take the impulse
        that gives them all ``v_N = 0``: the state the accumulation converges to. It is the
        minimum-kinetic-energy impulse (M-orthogonal projection), so it never adds energy;
        it stands for gravity's impulse over the vanishing rest of the accumulation, at most
        the mass times ``zeno_speed``. Counted as ``zeno_closures``.

        The same impulse stops a slip slower than ``mu_s`` times that speed, which friction
        under that normal impulse can hold: left, a tall part on a rough face slides on at
        round-off speed, its force LCP has no answer (Painlevé), and the tangential impact
        that follows rocks it again, an accumulation that never converges (a 10 x 20 mm box
        thrown at 0.1 m/s on a floor with mu = 5 rocked through 4 500 impacts in 6 ms at 1e-6
        m/s, with no end). ``v_n``, ``v_t``: the contacts' normal and tangential velocities
        (m/s), ``zeno``: their ``zeno_speed``."""
        near = np.flatnonzero((np.abs(v_n) < zeno)
                              | (np.abs(v_n) <= self.setup.slip_tol * 10))
        sub = cs.subset(near)
        for bodies, idx in self.islands(sub):
            part = sub.subset(idx)
            J, minv, W = jacobian(self.world, part, bodies)
            k = part.n
            slip = v_t[near][idx]
            stick = np.flatnonzero(np.abs(slip) < part.mu_static * zeno[near][idx])
            rows = np.concatenate([np.arange(k), k + stick])
            p = np.zeros(2 * k)
            p[rows] = -np.linalg.pinv(W[np.ix_(rows, rows)]) @ np.concatenate(
                [v_n[near][idx], slip[stick]])
            self._apply(J, minv, p, state, bodies)
            pending.append(StepContacts(part, p[:k], p[k:]))
            self.stats.zeno_closures += 1

    def impact(self, cs: ContactSet, state: State, v_n: np.ndarray, v_t: np.ndarray,
               pending: list[StepContacts]) -> None:
        """Simultaneous frictional impulse LCP (Kawachi) over every touching contact."""
        st = self.settings
        slip_tol = self.setup.slip_tol
        colliding = v_n < -slip_tol * 10
        for bodies, idx in self.islands(cs):
            whole = len(idx) == cs.n
            if not (colliding if whole else colliding[idx]).any():
                continue
            sub = cs if whole else cs.subset(idx)
            J, minv, W = jacobian(self.world, sub, bodies)
            vn, vt, hit = (v_n, v_t, colliding) if whole else (v_n[idx], v_t[idx], colliding[idx])
            b_full = kern.impact_rhs(vn, vt, sub.restitution, st.rest_speed_mps)
            friction, mu_lo, mu_hi = friction_rows(sub, vt, hit, self.friction_impulse, slip_tol)
            if not self.friction_impulse:
                friction[:] = NONE
            p, _, _ = self.solve_lcp('impact', W, b_full, friction, mu_lo, mu_hi)
            dv, gain, scale = kern.impulse_effect(J, minv, W, p, vn, vt)
            if gain > 1e-9 * max(1e-12, scale):
                # Never let a collision create kinetic energy: fall back to the frictionless
                # impulse, which cannot.
                self.stats.energy_fixes += 1
                p, _, _ = self.solve_lcp('impact', W, b_full, np.full(len(idx), NONE), mu_lo,
                                         mu_hi)
                dv = kern.impulse_effect(J, minv, W, p, vn, vt)[0]
            state.velocity[bodies] += dv[:, :2]
            state.omega[bodies] += dv[:, 2]
            k = len(idx)
            pending.append(StepContacts(sub, p[:k], p[k:]))
            self.stats.impacts += 1

    def choose(self, state: State, cs: ContactSet | None, v_n: np.ndarray | None,
               v_t: np.ndarray | None, pending: list[StepContacts]) -> ModeChoice:
        """Baraff's frictional force LCP over resting contacts decides the next phase.

        ``cs`` are the touching contacts (None if there are none), ``v_n, v_t`` their
        relative velocities."""
        if cs is None:
            return ModeChoice(Contacts.empty(), np.zeros(0, int), np.zeros(0), np.zeros(0, int),
                              ContactMaterial(np.zeros(0), np.zeros(0), np.zeros(0)), None,
                              np.zeros(0))
        setup = self.setup
        resting = np.flatnonzero(np.abs(v_n) <= setup.slip_tol * 10)
        if len(resting) < cs.n:
            cs = cs.subset(resting)
            v_n, v_t = v_n[resting], v_t[resting]
        k = cs.n
        keep = np.zeros(k, bool)
        friction = np.zeros(k, np.int64)
        force_n = np.zeros(k)
        sigma = np.sign(v_t)
        acc = self.free_acceleration(state.t)
        sliding = np.abs(v_t) > setup.slip_tol
        for bodies, idx in self.islands(cs):
            whole = len(idx) == k
            sub = cs if whole else cs.subset(idx)
            vn, vt, sig = (v_n, v_t, sigma) if whole else (v_n[idx], v_t[idx], sigma[idx])
            ok, message, a_rel, f, fr = self.force_lcp(sub, state, acc, bodies, vn, vt,
                                                       sliding[idx], sig)
            if not ok:
                # No consistent contact forces (Painlevé): impulse without collision, then
                # the forces of the contacts that still rest.
                self.stats.messages.append(
                    f'force LCP failed at t={state.t:.9f}s ({message}); impulse applied')
                self.impact_without_collision(sub, state, bodies, pending)
                vn, vt = relative_velocity(sub, state)
                still = np.abs(vn) <= setup.slip_tol * 10
                if not still.all():
                    keep[idx[~still]] = False
                    idx, sub = idx[still], sub.subset(np.flatnonzero(still))
                    vn, vt = vn[still], vt[still]
                slips = np.abs(vt) > setup.slip_tol
                sig = np.where(slips, np.sign(vt), sig[still])
                ok, message, a_rel, f, fr = self.force_lcp(sub, state, acc, bodies, vn, vt,
                                                           slips, sig)
                if not ok:
                    self.unresolved(state.t, message)
            if not len(idx):
                continue
            keep[idx], friction[idx], sigma[idx] = kern.mode_rows(
                f, a_rel, fr, sub.mu_static, sig, setup.force_scale * FORCE_TOL_REL,
                1e-9 * setup.g, sub.contacts.body_a, sub.contacts.body_b, sub.contacts.normal)
            force_n[idx] = f[:len(idx)]
            held = keep[idx]
            if kern.slip_left(friction[idx][held], vt[held], setup.slip_tol):
                self.close_slip(sub.subset(np.flatnonzero(held)), state, bodies, vn[held],
                                vt[held], friction[idx][held], pending)
        sel = np.flatnonzero(keep)
        active = cs if len(sel) == k else cs.subset(sel)
        return ModeChoice(active.contacts, friction[sel], sigma[sel], groups(active),
                          ContactMaterial(active.mu_static, active.mu_dynamic,
                                          active.restitution), active, force_n[sel])

    def close_slip(self, cs: ContactSet, state: State, bodies: np.ndarray, v_n: np.ndarray,
                   v_t: np.ndarray, friction: np.ndarray, pending: list[StepContacts]) -> None:
        """Stop what is left of a slip at contacts that stick from now on, and the normal
        motion of every held contact, by ``kern.stick_closure``'s impulse (recorded, counted
        as ``slip_closures``). ``cs``: the contacts the mode holds, ``v_n, v_t`` their
        relative velocities (m/s), ``friction`` their friction states."""
        J, minv, W = jacobian(self.world, cs, bodies)
        p = kern.stick_closure(W, v_n, v_t, friction)
        self._apply(J, minv, p, state, bodies)
        pending.append(StepContacts(cs, p[:cs.n], p[cs.n:]))
        self.stats.slip_closures += 1

    def force_lcp(self, cs: ContactSet, state: State, acc: np.ndarray, bodies: np.ndarray,
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
        _, _, W = jacobian(self.world, cs, bodies)
        f, ok, message = self.solve_lcp('force', W, b_full, fr, cs.mu_static, cs.mu_static,
                                        -sigma * cs.mu_dynamic)
        return ok, message, W @ f + b_full, f, fr

    def free_acceleration(self, t: float) -> np.ndarray:
        """(n, 2) accelerations without contact forces: gravity, or the prescribed motion."""
        w = self.world
        acc = w.prescribed_acceleration(t)
        acc[w.dynamic] = w.gravity
        return acc

    def impact_without_collision(self, cs: ContactSet, state: State, bodies: np.ndarray,
                                 pending: list[StepContacts]) -> None:
        """The impulse where no contact forces are consistent (Painlevé).

        A contact sliding on a ray on which its normal velocity would fall
        (``K_NN - mu_d sigma K_TN <= 0`` in its own collision matrix) takes Génot &
        Brogliato's tangential impact (``routh.routh_collision`` from ``u_N = 0``, e = 0): it
        presses in and stops slipping although it did not approach. The steepest such ray
        goes first and the velocities are read again after each, as the impulse-based method
        orders its collisions. Then Kawachi's impulse LCP stops whatever approach is left."""
        k = cs.n
        J, minv, W = jacobian(self.world, cs, bodies)
        # each contact's own collision matrix in (t, n)
        knn, ktt, ktn = np.diag(W)[:k], np.diag(W)[k:], np.diag(W[:k, k:])
        p = np.zeros(2 * k)
        for _ in range(k):
            v_n, v_t = relative_velocity(cs, state)
            fall = knn - cs.mu_dynamic * np.sign(v_t) * ktn
            fall[(np.abs(v_t) <= self.setup.slip_tol) | (np.abs(v_n) > self.setup.slip_tol)] = 0
            i = int(np.argmin(fall))
            if not fall[i] < 0.0:
                break
            pt, pn, *_ = routh_collision(ktt[i], ktn[i], knn[i], v_t[i], 0.0,
                                         cs.mu_dynamic[i], cs.mu_static[i], 0.0, STRONGE, 0.0)
            dp = np.zeros(2 * k)
            dp[i], dp[k + i] = pn, pt
            self._apply(J, minv, dp, state, bodies)
            p += dp
            self.stats.tangential_impacts += 1
        v_n, v_t = relative_velocity(cs, state)
        friction, mu_lo, mu_hi = friction_rows(cs, v_t, np.zeros(k, bool), True,
                                               self.setup.slip_tol)
        q, _, _ = self.solve_lcp('impact', W, np.concatenate([np.minimum(v_n, 0.0), v_t]),
                                 friction, mu_lo, mu_hi)
        self._apply(J, minv, q, state, bodies)
        p += q
        if p.any():
            self.stats.impacts += 1
            pending.append(StepContacts(cs, p[:k], p[k:]))

    def unresolved(self, t: float, message: str) -> None:
        """Count a force LCP that failed again after the impulse (reported by the run)."""
        self.stats.unresolved_force_lcps += 1
        if len(self.stats.messages) < 20:
            self.stats.messages.append(
                f'force LCP failed again after the impulse at t={t:.9f}s ({message})')

    @staticmethod
    def _apply(J: np.ndarray, minv: np.ndarray, p: np.ndarray, state: State,
               bodies: np.ndarray) -> None:
        dv = (minv * (J.T @ p)).reshape(-1, 3)
        state.velocity[bodies] += dv[:, :2]
        state.omega[bodies] += dv[:, 2]

    def contact_set(self, state: State, contacts: Contacts) -> ContactSet:
        """:func:`contact_set`, with the body pairs' materials looked up."""
        a, b = contacts.body_a, contacts.body_b
        mu_s, mu_d, e = self.setup.materials
        return ContactSet(contacts, contacts.normal[:, ::-1] * (-1.0, 1.0),
                          contacts.point - state.position[a], contacts.point - state.position[b],
                          mu_s[a, b], mu_d[a, b], e[a, b])

    def islands(self, cs: ContactSet) -> list[tuple[np.ndarray, np.ndarray]]:
        """(bodies, contacts) of each group of bodies the contacts connect."""
        dyn = self.setup.dyn
        if len(dyn) == 1:
            return [(dyn, np.arange(cs.n))] if cs.n else []
        return islands(self.world, cs)

    def solve_lcp(self, kind: str, W: np.ndarray, b_full: np.ndarray, friction: np.ndarray,
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
        pattern = self.patterns.get(key)
        if pattern is not None:
            f, x, w, res = kern.lcp_known_pattern(W, b_full, friction, mu_lo, mu_hi, slave,
                                                  pattern)
            if res <= tol:
                self.stats.record(lcp.LCPResult(x, w, 'active set', 0, 0, res, True, ''))
                return f, True, ''
        # The compiled Dantzig takes lcp.solve's pivots without its Python bookkeeping, which
        # would dominate an event's cost; an answer that misses the tolerance goes to
        # lcp.solve and its fallback ladder, as in time_stepping.
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
            self.patterns[key] = kern.lcp_pattern(result.x, normal_of, lo, hi)
        return f, result.converged, result.message
