"""Settings, tolerances and bookkeeping of the event-driven method.

What the method derives once from its world (:class:`Setup`), the contact mode it holds
between events (:class:`Mode`, with its closed-form :class:`Phase` and candidate collisions
:class:`Candidates`), the state vector of the integrator (:func:`pack`, :func:`unpack`) and the
record of the contact impulses transmitted (:func:`contacts_at`, :func:`accumulate_forces`,
:func:`recorded`, :func:`count_chain`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import ClassVar, NamedTuple

import numpy as np

from feeder_sim.contact.collision import Contacts
from feeder_sim.contact.dynamics import ContactSet, SolverStats
from feeder_sim.model.scene import SolverSpec
from feeder_sim.model.world import State, World
from feeder_sim.stepping.event_driven import _chain as chain
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.protocol import CheckedSettings, StepContacts

# Event functions are scaled to O(1); one fires when it drops below -EVENT_THRESHOLD, so a
# function that starts a phase at zero (a contact that just separated) does not fire on noise.
EVENT_THRESHOLD = 1e-9
GIVE_WAY_S = 1e-9            # first step past an event cascade (s)
GAP_SCALE_M = 1e-3   # gaps fire at -1e-12 m
# A body counts as not turning when its rotation moves its points by less than this fraction of
# the slip tolerance (impacts on a flat leave ~1e-16 m/s of round-off spin) and the held mode
# gives it no angular acceleration beyond round-off (relative to g over its radius).
SPIN_FRACTION = 1e-3
ALPHA_REL = 1e-12
# A contact force below this fraction of the force scale is taken as zero.
FORCE_TOL_REL = 1e-12
# Rows of contact impulses a compiled chain of phases can record; near full, it hands the next
# event back to the general path.
CHAIN_ROWS = 512


@dataclass
class EventSettings(CheckedSettings):
    """Tuning of the event-driven method (SI units); every value is checked when set."""

    LIMITS: ClassVar[dict[str, str]] = {
        'touch_m': '>= 0', 'slip_tol_mps': '>= 0', 'rest_speed_mps': '>= 0', 'lcp_tol': '> 0',
        'max_events_at_one_time': '>= 1', 'cascade_window_s': '>= 0', 'max_give_way_s': '> 0',
        'cascade_memory_s': '>= 0', 'max_events_again': '>= 1'}

    touch_m: float = 1e-9        # a vertex this close to an edge is in contact
    slip_tol_mps: float = 1e-9   # |v_T| below this is sticking
    rest_speed_mps: float = 1e-4  # impacts slower than this are plastic (no Zeno bouncing)
    lcp_tol: float = 1e-9
    max_events_at_one_time: int = 50
    cascade_window_s: float = 1e-6   # events closer than this in time count as one cascade
    max_give_way_s: float = 1e-5     # longest step taken past a persisting cascade
    # a cascade this soon (s) after the last one is the same chatter: it is recognised after
    # max_events_again dense events and its step past keeps growing (quiet steps between
    # bursts spaced by microseconds do not reset it)
    cascade_memory_s: float = 1e-3
    max_events_again: int = 5
    # One dynamic body: follow its closed-form phases through the events its own contacts
    # resolve in compiled code (:mod:`._chain`); False takes each event through the general
    # path (the same answers to round-off, with a return to Python at every event).
    chained: bool = True


@dataclass
class Candidates:
    """Active corners that may enter a nearby piece of another body (collision events)."""

    vertex: np.ndarray        # (c,) global vertex index
    piece: np.ndarray         # (c,) piece the vertex may enter
    arrays: kern.CandidateArrays
    anchor_pos: np.ndarray    # (n, 2) poses at detection
    anchor_ang: np.ndarray    # (n,)
    margin: float             # bounding boxes farther apart than this were left out
    t: float                  # detection time
    # candidates without each held contact set met so far (see without)
    reduced: dict = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        return len(self.vertex)

    def without(self, held: Contacts) -> Candidates:
        """Leave out the corners held on an edge of the piece: they stay on its boundary,
        watched by their own events."""
        if not held.n or not self.n:
            return self
        # The modes of a periodic motion hold the same few contact sets again and again.
        key = (held.vertex_a.tobytes(), held.piece_b.tobytes())
        out = self.reduced.get(key)
        if out is None:
            # contiguous, as the compiled chain passes them: one compile of held_mask
            c = np.ascontiguousarray
            keep = kern.held_mask(c(self.vertex), c(self.piece), c(held.vertex_a),
                                  c(held.piece_b))
            out = self.reduced[key] = Candidates(
                self.vertex[keep], self.piece[keep],
                kern.CandidateArrays(*(x[keep] for x in self.arrays)),
                self.anchor_pos, self.anchor_ang, self.margin, self.t)
        return out


class ContactMaterial(NamedTuple):
    """Each contact's material pair."""

    mu_static: np.ndarray      # (k,)
    mu_dynamic: np.ndarray     # (k,)
    restitution: np.ndarray    # (k,)


