"""Event location of the event-driven method: candidate collisions and integrated phases.

:class:`CandidateWatch` keeps the candidate collisions (active corners near a piece of another
body) and detects them again when a body may have moved half their margin. :class:`Integrator`
follows a mode without closed form by Dormand–Prince 5(4) steps with error control (compiled
when the drives are plain sinusoids, else in Python, asking the drives), shortened so that no
corner passes through a piece unseen, and locates the first event function to cross zero by
Illinois regula falsi on full integrator steps from the step start.
"""

from __future__ import annotations

import math

import numpy as np

from feeder_sim.contact.candidates import corner_piece_candidates
from feeder_sim.contact.dynamics import BOX, ContactSet, NONE, SLAVED, SolverStats
from feeder_sim.model.scene import STEP_RULES
from feeder_sim.model.world import perp, State, World
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.event_driven.bookkeeping import (
    accumulate_forces,
    Candidates,
    EVENT_THRESHOLD,
    GAP_SCALE_M,
    Mode,
    pack,
    Setup,
    unpack,
)
from feeder_sim.stepping.event_driven.modes import jacobian, with_geometry
from feeder_sim.stepping.protocol import StepContacts

STICK, SLIDE = kern.STICK, kern.SLIDE

# The Dormand–Prince 5(4) tableau of the compiled integrator, as the Python path reads it:
# stage i's coefficients, the 5th-order (FSAL) weights and the error weights.
_C = kern.DP_C
_A = [[float(a) for a in kern.DP_A[i, :i]] for i in range(7)]
_B5 = np.array(_A[6] + [0.0])
_E = kern.DP_E


def largest_step(world: World, time_step: float) -> float:
    """The scene's time step (s), at most the method's step rule's share of the period of
    every drive as it is now commanded."""
    return min(time_step, STEP_RULES['event_driven'].step(
        world.drives[i].frequency_hz for i in world.driven))


def closed_form_margin(world: World, length: float) -> float:
    """Margin (m) of the candidates of closed-form phases: a few body sizes and amplitudes."""
    amplitude = max((world.drives[i].amplitude_m for i in world.driven), default=0.0)
    return 4.0 * length + 4.0 * amplitude


class CandidateWatch:
    """The candidate collisions, before the held contacts are left out (``near``); kept
    across events while no body can have moved half their margin."""

    def __init__(self, world: World, setup: Setup) -> None:
        self.world = world
        self.setup = setup
        self.near: Candidates | None = None

    def find(self, state: State, margin: float) -> Candidates:
        """Active corners against pieces of other bodies whose boxes are within ``margin``."""
        setup = self.setup
        if len(setup.piece_body) < 2:
            none = np.zeros(0, dtype=np.int64)
            return Candidates(none, none, self.arrays(none, none), state.position.copy(),
                              state.angle.copy(), margin, state.t)
        vertex, piece = corner_piece_candidates(self.world, state, setup.active_vertex,
                                                margin)[:2]
        return Candidates(vertex, piece, self.arrays(vertex, piece), state.position.copy(),
                          state.angle.copy(), margin, state.t)

    def arrays(self, vertex: np.ndarray, piece: np.ndarray) -> kern.CandidateArrays:
        """Kernel arrays of candidate corners against pieces."""
        s = self.setup
        v, ps = s.verts, s.piece_start
        wedge = np.stack([v[s.next_vertex[vertex]] - v[vertex],
                          v[s.prev_vertex[vertex]] - v[vertex]], axis=1).reshape(-1, 2, 2)
        return kern.CandidateArrays(
            s.vertex_body[vertex].astype(np.int64), v[vertex],
            s.piece_body[piece].astype(np.int64), ps[piece].astype(np.int64),
            ps[piece + 1].astype(np.int64), np.ascontiguousarray(wedge), s.piece_width[piece])

    def closed_form_margin(self) -> float:
        return closed_form_margin(self.world, self.setup.length)

    def travel_margin(self, state: State, duration: float) -> float:
        """Twice the farthest (m) a dynamic body's corners get within ``duration`` (s) at
        their speed now under gravity: a margin no body outruns in that time unless a
        contact or a drive speeds it up."""
        s = self.setup
        speed = float(np.max(np.hypot(state.velocity[s.dyn, 0], state.velocity[s.dyn, 1])
                             + np.abs(state.omega[s.dyn]) * s.radius[s.dyn], initial=0.0))
        return 2.0 * duration * (speed + 0.5 * s.g * duration)

    def ensure(self, state: State) -> Candidates:
        """The candidates of closed-form phases, detected now if there are none."""
        if self.near is None:
            self.near = self.find(state, self.closed_form_margin())
        return self.near

    def redetect(self, mode: Mode, state: State, margin: float) -> None:
        """Detect the candidates again within ``margin`` (m) and give ``mode`` its own."""
        self.near = self.find(state, margin)
        mode.candidates = self.near.without(mode.features)

    def for_step(self, mode: Mode, state: State, h: float) -> None:
        """Candidates of an integrator step: every pair within a heuristic reach of the step.

        The pairs detected earlier within a wider margin still contain them while no body has
        moved more than half the difference."""
        near = self.near
        reach = 2.0 * h * (self.setup.speed * 4 + float(np.max(
            np.linalg.norm(state.velocity, axis=1), initial=0.0))) + 1e-6
        if near is not None:
            moved = float(np.max(np.linalg.norm(state.position - near.anchor_pos, axis=1) +
                                 np.abs(state.angle - near.anchor_ang) * self.setup.radius))
            if 2.0 * moved + reach > near.margin:
                near = None
        if near is None:
            near = self.near = self.find(state, max(2.0 * reach, self.closed_form_margin()))
            mode.candidates = None
        if mode.candidates is None:
            mode.candidates = near.without(mode.features)


