"""Closed-form phases of the event-driven method, and the hand-off to the compiled chain.

A mode in which every dynamic body flies free or translates without turning against static or
sinusoidally driven bodies has linear equations with constant coefficients in gravity and the
drives' accelerations: :func:`closed_form` solves them once per phase, :func:`follow_closed_form`
moves the state along the exact motion to the first event and :func:`follow_chain` carries a
single dynamic body on through the events its own contacts resolve (:mod:`._chain`). A mode
without closed form gets the compiled integrator's arguments (:func:`compiled_rhs`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from feeder_sim.contact.collision import Contacts
from feeder_sim.contact.dynamics import ContactSet, SolverStats
from feeder_sim.model.world import DRIVEN, FIXED, MOVING, State, World
from feeder_sim.stepping.event_driven import _chain as chain
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.event_driven.bookkeeping import (
    ALPHA_REL,
    CHAIN_ROWS,
    ContactMaterial,
    contacts_at,
    count_chain,
    EVENT_THRESHOLD,
    Mode,
    Phase,
    recorded,
    Setup,
    SPIN_FRACTION,
)
from feeder_sim.stepping.event_driven.events import CandidateWatch
from feeder_sim.stepping.event_driven.modes import held_arrays
from feeder_sim.stepping.protocol import StepContacts


class DriveModel(NamedTuple):
    """Body kinds and drive arrays of closed-form phases."""

    index: np.ndarray         # (n,) drive row of a driven body, else -1
    drives: kern.Drives
    free: Phase               # every body without contacts


class DriveModels:
    """The drive model of the current drive settings, kept while the drives' amplitudes and
    frequencies stay, so that every phase follows one and the same sinusoid per drive (a
    command resets the stepper)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.key: tuple | None = None
        self.model: DriveModel | None = None

    def clear(self) -> None:
        self.key = self.model = None

    def at(self, t: float) -> DriveModel | None:
        """The drive model from ``t`` on, or None while a drive blends."""
        w = self.world
        segs = w.drive_segments(t)
        if segs.blending(t):
            return None   # a command blend: not a plain sinusoid
        key = tuple(zip(segs.amplitude_m.tolist(), segs.omega_rad_s.tolist()))
        if self.model is not None and self.key == key:
            return self.model
        n = w.n
        kind = np.where(w.dynamic, MOVING, FIXED).astype(np.int64)
        index = np.full(n, -1, dtype=np.int64)
        u, base, amp, omega, phase = [], [], [], [], []
        for row, i in enumerate(w.driven):
            d, v, _ = w.drives[i].motion(t)
            a, om = segs.amplitude_m[row], segs.omega_rad_s[row]
            if a == 0.0 or om == 0.0:
                continue      # at rest
            # The drive is A sin(phase + omega (t - t_ref)) from its current phase on.
            sn, cs = d / a, v / (a * om)
            if abs(math.hypot(sn, cs) - 1.0) > 1e-9:
                return None
            kind[i], index[i] = DRIVEN, len(amp)
            u.append(segs.direction[row])
            base.append(segs.base_m[row])
            amp.append(a)
            omega.append(om)
            phase.append(math.atan2(sn, cs))
        nd = len(amp)
        drives = kern.Drives(np.array(u, dtype=float).reshape(nd, 2),
                             np.array(base, dtype=float).reshape(nd, 2),
                             np.array(amp, dtype=float), np.array(omega, dtype=float),
                             np.array(phase, dtype=float), float(t))
        phi0 = np.zeros((n, 2))
        phi0[w.dynamic] = w.gravity
        none_i, none_f = np.zeros(0, np.int64), np.zeros(0)
        none_v = np.zeros((0, 2))
        f1 = np.zeros((0, nd))
        free = Phase(kind, index, phi0, np.zeros((n, 2, nd)), drives,
                     kern.HeldContacts(none_i, none_i, none_v, none_v, none_v, none_v, none_f,
                                       f1, none_i, none_f, none_f, none_i, 0), none_f, f1)
        self.key, self.model = key, DriveModel(index, drives, free)
        return self.model