@dataclass
class Phase:
    """Kernel arrays of a closed-form phase (see :mod:`._kernels`)."""

    kind: np.ndarray          # (n,) FIXED / DRIVEN / MOVING
    index: np.ndarray         # (n,) drive of a DRIVEN body
    phi0: np.ndarray          # (n, 2) acceleration without drive terms
    phi1: np.ndarray          # (n, 2, nd) acceleration per unit drive acceleration
    drives: kern.Drives
    contacts: kern.HeldContacts   # held contacts with their force coefficients
    f0: np.ndarray            # (2k,) contact forces without drive terms
    f1: np.ndarray            # (2k, nd)


@dataclass
class Mode:
    """The contact mode held during one smooth phase."""

    features: Contacts        # active contacts (geometry at the phase start)
    friction: np.ndarray      # (k,) NONE / STICK / SLIDE
    sigma: np.ndarray         # (k,) slip direction of sliding contacts
    group: np.ndarray         # (k,) parallel-contact group id
    material: ContactMaterial
    held: kern.HeldContacts   # kernel arrays of the held contacts (forces filled by a phase)
    n_events: int             # event functions besides the candidate collisions
    candidates: Candidates | None = None
    phase: Phase | None = None   # closed-form description, if the mode has one
    spec: kern.RhsSpec | None = None   # compiled right-hand side, when integrated and supported
    drive_acc: np.ndarray | None = None   # (n,) largest drive acceleration (m/s^2), once used


@dataclass(frozen=True)
class Setup:
    """What the method derives once from its world, spec and settings."""

    dyn: np.ndarray           # (nd,) dynamic bodies
    radius: np.ndarray        # (n,) m
    length: float             # largest dynamic body's radius, m
    g: float                  # gravity's magnitude, m/s^2
    speed: float              # speed scale of the event functions, m/s
    scale: np.ndarray         # (6 nd,) scale of each state component for error control
    force_scale: float        # force scale of the event functions, N
    slip_tol: float           # |v_T| below this is sticking, m/s (see make_setup)
    verts: np.ndarray         # (V, 2) local vertices
    normals: np.ndarray       # (V, 2) local normals of the edges starting at each vertex
    next_vertex: np.ndarray
    prev_vertex: np.ndarray
    piece_width: np.ndarray   # (P,) m
    vertex_body: np.ndarray
    vertex_piece: np.ndarray
    active_vertex: np.ndarray
    piece_start: np.ndarray
    piece_body: np.ndarray
    materials: tuple          # (n, n) mu_static, mu_dynamic, restitution of body pairs
    no_contacts: kern.HeldContacts
    # (pos, ang, vel, om) scratch of every body for the kernels' answers
    out: tuple
    chained: bool             # one dynamic body: closed-form phases run chained (._chain)
    chain_world: chain.BodyArrays
    chain_geometry: chain.ChainGeometry
    chain_tols: chain.ChainTolerances

    @property
    def scales(self) -> kern.EventScales:
        return kern.EventScales(self.force_scale, self.speed, GAP_SCALE_M)