class Integrator:
    """Dormand–Prince steps of a held mode without closed form, and their events."""

    def __init__(self, world: World, setup: Setup, rtol: float, time_step: float) -> None:
        self.world = world
        self.setup = setup
        self.tol_scale = rtol * setup.scale
        self.time_step = time_step

    # ------------------------------------------------------------------ smooth dynamics
    def rhs(self, mode: Mode | None, t: float, y: np.ndarray,
            scratch: State) -> tuple[np.ndarray, dict]:
        """Time derivative of y under the held mode, and the values the events watch."""
        w, dyn = self.world, self.setup.dyn
        s = unpack(w, dyn, t, y, scratch)
        nd = len(dyn)
        acc = np.zeros((w.n, 2))
        acc[w.dynamic] = w.gravity
        kin_acc = w.prescribed_acceleration(t)
        acc[~w.dynamic] = kin_acc[~w.dynamic]
        alpha = np.zeros(w.n)
        aux: dict = {}
        if mode is not None and mode.features.n:
            cs = with_geometry(w, mode.features, s)
            f_n, f_t, v_t = self.contact_forces(mode, cs, s, acc, alpha)
            aux = {'cs': cs, 'f_n': f_n, 'f_t': f_t, 'v_t': v_t}
        dydt = np.concatenate([y[3 * nd:5 * nd], y[5 * nd:], acc[dyn].ravel(), alpha[dyn]])
        return dydt, aux

    def mode_system(self, mode: Mode, cs: ContactSet):
        """The held mode's equations: bodies, J, M^-1 and the square system A x = -b[rows]
        whose solution x gives the stacked contact forces P x."""
        w = self.world
        c = cs.contacts
        k = c.n
        bodies = np.unique(np.concatenate([c.body_a, c.body_b]))
        bodies = bodies[w.dynamic[bodies]]
        J, minv, W = jacobian(w, cs, bodies)
        friction = np.where(mode.friction == STICK, BOX,
                            np.where(mode.friction == SLIDE, SLAVED, NONE))
        slave = -mode.sigma * cs.mu_dynamic
        A, P, rows, _, _, _ = kern.reduce_lcp(W, friction.astype(np.int64), np.zeros(k),
                                              np.zeros(k), slave)
        return bodies, J, minv, A, P, rows

    def contact_forces(self, mode: Mode, cs: ContactSet, s: State, acc: np.ndarray,
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
        bodies, J, minv, A, P, rows = self.mode_system(mode, cs)
        x = np.linalg.lstsq(A, -np.concatenate([b_n, b_t])[rows], rcond=1e-12)[0]
        f = P @ x
        dv = (minv * (J.T @ f)).reshape(-1, 3)
        acc[bodies] += dv[:, :2]
        alpha[bodies] += dv[:, 2]
        return f[:k], f[k:], v_t

    def event_values(self, mode: Mode, aux: dict) -> np.ndarray:
        """Event functions of the held mode (each must stay >= 0), scaled to be comparable."""
        if not aux:
            return np.zeros(0)
        f_n, f_t, v_t = aux['f_n'], aux['f_t'], aux['v_t']
        cs = aux['cs']
        fs, vs = self.setup.force_scale, self.setup.speed
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

    def gap_values(self, mode: Mode, s: State) -> np.ndarray:
        """The candidates' collision gaps in units of GAP_SCALE_M."""
        cand = mode.candidates
        out = np.empty(cand.n)
        if cand.n:
            kern.candidate_gaps(s.position, s.angle, cand.arrays, self.setup.verts,
                                self.setup.normals, out)
        return out / GAP_SCALE_M

    def events_of(self, mode: Mode, aux: dict,
                  scratch: State) -> tuple[np.ndarray, np.ndarray]:
        """Event functions and stacked forces of a Python right-hand side evaluation."""
        g = np.concatenate([self.event_values(mode, aux), self.gap_values(mode, scratch)])
        return g, (np.concatenate([aux['f_n'], aux['f_t']]) if aux else np.zeros(0))

    def evaluate(self, mode: Mode, t: float, y: np.ndarray,
                 scratch: State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dy/dt, event functions, stacked contact forces)`` of the held mode at (t, y)."""
        if mode.spec is not None:
            return kern.mode_rhs(t, y, mode.spec._replace(cands=mode.candidates.arrays),
                                 mode.n_events + mode.candidates.n, *self.setup.out)
        dydt, aux = self.rhs(mode, t, y, scratch)
        return (dydt, *self.events_of(mode, aux, scratch))

    # ------------------------------------------------------------------ integration
    def dopri_step(self, mode: Mode, t: float, y: np.ndarray, h: float, k0: np.ndarray,
                   scratch: State):
        """Dormand–Prince step: ``(y_new, error norm, dy/dt, events, forces)``, the last three
        at the step's end (first same as last)."""
        if mode.spec is not None:
            return kern.dopri_step(t, y, h, k0, mode.spec._replace(cands=mode.candidates.arrays),
                                   mode.n_events + mode.candidates.n, self.tol_scale,
                                   *self.setup.out)
        ks = [k0]
        aux: dict = {}
        for i in range(1, 7):
            yi = y + h * sum(a * k for a, k in zip(_A[i], ks))
            k, aux = self.rhs(mode, t + _C[i] * h, yi, scratch)
            ks.append(k)
        y_new = y + h * sum(b * k for b, k in zip(_B5[:6], ks[:6]))
        err_vec = h * sum(e * k for e, k in zip(_E, ks))
        err = float(np.sqrt(np.mean((err_vec / self.tol_scale) ** 2))) \
            if len(y) else 0.0
        return (y_new, err, ks[6], *self.events_of(mode, aux, scratch))

    def step(self, mode: Mode, state: State, t_stop: float, h: float, scratch: State,
             watch: CandidateWatch, pending: list[StepContacts],
             stats: SolverStats) -> tuple[bool, float]:
        """One Dormand–Prince step of the held mode from ``state`` (or up to its first event),
        tried at ``h`` (s): whether an event ended it, and the next step to try."""
        h_max = largest_step(self.world, self.time_step)
        h = min(h, h_max, t_stop - state.t)
        t0 = state.t
        y0 = pack(self.setup.dyn, state)
        watch.for_step(mode, state, h)
        k0, g0, f0 = self.evaluate(mode, t0, y0, scratch)
        offset = kern.event_offsets(g0, mode.candidates.n, EVENT_THRESHOLD)
        h = self.guarded_step(mode, state, k0, h, g0, offset)
        while True:
            y1, err, k1, g1, f1 = self.dopri_step(mode, t0, y0, h, k0, scratch)
            if err <= 1.0 or h < 1e-14:
                break
            h *= max(0.2, 0.9 * err ** -0.2)
        hit = (g1 + offset < 0.0) & (g0 + offset >= 0.0)
        factor = 5.0 if err == 0 else min(5.0, max(0.2, 0.9 * err ** -0.2))
        if hit.any():
            tau, y_ev, f_ev = self.locate(mode, t0, y0, k0, h, g0 + offset, g1 + offset, f1,
                                          y1, hit, offset, scratch)
            unpack(self.world, self.setup.dyn, t0 + tau, y_ev, state)
            accumulate_forces(pending, mode, f0, f_ev, tau, state)
            return True, max(h, 1e-9)
        unpack(self.world, self.setup.dyn, t0 + h, y1, state)
        accumulate_forces(pending, mode, f0, f1, h, state)
        stats.steps += 1
        return False, min(h * factor, largest_step(self.world, self.time_step))

    def guarded_step(self, mode: Mode, state: State, k0: np.ndarray, h: float, g0: np.ndarray,
                     offset: np.ndarray) -> float:
        """``h`` shortened so that no corner can pass through a piece within the step
        (:func:`feeder_sim.stepping.event_driven._kernels.guarded_step`)."""
        cand = mode.candidates
        if not cand.n:
            return h
        if mode.drive_acc is None:
            mode.drive_acc = self.drive_accelerations()
        return kern.guarded_integrator_step(h, state.position, state.angle, state.velocity,
                                            state.omega, k0, self.setup.dyn, mode.drive_acc,
                                            cand.arrays, g0, len(g0) - cand.n, offset,
                                            GAP_SCALE_M)

    def drive_accelerations(self) -> np.ndarray:
        """(n,) every body's largest drive acceleration A (2 pi f)^2 (m/s^2), 0 undriven."""
        w = self.world
        acc = np.zeros(w.n)
        for i in w.driven:
            drive = w.drives[i]
            acc[i] = drive.amplitude_m * (2.0 * math.pi * drive.frequency_hz) ** 2
        return acc

    def locate(self, mode: Mode, t0: float, y0: np.ndarray, k0: np.ndarray, h: float,
               g0: np.ndarray, g1: np.ndarray, f1: np.ndarray, y1: np.ndarray, hit: np.ndarray,
               offset: np.ndarray, scratch: State) -> tuple[float, np.ndarray, np.ndarray]:
        """Earliest time in (0, h] at which a hit event function reaches its level.

        ``g0``, ``g1`` are the event functions with ``offset`` added (see
        ``kern.event_offsets``): a function fires when that sum drops below zero.

        Illinois regula falsi on tau -> g(step(y0, tau)), bracketing the earliest crossing of
        any hit function (the iteration of ``kern.illinois_trial``): every trial is a full
        integrator step from the phase start, so the event state is as accurate as a normal
        step. Returns the state just past the crossing and the contact forces there.
        """
        lo, hi = 0.0, h
        g_lo = g0[hit]
        g_hi = g1[hit]
        best = (h, y1, f1)
        side = 0
        for _ in range(100):
            if hi - lo <= 1e-15 * max(1.0, abs(t0)) + 1e-16:
                break
            tau = kern.illinois_trial(lo, hi, g_lo, g_hi)
            y_t, _, _, g_t_all, f_t = self.dopri_step(mode, t0, y0, tau, k0, scratch)
            g_t = g_t_all[hit] + offset[hit]
            crossed, lo, hi, g_lo, g_hi, side = kern.illinois_narrow(tau, g_t, lo, hi, g_lo,
                                                                     g_hi, side)
            if crossed:
                best = (tau, y_t, f_t)
        return best
