"""Contact kinematics shared by the stepping methods: Jacobians, Delassus matrices, islands.

For contact i the vertex body is ``a`` and the edge body is ``b``; ``n`` is the edge's outward
normal (from b toward a) and ``t = perp(n)``. Relative contact velocity ``v = (v_N, v_T)`` is
that of a's vertex with respect to b's material point under it; ``v_N < 0`` approaches.

Rows of every contact LCP are ordered ``[N_0 .. N_{c-1}, T_0 .. T_{c-1}]`` before the friction
rows a scene does not need are dropped (mu = 0, friction off, sliding contacts slaved to their
normal), so a frictionless scene solves a c x c problem, never 2c x 2c.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from feeder_sim.compiled.arena import heap_state
from feeder_sim.contact._island_kernels import island_groups
from feeder_sim.contact.collision import CONTACT_FIELDS, Contacts
from feeder_sim.contact.lcp import FrictionalLCP
from feeder_sim.model.world import cross2, mix, perp, State, World

# friction treatment of one contact row in an LCP
NONE, BOX, SLAVED = 0, 1, 2


@dataclass
class ContactSet:
    """Contacts at one configuration with their lever arms and material."""

    contacts: Contacts
    tangent: np.ndarray     # (k, 2)
    r_a: np.ndarray         # (k, 2) contact point relative to a's centre of mass
    r_b: np.ndarray         # (k, 2)
    mu_static: np.ndarray   # (k,)
    mu_dynamic: np.ndarray  # (k,)
    restitution: np.ndarray  # (k,)

    @property
    def n(self) -> int:
        return self.contacts.n

    def subset(self, idx: np.ndarray) -> ContactSet:
        c = self.contacts
        sub = Contacts(*(getattr(c, f)[idx] for f in CONTACT_FIELDS))
        return ContactSet(sub, self.tangent[idx], self.r_a[idx], self.r_b[idx],
                          self.mu_static[idx], self.mu_dynamic[idx], self.restitution[idx])




def contact_set(world: World, state: State, contacts: Contacts) -> ContactSet:
    a, b = contacts.body_a, contacts.body_b
    return ContactSet(
        contacts=contacts,
        tangent=perp(contacts.normal),
        r_a=contacts.point - state.position[a],
        r_b=contacts.point - state.position[b],
        mu_static=mix(world.mu_static[a], world.mu_static[b], 'friction'),
        mu_dynamic=mix(world.mu_dynamic[a], world.mu_dynamic[b], 'friction'),
        restitution=mix(world.restitution[a], world.restitution[b], 'restitution'),
    )


def friction_rows(cs: ContactSet, v_t: np.ndarray, colliding: np.ndarray, friction_impulse: bool,
                  slip_tol: float, restick: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Friction treatment and bounds (mu_lo, mu_hi) of every contact for an impulse LCP.

    Kawachi's rule: the pre-impact slip ``v_t`` (m/s) picks static (zero slip) or dynamic
    friction, and dynamic friction is one-sided so it cannot reverse the slip. That suits an
    impact, whose free velocities are the pre-impact ones. Over a time step (``restick``)
    gravity and the drives act too, and can carry the slip through zero within the step.
    Where ``mu_static > mu_dynamic`` the side that holds the contact once it has stopped is
    then bounded by ``mu_static``, so a part that comes to rest where static friction can
    hold it, but dynamic friction could not, sticks; ``second_pass`` makes that side
    one-sided again where the slip reverses anyway. (With ``mu_static == mu_dynamic`` the
    one-sided rule already resticks: the reversed slip is stopped in the next step.)
    """
    k = cs.n
    friction = np.full(k, BOX)
    sliding = np.abs(v_t) > slip_tol
    mu = np.where(sliding, cs.mu_dynamic, cs.mu_static)
    hold = np.where(cs.mu_static > cs.mu_dynamic, cs.mu_static, 0.0) if restick else 0.0
    mu_lo = np.where(sliding & (v_t < 0), hold, mu)
    mu_hi = np.where(sliding & (v_t > 0), hold, mu)
    friction[np.maximum(mu_lo, mu_hi) <= 0.0] = NONE
    if not friction_impulse:
        friction[colliding] = NONE
    return friction, mu_lo, mu_hi