def closed_form(world: World, setup: Setup, mode: Mode, state: State, cs: ContactSet | None,
                model: DriveModel | None) -> Phase | None:
    """The held mode's exact motion, if it has the closed form (package docstring).

    ``cs`` are the held contacts at ``state`` (None when there are none)."""
    if model is None:
        return None
    index, drives, free = model
    c = mode.features
    k = c.n
    if not k:
        return free
    a, b = c.body_a, c.body_b
    if not (world.dynamic[a].all() and not world.dynamic[b].any()):
        return None
    ok, bodies, dv, f = kern.closed_form_mode(
        c.normal, cs.r_a, cs.r_b, a, b, world.dynamic, world.inv_mass, world.inv_inertia,
        mode.friction, mode.sigma, cs.mu_dynamic, state.omega, setup.radius,
        SPIN_FRACTION * setup.slip_tol, ALPHA_REL * setup.g, np.asarray(world.gravity,
                                                                        dtype=float),
        index, drives.u)
    if not ok:
        return None
    phi0, phi1 = free.phi0.copy(), free.phi1.copy()
    phi0[bodies] += dv[:, :2, 0]
    phi1[bodies] = dv[:, :2, 1:]
    f0, f1 = f[:, 0].copy(), np.ascontiguousarray(f[:, 1:])
    contacts = mode.held._replace(f0=f0, f1=f1)
    return Phase(free.kind, index, phi0, phi1, drives, contacts, f0, f1)


def compiled_rhs(world: World, setup: Setup, mode: Mode, state: State,
                 model: DriveModel | None) -> kern.RhsSpec | None:
    """Arguments of the compiled right-hand side of the held mode (candidates still empty),
    None while a drive blends (then the Python one, which asks the drives, integrates)."""
    if model is None:
        return None
    index, drives, free = model
    dyn = setup.dyn
    col = np.full(world.n, -1, dtype=np.int64)
    col[dyn] = 3 * np.arange(len(dyn))
    return kern.RhsSpec(
        dyn=dyn.astype(np.int64), col=col, kind=free.kind, index=index,
        pos_fixed=state.position.copy(), ang_fixed=state.angle.copy(), drives=drives,
        gravity=np.asarray(world.gravity, dtype=float), inv_mass=world.inv_mass,
        inv_inertia=world.inv_inertia, contacts=mode.held, mu_dynamic=mode.material.mu_dynamic,
        cands=None, verts=setup.verts, normals=setup.normals, scales=setup.scales)


def _store(world: World, setup: Setup, state: State, t: float, out: tuple) -> None:
    """The dynamic bodies of ``out`` (pos, ang, vel, om) into ``state`` at t."""
    d = setup.dyn
    pos, ang, vel, om = out
    state.t = t
    state.position[d] = pos[d]
    state.angle[d] = ang[d]
    state.velocity[d] = vel[d]
    state.omega[d] = om[d]
    world.apply_prescribed_motion(state)


# Candidates detected again are to last this many of the largest steps, at the bodies' speed.
REDETECT_STEPS = 16


def _redetect(watch: CandidateWatch, mode: Mode, state: State, margin: float, t_stop: float,
              h_max: float) -> None:
    """Detect the candidate collisions again, within ``margin`` (m) or what the bodies can
    travel in the next ``REDETECT_STEPS`` steps, whichever is more: a part falling fast,
    far from anything, would otherwise be detected again at every step."""
    ahead = min(t_stop - state.t, REDETECT_STEPS * h_max)
    watch.redetect(mode, state, max(margin, watch.travel_margin(state, ahead)))


def follow_closed_form(world: World, setup: Setup, mode: Mode, state: State, t_stop: float,
                       h_max: float, watch: CandidateWatch, models: DriveModels,
                       pending: list[StepContacts], stats: SolverStats) -> bool:
    """Move the state along the held mode's exact motion to t_stop or its first event;
    True at an event."""
    ph = mode.phase
    near = watch.ensure(state)
    if mode.candidates is None:
        mode.candidates = near.without(mode.features)
    pos, ang, vel, om = setup.out
    dvel = np.zeros(len(ph.drives.amplitude))
    t0 = state.t
    for _ in range(64):
        cand = mode.candidates
        bodies = kern.PhaseBodies(ph.kind, ph.index, state.position, state.angle,
                                  state.velocity, state.omega, ph.phi0, ph.phi1)
        reach = kern.Reach(cand.anchor_pos, cand.anchor_ang, setup.radius, 0.5 * cand.margin)
        status, t_new, steps = kern.advance(
            t0, t_stop, h_max, EVENT_THRESHOLD, mode.n_events + cand.n, bodies, ph.drives,
            ph.contacts, cand.arrays, setup.verts, setup.normals, setup.scales, reach, pos,
            ang, vel, om, dvel)
        stats.steps += steps
        if status == kern.REFRESH and t_new == t0:
            # Detected at another configuration, or a single step can outrun the margin.
            grow = 2.0 if cand.t == t0 else 1.0
            _redetect(watch, mode, state, grow * cand.margin, t_stop, h_max)
            continue
        break
    else:
        mode.phase = None    # no finite speed bound: integrate instead
        mode.spec = compiled_rhs(world, setup, mode, state, models.at(state.t))
        return False
    if ph.f0.size:
        impulse = ph.f0 * (t_new - t0) + ph.f1 @ dvel
        k = len(impulse) // 2
        pending.append(StepContacts(contacts_at(mode, pos, ang), impulse[:k], impulse[k:]))
    _store(world, setup, state, t_new, setup.out)
    if status == kern.REFRESH:
        _redetect(watch, mode, state, cand.margin, t_stop, h_max)
    return status == kern.EVENT