def make_setup(world: World, spec: SolverSpec, settings: EventSettings) -> Setup:
    """The method's derived constants and arrays for ``world``."""
    dyn = np.flatnonzero(world.dynamic)
    sh = world.shapes
    radius = world.radius
    length = float(np.max(radius[dyn], initial=1e-2))
    g = float(np.linalg.norm(world.gravity)) or 9.81
    speed = math.sqrt(g * length)
    for i in world.driven:
        d = world.drives[i]
        speed = max(speed, 2 * math.pi * d.frequency_hz * d.amplitude_m)
    nd = len(dyn)
    scale = np.concatenate([np.full(2 * nd, length), np.ones(nd),
                            np.full(2 * nd, speed), np.full(nd, speed / length)])
    force_scale = float(np.max(world.mass[dyn] * g, initial=1.0))
    # A slip event fires once sigma v_T / speed is below -EVENT_THRESHOLD, i.e. with the
    # slip already reversed by up to EVENT_THRESHOLD * speed. Below that speed a contact
    # must count as not sliding, or a part too large for the default (metre-sized:
    # speed ~ 3 m/s) is seen sliding back at every reversal, and the mode flips between
    # the two directions every nanosecond without ever testing for sticking.
    slip_tol = max(settings.slip_tol_mps, 2.0 * EVENT_THRESHOLD * speed)
    topo = sh.derived
    verts = np.ascontiguousarray(sh.vertices, dtype=float)
    normals = np.ascontiguousarray(sh.normals, dtype=float)
    none_i, none_f, none_v = np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2))
    no_contacts = kern.HeldContacts(none_i, none_i, none_v, none_v, none_v, none_v, none_f,
                                    np.zeros((0, 0)), none_i, none_f, none_f, none_i, 0)
    out = (np.zeros((world.n, 2)), np.zeros(world.n), np.zeros((world.n, 2)),
           np.zeros(world.n))
    covered = topo.edge_internal | (np.diff(topo.cover_start) > 0)
    chain_geometry = chain.ChainGeometry(
        verts, normals, topo.next_vertex.astype(np.int64), topo.prev_vertex.astype(np.int64),
        np.asarray(sh.piece_start, dtype=np.int64), np.asarray(topo.edge_length, dtype=float),
        np.ascontiguousarray(covered, dtype=np.bool_))
    chain_tols = chain.ChainTolerances(
        event_threshold=EVENT_THRESHOLD, slip_tol_mps=slip_tol, touch_m=settings.touch_m,
        lcp_tol=settings.lcp_tol, cascade_window_s=settings.cascade_window_s,
        spin_limit=SPIN_FRACTION * slip_tol, alpha_limit=ALPHA_REL * g,
        force_tol=force_scale * FORCE_TOL_REL, acc_tol=1e-9 * g, near_m=1e3 * settings.touch_m,
        rest_speed_mps=settings.rest_speed_mps,
        friction_impulse=1.0 if spec.friction_impulse else 0.0)
    chain_world = chain.BodyArrays(
        np.asarray(world.dynamic, dtype=np.bool_), world.inv_mass, world.inv_inertia, radius,
        np.asarray(world.gravity, dtype=float))
    return Setup(
        dyn=dyn, radius=radius, length=length, g=g, speed=speed, scale=scale,
        force_scale=force_scale, slip_tol=slip_tol, verts=verts, normals=normals,
        next_vertex=topo.next_vertex, prev_vertex=topo.prev_vertex,
        piece_width=np.ascontiguousarray(topo.piece_width, dtype=float),
        vertex_body=topo.vertex_body, vertex_piece=topo.vertex_piece,
        active_vertex=np.flatnonzero(topo.vertex_active), piece_start=sh.piece_start,
        piece_body=sh.piece_body, materials=world.pair_materials, no_contacts=no_contacts,
        out=out, chained=nd == 1 and settings.chained, chain_world=chain_world,
        chain_geometry=chain_geometry, chain_tols=chain_tols)