def second_pass(lo: np.ndarray, hi: np.ndarray, x_n: np.ndarray, x_t: np.ndarray,
                v_t_new: np.ndarray, mu_static: np.ndarray, mu_dynamic: np.ndarray,
                may_slide: np.ndarray, slip_tol: float, remain: np.ndarray | float = 1.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kawachi's second pass over a step's friction answer: ``(redo, lo, hi)``.

    A contact that slips at the end of the step (``|v_t_new| > slip_tol``, m/s) with its
    impulse ``x_t`` on a bound set by ``mu_static`` slid during the step, so that bound is
    wrong: a static contact driven to its bound slides on with ``mu_dynamic``, one-sided
    against the new slip; a sliding contact whose slip reversed although its holding side
    allowed ``mu_static`` could not stick, and its holding side goes back to Kawachi's
    one-sided 0 (the friction of the step in which a slip reverses is then unbiased:
    ``friction_rows`` without ``restick``). ``may_slide``: contacts with a friction row and
    ``mu_dynamic < mu_static`` (for the others a second pass changes nothing). ``remain``:
    the fraction of the step a contact's static law covers (below 1 where its slip stopped
    within the step, ``_island_kernels.stop_within_step``), which scales its ``mu_dynamic``."""
    held = may_slide & (x_n > 0)
    limit_lo = x_t <= -lo * x_n * (1 - 1e-9)
    limit_hi = x_t >= hi * x_n * (1 - 1e-9)
    static = held & (lo == hi) & (lo > 0) & (limit_lo | limit_hi) \
        & (np.abs(v_t_new) > slip_tol)
    back_hi = held & ~static & (hi == mu_static) & (hi > 0) & limit_hi & (v_t_new < -slip_tol)
    back_lo = held & ~static & (lo == mu_static) & (lo > 0) & limit_lo & (v_t_new > slip_tol)
    lo = np.where(static, np.where(v_t_new > 0, mu_dynamic * remain, 0.0), lo)
    hi = np.where(static, np.where(v_t_new < 0, mu_dynamic * remain, 0.0), hi)
    hi = np.where(back_hi, 0.0, hi)
    lo = np.where(back_lo, 0.0, lo)
    return static | back_hi | back_lo, lo, hi


def islands(world: World, cs: ContactSet) -> list[tuple[np.ndarray, np.ndarray]]:
    """Groups of dynamic bodies that touch each other, with their contacts.

    Static and kinematic bodies do not join islands: their motion is known, so two parts
    touching only the track are solved apart. Returns (bodies, contact indices) per island
    that has at least one contact, islands ordered by their lowest body index, bodies and
    contact indices ascending.
    """
    if cs.n == 0:
        return []
    order, starts, bodies, body_starts = island_groups(heap_state(), world.n, world.dynamic,
                                                       cs.contacts.body_a, cs.contacts.body_b)
    return [(bodies[body_starts[i]:body_starts[i + 1]], order[starts[i]:starts[i + 1]])
            for i in range(len(starts) - 1)]


@dataclass
class IslandJacobian:
    """Contact Jacobian of one island over its dynamic bodies' (vx, vy, omega) columns."""

    bodies: np.ndarray     # (nb,) dynamic body indices, column block order
    J: np.ndarray          # (2c, 3nb) rows N_0..N_{c-1}, T_0..T_{c-1}
    inv_mass: np.ndarray   # (3nb,) diagonal of M^-1

    def delassus(self) -> np.ndarray:
        return (self.J * self.inv_mass) @ self.J.T

    def velocity_change(self, impulse: np.ndarray) -> np.ndarray:
        """(nb, 3) change of (vx, vy, omega) from stacked contact impulses (2c,)."""
        return (self.inv_mass * (self.J.T @ impulse)).reshape(-1, 3)


def island_jacobian(world: World, cs: ContactSet, bodies: np.ndarray) -> IslandJacobian:
    c = cs.contacts
    k = c.n
    col = np.full(world.n, -1)
    col[bodies] = np.arange(len(bodies))
    J = np.zeros((2 * k, 3 * len(bodies)))
    rows = np.arange(k)
    for body, r, sign in ((c.body_a, cs.r_a, 1.0), (c.body_b, cs.r_b, -1.0)):
        cb = col[body]
        m = cb >= 0
        base = 3 * cb[m]
        for direction, row0 in ((c.normal, 0), (cs.tangent, k)):
            rr = rows[m] + row0
            J[rr, base] += sign * direction[m, 0]
            J[rr, base + 1] += sign * direction[m, 1]
            J[rr, base + 2] += sign * cross2(r[m], direction[m])
    inv_mass = np.stack([world.inv_mass[bodies], world.inv_mass[bodies],
                         world.inv_inertia[bodies]], 1).reshape(-1)
    return IslandJacobian(bodies, J, inv_mass)


@dataclass
class Assembly:
    """A contact LCP and the map from its unknowns back to stacked contact impulses."""

    problem: FrictionalLCP
    P: np.ndarray            # (2c, m): impulses_full = P @ x
    friction: np.ndarray     # (c,) NONE / BOX / SLAVED
    box_rows: np.ndarray     # contact index of each BOX friction row
    extra: dict = field(default_factory=dict)

    def full(self, x: np.ndarray) -> np.ndarray:
        return self.P @ x