def follow_chain(world: World, setup: Setup, mode: Mode, state: State, t_stop: float,
                 h_max: float, watch: CandidateWatch, models: DriveModels,
                 pending: list[StepContacts], stats: SolverStats) -> tuple[bool, Mode]:
    """:func:`follow_closed_form` for a single dynamic body, carried on through the events its
    own contacts resolve (:mod:`._chain`): whether it ended at an event, and the mode held
    then."""
    ph = mode.phase
    near = watch.ensure(state)
    f = mode.features
    t0 = state.t
    out = (state.position.copy(), state.angle.copy(), state.velocity.copy(),
           state.omega.copy())
    size = max(CHAIN_ROWS, 64 * f.n)
    record = chain.ImpulseRecord(
        np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.int64),
        np.empty(size, np.int64), np.empty((size, 2)), np.empty((size, 2)), np.empty(size),
        np.empty(size))
    h = mode.held
    held = chain.ChainContacts(
        f.vertex_a.astype(np.int64), f.edge_b.astype(np.int64), f.piece_b.astype(np.int64),
        h.body_a, h.body_b, h.vertex, h.edge_start, h.edge_end, h.normal,
        *(np.ascontiguousarray(m, dtype=float) for m in mode.material))
    res = chain.follow(
        t0, t_stop, h_max, out,
        chain.PhaseModel(ph.kind, ph.index, models.model.free.phi0, ph.drives),
        setup.chain_world, held,
        chain.ChainMode(mode.friction.astype(np.int64), mode.sigma.astype(float), ph.phi0,
                        ph.phi1, ph.f0, ph.f1),
        chain.Near(near.vertex.astype(np.int64), near.piece.astype(np.int64), near.arrays,
                   near.anchor_pos, near.anchor_ang, near.margin),
        setup.chain_geometry, setup.materials, setup.scales, setup.chain_tols, record)
    if res.status == kern.REFRESH and res.t == t0 and not res.events:
        # follow_closed_form widens the candidates' margin
        return follow_closed_form(world, setup, mode, state, t_stop, h_max, watch, models,
                                  pending, stats), mode
    count_chain(stats, res.steps, res.events, res.stats)
    _store(world, setup, state, res.t, out)
    if res.rows:
        pending.append(recorded(setup, state, record, res.rows))
    if res.status == kern.EVENT:
        return True, mode
    if res.events:
        held, friction, sigma = res.held, res.friction, res.sigma
        point, normal, gap, param = kern.held_geometry(
            state.position, state.angle, held.body_a, held.body_b, held.vertex_local,
            held.edge_start, held.edge_end, held.normal)
        features = Contacts(held.body_a, setup.vertex_piece[held.vertex], held.vertex,
                            held.body_b, held.piece, held.edge, point, normal, gap, param)
        material = ContactMaterial(held.mu_static, held.mu_dynamic, held.restitution)
        group = kern.contact_groups(features.body_a, features.body_b, normal)
        kernel_held, n_events = held_arrays(setup, features, friction, sigma, group,
                                            material.mu_static)
        mode = Mode(features, friction, sigma, group, material, kernel_held, n_events)
        mode.phase = Phase(ph.kind, ph.index, res.phi0, res.phi1, ph.drives,
                           kernel_held._replace(f0=res.f0, f1=res.f1), res.f0, res.f1)
        mode.candidates = near.without(features)
    if res.status == kern.REFRESH:
        _redetect(watch, mode, state, near.margin, t_stop, h_max)
    return False, mode