# ------------------------------------------------------------------ state <-> vector
def pack(dyn: np.ndarray, s: State) -> np.ndarray:
    """The integrator's vector of the dynamic bodies: positions, angles, velocities, omegas."""
    return np.concatenate([s.position[dyn].ravel(), s.angle[dyn], s.velocity[dyn].ravel(),
                           s.omega[dyn]])


def unpack(world: World, dyn: np.ndarray, t: float, y: np.ndarray, into: State) -> State:
    """``into`` at time t with the dynamic bodies from ``y`` and the others as prescribed."""
    nd = len(dyn)
    into.t = t
    into.position[dyn] = y[:2 * nd].reshape(nd, 2)
    into.angle[dyn] = y[2 * nd:3 * nd]
    into.velocity[dyn] = y[3 * nd:5 * nd].reshape(nd, 2)
    into.omega[dyn] = y[5 * nd:]
    world.apply_prescribed_motion(into)
    return into


# ------------------------------------------------------------------ record of impulses
def contacts_at(mode: Mode, pos: np.ndarray, ang: np.ndarray) -> ContactSet:
    """The held contacts at the configuration (pos, ang), built without re-detection."""
    f, h = mode.features, mode.held
    point, normal, gap, param = kern.held_geometry(pos, ang, h.body_a, h.body_b, h.vertex,
                                                   h.edge_start, h.edge_end, h.normal)
    c = Contacts(f.body_a, f.piece_a, f.vertex_a, f.body_b, f.piece_b, f.edge_b, point,
                 normal, gap, param)
    return ContactSet(c, normal[:, ::-1] * (-1.0, 1.0), point - pos[f.body_a],
                      point - pos[f.body_b], *mode.material)


def accumulate_forces(pending: list[StepContacts], mode: Mode, f0: np.ndarray, f1: np.ndarray,
                      h: float, state: State) -> None:
    """Impulses of the held contacts over a step (trapezoid rule), ending at ``state``."""
    if not f0.size or not f1.size:
        return
    k = len(f0) // 2
    p = 0.5 * h * (f0 + f1)
    pending.append(StepContacts(contacts_at(mode, state.position, state.angle), p[:k], p[k:]))


def recorded(setup: Setup, state: State, record: chain.ImpulseRecord,
             rows: int) -> StepContacts:
    """The contact impulses a chain of phases recorded, as one report."""
    vertex, edge, a, b, point, normal, p_n, p_t = (x[:rows] for x in record)
    piece = setup.vertex_piece
    mu_s, mu_d, e = setup.materials
    c = Contacts(a, piece[vertex], vertex, b, piece[edge], edge, point, normal,
                 np.zeros(rows), np.full(rows, np.nan))
    return StepContacts(ContactSet(c, normal[:, ::-1] * (-1.0, 1.0),
                                   point - state.position[a], point - state.position[b],
                                   mu_s[a, b], mu_d[a, b], e[a, b]), p_n, p_t)


def count_chain(stats: SolverStats, steps: int, events: int, sums: np.ndarray) -> None:
    """A chain of phases' statistics (``_chain.follow``) into ``stats``."""
    stats.steps += steps
    stats.events += events
    stats.lcp_solves += int(sums[chain.N_LCPS])
    stats.trivial_solves += int(sums[chain.N_TRIVIAL])
    stats.lcp_rows += int(sums[chain.LCP_ROWS])
    stats.max_lcp_rows = max(stats.max_lcp_rows, int(sums[chain.MAX_ROWS]))
    stats.max_residual = max(stats.max_residual, float(sums[chain.MAX_RESIDUAL]))
    stats.max_penetration_m = max(stats.max_penetration_m, float(sums[chain.MAX_PENETRATION]))
    stats.pivots += int(sums[chain.PIVOTS])
    stats.impacts += int(sums[chain.IMPACTS])
    stats.energy_fixes += int(sums[chain.ENERGY_FIXES])
    stats.slip_closures += int(sums[chain.SLIP_CLOSURES])