def assemble(W: np.ndarray, b_full: np.ndarray, friction: np.ndarray, mu_lo: np.ndarray,
             mu_hi: np.ndarray, slave: np.ndarray | None = None) -> Assembly:
    """Build the boxed LCP ``w = A x + b`` from the full 2c x 2c problem.

    ``friction[i]`` decides contact i's tangential unknown: NONE drops it (mu = 0 or friction
    off), BOX keeps a row with bounds ``[-mu_lo x_N, mu_hi x_N]``, SLAVED fixes it to
    ``slave[i] * x_N`` (sliding contact in the force problem) and changes x_N's column instead.
    """
    c = len(friction)
    box = np.flatnonzero(friction == BOX)
    m = c + len(box)
    P = np.zeros((2 * c, m))
    P[np.arange(c), np.arange(c)] = 1.0
    P[c + box, c + np.arange(len(box))] = 1.0
    slaved = np.flatnonzero(friction == SLAVED)
    if len(slaved):
        P[c + slaved, slaved] = slave[slaved]
    rows = np.concatenate([np.arange(c), c + box])
    A = W[rows] @ P
    normal_of = np.concatenate([np.full(c, -1), box])
    lo = np.concatenate([np.zeros(c), mu_lo[box]])
    hi = np.concatenate([np.zeros(c), mu_hi[box]])
    problem = FrictionalLCP(A=A, b=b_full[rows], normal_of=normal_of, mu_lo=lo, mu_hi=hi)
    return Assembly(problem, P, friction, box)

# solver messages a run keeps (the first ones: the counts go on)
MAX_MESSAGES = 20


@dataclass
class SolverStats:
    """Counters every stepping method keeps; written to the run summary."""

    steps: int = 0
    lcp_solves: int = 0
    trivial_solves: int = 0
    pivots: int = 0
    fallbacks: int = 0
    unconverged: int = 0
    max_residual: float = 0.0
    max_penetration_m: float = 0.0
    impacts: int = 0
    events: int = 0
    energy_fixes: int = 0
    cascades: int = 0          # event cascades stepped past (event driven)
    tangential_impacts: int = 0   # Painlevé sliding ended by an impulse (event driven)
    zeno_closures: int = 0     # accumulations of impacts ended at their limit (event driven)
    slip_closures: int = 0     # slips left at a stop, ended by an impulse (event driven)
    frictionless_answers: int = 0  # LCPs whose fallback ladder ended without friction
    unresolved_force_lcps: int = 0  # force LCPs without an answer after the Painlevé impulse
    overlaps_moved_out: int = 0  # parts placed inside a body, moved out (event driven)
    islands: int = 0           # islands with contacts, summed over steps (time stepping)
    pgs_solves: int = 0        # LCPs answered by the large-island projected Gauss-Seidel
    max_pgs_velocity_residual_mps: float = 0.0   # worst PGS answer, m/s (see _island_kernels)
    lcp_rows: int = 0          # rows of the non-trivial LCPs, summed
    max_lcp_rows: int = 0      # rows of the largest non-trivial LCP
    substeps: int = 0          # steps shortened for a pair closing fast (time stepping)
    messages: list = field(default_factory=list)

    def record(self, result) -> None:
        self.lcp_solves += 1
        trivial = result.method == 'trivial'
        self.trivial_solves += trivial
        if not trivial:
            m = len(result.x)
            self.lcp_rows += m
            if m > self.max_lcp_rows:
                self.max_lcp_rows = m
        self.pivots += result.pivots
        self.fallbacks += result.fallbacks
        self.frictionless_answers += result.method == 'frictionless'
        self.unconverged += not result.converged
        self.max_residual = max(self.max_residual, float(result.residual))
        if result.message and len(self.messages) < MAX_MESSAGES:
            self.messages.append(result.message)

    def inexact(self) -> dict[str, str]:
        """What a run must tell its user: per kind of answer that changed the physics, a
        line (empty when every answer was exact)."""
        out = {}
        if self.frictionless_answers:
            out['frictionless'] = (f'{self.frictionless_answers} contact LCPs answered without '
                                   'friction by the last fallback: friction was lost there')
        if self.unresolved_force_lcps:
            out['unresolved'] = (f'{self.unresolved_force_lcps} contact force LCPs without an '
                                 'answer after the Painlevé impulse: the fallback answer used')
        return out

    def record_batch(self, rows: np.ndarray, pivots: np.ndarray, residual: np.ndarray,
                     converged: np.ndarray, method: str) -> None:
        """Several non-trivial answers at once (messages are the caller's business)."""
        n = len(rows)
        if not n:
            return
        self.lcp_solves += n
        self.lcp_rows += int(rows.sum())
        self.max_lcp_rows = max(self.max_lcp_rows, int(rows.max()))
        self.pivots += int(pivots.sum())
        self.unconverged += int(n - np.count_nonzero(converged))
        self.max_residual = max(self.max_residual, float(residual.max()))

    def record_trivial(self, count: int) -> None:
        """``count`` problems answered by x = 0 (every normal row has b >= 0)."""
        self.lcp_solves += count
        self.trivial_solves += count

    def as_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items()}
