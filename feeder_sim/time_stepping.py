"""``time_stepping``: a velocity-level step with the frictional impulse LCP (throughput method).

Moreau's midpoint scheme: positions move half a step, contacts are found there, one
frictional impulse LCP per island gives the end-of-step velocities, positions move the other
half step with them. Contact rows are

* touching contacts (gap <= ``touch_m``): ``v'_N + e min(v_N, 0) >= 0`` — Newton restitution on
  the pre-step approach speed, with a gentle push-out of penetration deeper than ``slop_m``;
* speculative contacts (gap > ``touch_m``): ``v'_N + 2 gap / h >= 0`` — the vertex may close the
  gap during the step but not cross the edge, so fast parts do not tunnel through thin walls.

Friction follows Kawachi: static bounds ``mu_s p_N`` when the pre-step slip is zero; when it
slides, a one-sided bound ``mu_d p_N`` that stops the slip but never reverses it. A static
contact that saturates slides during the step, so it is solved again with ``mu_d``.
Constant-acceleration motion (a block sliding on an incline) is integrated exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feeder_sim import lcp
from feeder_sim.collision import find_contacts
from feeder_sim.dynamics import (
    assemble,
    BOX,
    contact_set,
    ContactSet,
    island_jacobian,
    islands,
    NONE,
    relative_velocity,
    SolverStats,
)
from feeder_sim.scene import SolverSpec
from feeder_sim.world import State, World


@dataclass
class StepContacts:
    """Contacts of one step and the impulses (N s) they transmitted."""

    cs: ContactSet
    normal_impulse: np.ndarray
    tangent_impulse: np.ndarray


@dataclass
class TimeStepSettings:
    touch_m: float = 1e-9          # gap below which a contact is touching, not speculative
    slop_m: float = 1e-7           # penetration tolerated before push-out
    push_out: float = 0.2          # fraction of the penetration beyond slop removed per step
    slip_tol_mps: float = 1e-9     # |v_T| below which a contact is sticking
    lcp_tol: float = 1e-9


def friction_rows(cs: ContactSet, v_t: np.ndarray, colliding: np.ndarray, friction_impulse: bool,
                  slip_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Friction treatment and bounds (mu_lo, mu_hi) of every contact for an impulse LCP.

    Kawachi's rule: the pre-impact slip picks static (zero slip) or dynamic friction, and
    dynamic friction is one-sided so it cannot reverse the slip.
    """
    k = cs.n
    friction = np.full(k, BOX)
    sliding = np.abs(v_t) > slip_tol
    mu = np.where(sliding, cs.mu_dynamic, cs.mu_static)
    friction[mu <= 0.0] = NONE
    if not friction_impulse:
        friction[colliding] = NONE
    mu_lo = np.where(sliding & (v_t < 0), 0.0, mu)
    mu_hi = np.where(sliding & (v_t > 0), 0.0, mu)
    return friction, mu_lo, mu_hi


def solve_impulses(world: World, cs: ContactSet, bodies: np.ndarray, b_n: np.ndarray,
                   v_t_free: np.ndarray, v_t_pre: np.ndarray, colliding: np.ndarray,
                   friction_impulse: bool, settings: TimeStepSettings,
                   stats: SolverStats) -> tuple[np.ndarray, np.ndarray]:
    """Contact impulses (2c,) of one island and the (nb, 3) velocity change they cause.

    ``b_n`` is the constant part of each normal row (free normal velocity plus restitution or
    gap terms); ``v_t_free`` the free tangential velocity.
    """
    jac = island_jacobian(world, cs, bodies)
    W = jac.delassus()
    b_full = np.concatenate([b_n, v_t_free])
    friction, mu_lo, mu_hi = friction_rows(cs, v_t_pre, colliding, friction_impulse,
                                           settings.slip_tol_mps)
    impulse = None
    for _ in range(2):
        asm = assemble(W, b_full, friction, mu_lo, mu_hi)
        result = lcp.solve(asm.problem, tol=settings.lcp_tol)
        stats.record(result)
        impulse = asm.full(result.x)
        # A static contact driven to its bound slides within the step: from then on the
        # dynamic coefficient acts, one-sided in the direction the contact now slips.
        c = cs.n
        p_n, p_t = impulse[:c], impulse[c:]
        v_t_new = v_t_free + (W @ impulse)[c:]
        static = (friction == BOX) & (mu_lo == mu_hi) & (mu_lo > 0)
        saturated = static & (np.abs(p_t) >= mu_lo * p_n * (1 - 1e-9)) & (p_n > 0) \
            & (np.abs(v_t_new) > settings.slip_tol_mps) & (cs.mu_dynamic < cs.mu_static)
        if not saturated.any():
            break
        mu_lo = np.where(saturated, np.where(v_t_new > 0, cs.mu_dynamic, 0.0), mu_lo)
        mu_hi = np.where(saturated, np.where(v_t_new < 0, cs.mu_dynamic, 0.0), mu_hi)
    return impulse, jac.velocity_change(impulse)


class TimeStepper:
    """Advances a state by fixed steps of ``spec.time_step``."""

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: TimeStepSettings | None = None) -> None:
        self.world = world
        self.spec = spec
        self.stats = stats
        self.settings = settings or TimeStepSettings()
        self._radius = np.zeros(world.n)
        np.maximum.at(self._radius, world.shapes.piece_body, world.shapes.radius)

    def margin(self, state: State, h: float) -> float:
        """Distance a vertex can close on any edge in one step (m), for speculative contacts."""
        w = self.world
        speed = np.linalg.norm(state.velocity, axis=1) + np.abs(state.omega) * self._radius
        v_max = float(np.max(speed[w.dynamic], initial=0.0))
        v_kin = float(np.max(speed[~w.dynamic], initial=0.0))
        for i in w.driven:
            d = w.drives[i]
            v_kin = max(v_kin, 2 * np.pi * d.frequency_hz * d.amplitude_m * 2)
        g_h = float(np.linalg.norm(w.gravity)) * h
        return 1.5 * h * (v_max + v_kin + g_h) + 10 * self.settings.touch_m

    def step(self, state: State, h: float | None = None) -> StepContacts | None:
        """Advance ``state`` in place by h (default: the scene's time step)."""
        w, st = self.world, self.settings
        h = self.spec.time_step if h is None else h
        dyn = w.dynamic
        t0 = state.t
        mid = state.copy()
        mid.t = t0 + 0.5 * h
        mid.position[dyn] += 0.5 * h * state.velocity[dyn]
        mid.angle[dyn] += 0.5 * h * state.omega[dyn]
        w.apply_prescribed_motion(mid)

        end = mid.copy()           # velocities: free end-of-step, kinematic at t0 + h
        end.t = t0 + h
        end.velocity[dyn] += h * w.gravity
        w.apply_prescribed_motion(end)
        pre = mid.copy()           # velocities at t0 in the midpoint configuration
        pre.velocity, pre.omega = state.velocity.copy(), state.omega.copy()

        contacts = find_contacts(w.shapes, mid.position, mid.angle, dyn,
                                 margin=self.margin(state, h))
        report = None
        if contacts.n:
            cs = contact_set(w, mid, contacts)
            gap = contacts.gap
            self.stats.max_penetration_m = max(self.stats.max_penetration_m,
                                               float(np.max(-gap, initial=0.0)))
            v_n_pre, v_t_pre = relative_velocity(cs, pre)
            v_n_free, v_t_free = relative_velocity(cs, end)
            touching = gap <= st.touch_m
            g_acc = np.linalg.norm(w.gravity) * h
            colliding = touching & (v_n_pre < -2.0 * g_acc)
            push = st.push_out * np.maximum(-gap - st.slop_m, 0.0) * 2.0 / h
            b_n = np.where(touching,
                           v_n_free + cs.restitution * np.minimum(v_n_pre, 0.0) - push,
                           v_n_free + 2.0 * gap / h)
            p_n = np.zeros(contacts.n)
            p_t = np.zeros(contacts.n)
            for bodies, idx in islands(w, cs):
                sub = cs.subset(idx)
                impulse, dv = solve_impulses(
                    w, sub, bodies, b_n[idx], v_t_free[idx], v_t_pre[idx], colliding[idx],
                    self.spec.friction_impulse, st, self.stats)
                end.velocity[bodies] += dv[:, :2]
                end.omega[bodies] += dv[:, 2]
                p_n[idx], p_t[idx] = impulse[:len(idx)], impulse[len(idx):]
            self.stats.impacts += int(np.count_nonzero(colliding & (p_n > 0)))
            report = StepContacts(cs, p_n, p_t)

        state.t = end.t
        state.position[dyn] = mid.position[dyn] + 0.5 * h * end.velocity[dyn]
        state.angle[dyn] = mid.angle[dyn] + 0.5 * h * end.omega[dyn]
        state.velocity[dyn] = end.velocity[dyn]
        state.omega[dyn] = end.omega[dyn]
        w.apply_prescribed_motion(state)
        self.stats.steps += 1
        return report
