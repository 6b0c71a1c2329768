"""``time_stepping``: a velocity-level step with the frictional impulse LCP (throughput method).

Moreau's midpoint scheme: positions move half a step, contacts are found there, one
frictional impulse LCP per island gives the end-of-step velocities, positions move the other
half step with them (Moreau–Jean). In islands solved by pivoting a contact takes part when it
touches at the midpoint or would close its gap by the end of the step, with Newton's law
``v'_N + e min(v_N, 0) >= 0`` on the pre-step approach speed: a fast part stops short of a thin
wall instead of tunnelling. The scheme lets a landing vertex sink by up to ``h |v_N| / 2``;
that penetration is removed by a position projection after the step, never by a velocity
bias, so a landing gains no energy. Piles (islands above ``direct_max_rows``, solved by PGS)
keep speculative rows ``v'_N + 2 gap / h >= 0`` and a velocity push-out of deep penetration.

Friction follows Kawachi: static bounds ``mu_s p_N`` when the pre-step slip is zero; when it
slides, a one-sided bound ``mu_d p_N`` that stops the slip but never reverses it. A static
contact that saturates slides during the step, so it is solved again with ``mu_d``.
Constant-acceleration motion (a block sliding on an incline) is integrated exactly.

Which solver serves which island
--------------------------------
Islands are groups of dynamic bodies joined by contacts (``_kernels.island_groups``); every
island's problem is the ``dynamics.assemble`` layout (normals, then the friction rows kept).

* no normal row with b < 0: zero impulses, counted as a trivial solve (as ``lcp.solve``);
* at most ``direct_max_rows`` (48) rows: Baraff-Dantzig pivoting, exact to ``lcp_tol`` on the
  ``lcp.residual`` scale: ``_kernels.dantzig``, a numba port of ``lcp``'s Dantzig pass (same
  sets, events, tie-breaking, cycling/fold handling, normals-first retry and polish; it takes
  the same pivots as ``lcp.solve`` on the problems checked, and the single box on a vibrating
  track gives the same conveying speed to the last bit). It is 40-100x faster than
  ``lcp.solve`` in Python (4 rows: 0.5 ms -> ~5 us; 30-38 rows: 1.5-5 ms -> 35-150 us). If
  its answer misses ``lcp_tol`` the island is solved again by the reference path
  (``solve_impulses``: ``lcp.solve`` and its Lemke / PGS / frictionless ladder) and counted in
  ``stats.fallbacks``;
* larger islands (piles): projected Gauss-Seidel in velocity form (``_kernels.solve_pgs``,
  SOR factor ``pgs_omega``), warm-started with the previous step's impulses of the same
  vertex-edge features, each normal followed by its friction row. Pivoting does not scale:
  every pivot solves the clamped system, so a pile's 1 070-row island took 1 250 pivots and
  5-7 s in the numba Dantzig, against 1.2-1.5 ms for PGS to 1e-3 m/s. Above ~50 rows one
  Dantzig solve already costs more than a whole step of the pile benchmark. PGS stops when
  its velocity residual, the largest velocity change one more sweep would make
  (``A_ii |x_i - proj(x_i - w_i / A_ii)|``, m/s), is <= ``pgs_tol_mps``, or after
  ``pgs_max_sweeps``; an island that ends above the tolerance counts as unconverged. The
  ``lcp.residual`` of every PGS answer is recorded too (``stats.max_residual``); it is not the
  stopping test because it scales with the island's largest ``|b|`` (the approach speed of
  the fastest landing part). PGS answers are approximate (velocity errors up to
  ``pgs_tol_mps``), which is the usual price of a throughput method for piles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feeder_sim import _kernels as K
from feeder_sim import lcp
from feeder_sim._kernels import island_groups
from feeder_sim.collision import evaluate_gaps, find_contacts
from feeder_sim.dynamics import (
    assemble,
    BOX,
    contact_set,
    ContactSet,
    island_jacobian,
    islands,
    NONE,
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
    touch_m: float = 1e-9          # gap below which a contact is touching
    projection_slop_m: float = 1e-9  # penetration left by the projection (small islands)
    slop_m: float = 1e-7           # penetration tolerated before push-out (piles)
    push_out: float = 0.2          # fraction of that penetration removed per step (piles)
    slip_tol_mps: float = 1e-9     # |v_T| below which a contact is sticking
    lcp_tol: float = 1e-9          # lcp.residual the Dantzig path must reach
    direct_max_rows: int = 48      # islands with more LCP rows go to projected Gauss-Seidel
    pgs_tol_mps: float = 1e-3      # velocity residual (m/s) the PGS path must reach
    pgs_max_sweeps: int = 200
    pgs_check: int = 1             # PGS sweeps between convergence tests
    pgs_omega: float = 1.3         # over-relaxation of the large-island PGS (24 instead of
    #                                33 sweeps per solve in the 200-part pile, same result)


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
                   stats: SolverStats, slip_tol: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Contact impulses (2c,) of one island and the (nb, 3) velocity change they cause.

    The reference path (numpy Delassus matrix, ``lcp.solve`` with its whole fallback
    ladder); ``TimeStepper`` uses it when the numba Dantzig misses ``lcp_tol``. ``b_n`` is
    the constant part of each normal row (free normal velocity plus restitution);
    ``v_t_free`` the free tangential velocity; ``slip_tol`` the slip speed below which a
    contact sticks (default ``settings.slip_tol_mps``).
    """
    jac = island_jacobian(world, cs, bodies)
    W = jac.delassus()
    b_full = np.concatenate([b_n, v_t_free])
    friction, mu_lo, mu_hi = friction_rows(
        cs, v_t_pre, colliding, friction_impulse,
        settings.slip_tol_mps if slip_tol is None else slip_tol)
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


class _Warm:
    """Impulses of the previous step by contact feature (vertex, edge), to warm-start PGS."""

    def __init__(self, n_vertices: int) -> None:
        self.n_vertices = n_vertices
        self.keys = np.zeros(0, np.int64)
        self.p_n = np.zeros(0)
        self.p_t = np.zeros(0)

    def key(self, contacts) -> np.ndarray:
        return contacts.vertex_a.astype(np.int64) * self.n_vertices + contacts.edge_b

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Previous impulses of these features (0 where a feature is new)."""
        if not self.keys.size:
            return np.zeros(keys.size), np.zeros(keys.size)
        pos = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        hit = self.keys[pos] == keys
        return np.where(hit, self.p_n[pos], 0.0), np.where(hit, self.p_t[pos], 0.0)

    def store(self, keys: np.ndarray, p_n: np.ndarray, p_t: np.ndarray) -> None:
        o = np.argsort(keys, kind='stable')
        self.keys, self.p_n, self.p_t = keys[o], p_n[o], p_t[o]


# why a numba Dantzig pass gave up (``_kernels`` abort codes)
_ABORTS = ('', 'pivot cap reached', 'no admissible step', 'non-finite step',
           'invalid end of a drive', 'cycling', 'row-selection budget exhausted',
           'numerical failure')


class TimeStepper:
    """Advances a state by fixed steps of ``spec.time_step``."""

    def __init__(self, world: World, spec: SolverSpec, stats: SolverStats,
                 settings: TimeStepSettings | None = None) -> None:
        self.world = world
        self.spec = spec
        self.stats = stats
        self.settings = settings or TimeStepSettings()
        self._radius = world.radius
        self._dyn = world.dynamic
        self._dyn_idx = np.flatnonzero(self._dyn)
        self._kin_idx = np.flatnonzero(~self._dyn)
        self._driven = world.driven
        self._g = float(np.linalg.norm(world.gravity))
        self._warm = _Warm(len(world.shapes.vertices))
        self._projected = np.zeros(0, bool)

    def margin(self, state: State, h: float) -> float:
        """Distance a vertex can close on any edge in one step (m): contacts to look at."""
        w = self.world
        v = state.velocity
        speed = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]) + np.abs(state.omega) * self._radius
        v_max = float(speed[self._dyn_idx].max(initial=0.0))
        v_kin = float(speed[self._kin_idx].max(initial=0.0))
        for i in self._driven:
            d = w.drives[i]
            v_kin = max(v_kin, 2 * np.pi * d.frequency_hz * d.amplitude_m * 2)
        return 1.5 * h * (v_max + v_kin + self._g * h) + 10 * self.settings.touch_m

    def step(self, state: State, h: float | None = None) -> StepContacts | None:
        """Advance ``state`` in place by h (default: the scene's time step)."""
        w = self.world
        h = self.spec.time_step if h is None else h
        dyn = self._dyn_idx
        t0 = state.t
        mid = state.copy()
        mid.t = t0 + 0.5 * h
        mid.position[dyn] += 0.5 * h * state.velocity[dyn]
        mid.angle[dyn] += 0.5 * h * state.omega[dyn]
        w.apply_prescribed_motion(mid)

        # free end-of-step velocities; driven bodies' positions and velocities at t0 + h
        end = State(t0 + h, mid.position.copy(), mid.angle, mid.velocity.copy(),
                    mid.omega.copy())
        end.velocity[dyn] += h * w.gravity
        w.apply_prescribed_motion(end)

        contacts = find_contacts(w.shapes, mid.position, mid.angle, self._dyn,
                                 margin=self.margin(state, h))
        report = self._contacts(contacts, state, mid, end, h) if contacts.n else None

        state.t = end.t
        state.position[dyn] = mid.position[dyn] + 0.5 * h * end.velocity[dyn]
        state.angle[dyn] = mid.angle[dyn] + 0.5 * h * end.omega[dyn]
        state.velocity[dyn] = end.velocity[dyn]
        state.omega[dyn] = end.omega[dyn]
        drv = self._driven
        state.position[drv] = end.position[drv]
        state.velocity[drv] = end.velocity[drv]
        if report is not None and self._projected.any():
            self._project(report.cs, state, self._projected)
        self.stats.steps += 1
        return report

    def _slip_tol(self, state: State, h: float) -> float:
        """Slip speed below which a contact counts as sticking in a step of h.

        Velocities are evaluated at the midpoint configuration, so the corner of a spinning
        body shows a slip of order omega^2 r h / 2 that is not there; below twice that, static
        friction is the right model (a static contact that cannot hold is solved again as
        sliding, so a real slip is never held back).
        """
        dyn = self._dyn_idx
        spin = float((state.omega[dyn] ** 2 * self._radius[dyn]).max(initial=0.0))
        return max(self.settings.slip_tol_mps, h * spin)

    def _project(self, cs: ContactSet, state: State, mask: np.ndarray) -> None:
        """Move penetrating bodies out along their contact normals; velocities are untouched.

        The midpoint scheme lets a landing vertex sink by up to h |v_N| / 2. Correcting that
        with a velocity bias would inject kinetic energy, so positions are projected instead:
        the smallest mass-weighted move (a frictionless LCP on the normal rows) that brings
        every contact back to within ``slop_m``.
        """
        w, st = self.world, self.settings
        gap, _ = evaluate_gaps(w.shapes, cs.contacts, state.position, state.angle)
        deep = (gap < -st.projection_slop_m) & mask
        if not deep.any():
            return
        for bodies, idx in islands(w, cs):
            if not deep[idx].any():
                continue
            jac = island_jacobian(w, cs.subset(idx), bodies)
            k = len(idx)
            W = jac.delassus()[:k, :k]
            problem = lcp.FrictionalLCP(W, gap[idx] + st.projection_slop_m, np.full(k, -1),
                                        np.zeros(k), np.zeros(k))
            result = lcp.solve(problem, tol=st.lcp_tol)
            self.stats.record(result)
            move = jac.velocity_change(np.concatenate([result.x, np.zeros(k)]))
            state.position[bodies] += move[:, :2]
            state.angle[bodies] += move[:, 2]

    # ---------------------------------------------------------------------------------------

    def _contacts(self, contacts, state: State, mid: State, end: State,
                  h: float) -> StepContacts | None:
        """Solve every island's impulse LCP; adds the velocity changes to ``end``."""
        w, st, stats = self.world, self.settings, self.stats
        cs = contact_set(w, mid, contacts)
        # free end-of-step velocities at the midpoint configuration
        v_n_free, v_t_free = K.contact_velocities(contacts.body_a, contacts.body_b,
                                                  contacts.normal, cs.r_a, cs.r_b,
                                                  end.velocity, end.omega)
        # Small islands (solved exactly by pivoting) use the Moreau-Jean index set: a contact
        # takes part when it touches at the midpoint or would close its gap by the end of the
        # step, under Newton's law, and penetration is removed afterwards by a position
        # projection, so no velocity is spent on it. Piles (islands above direct_max_rows,
        # solved by PGS) keep speculative rows and a velocity push-out, which PGS handles
        # robustly at their size.
        gap = contacts.gap
        order0, starts0, _, _ = island_groups(w.n, self._dyn, contacts.body_a, contacts.body_b)
        size = np.empty(contacts.n, np.int64)
        size[order0] = np.repeat(np.diff(starts0), np.diff(starts0))
        pile = 2 * size > st.direct_max_rows
        keep = np.flatnonzero(pile | (gap <= st.touch_m)
                              | (gap + 0.5 * h * v_n_free <= st.touch_m))
        if not len(keep):
            return None
        if len(keep) < contacts.n:
            contacts, cs = contacts.take(keep), cs.subset(keep)
            v_n_free, v_t_free, gap, pile = (v_n_free[keep], v_t_free[keep], gap[keep],
                                             pile[keep])
        c = contacts
        a, b = c.body_a, c.body_b
        stats.max_penetration_m = max(stats.max_penetration_m, float(-gap.min()))
        v_n_pre, v_t_pre = K.contact_velocities(a, b, c.normal, cs.r_a, cs.r_b,
                                                state.velocity, state.omega)
        touching = gap <= st.touch_m
        colliding = (touching | ~pile) & (v_n_pre < -2.0 * self._g * h)
        newton = v_n_free + cs.restitution * np.minimum(v_n_pre, 0.0)
        push = st.push_out * np.maximum(-gap - st.slop_m, 0.0) * 2.0 / h
        b_n = np.where(~pile, newton,
                       np.where(touching, newton - push, v_n_free + 2.0 * gap / h))
        self._projected = ~pile
        slip_tol = self._slip_tol(state, h)
        friction, mu_lo, mu_hi = friction_rows(cs, v_t_pre, colliding,
                                               self.spec.friction_impulse, slip_tol)
        keys = self._warm.key(c)
        p_n = np.zeros(c.n)
        p_t = np.zeros(c.n)

        order, starts, bodies, body_starts = island_groups(w.n, self._dyn, a, b)
        n_isl = len(starts) - 1
        stats.islands += n_isl
        # an island whose normal rows all have b >= 0 is answered by zero impulses
        b_no = b_n[order]
        neg = np.minimum.reduceat(b_no, starts[:-1]) < 0.0
        stats.record_trivial(n_isl - int(np.count_nonzero(neg)))
        if neg.any():
            failed = self._solve(cs, order, starts, neg, b_no, v_t_free[order],
                                 friction[order] == BOX, mu_lo[order], mu_hi[order],
                                 keys[order], p_n, p_t)
            for i in failed:
                # the numba Dantzig missed the tolerance: the reference path (lcp.solve's
                # whole ladder) solves the island again
                idx = order[starts[i]:starts[i + 1]]
                impulse, _ = solve_impulses(
                    w, cs.subset(idx), bodies[body_starts[i]:body_starts[i + 1]], b_n[idx],
                    v_t_free[idx], v_t_pre[idx], colliding[idx], self.spec.friction_impulse,
                    st, stats, slip_tol)
                p_n[idx], p_t[idx] = impulse[:len(idx)], impulse[len(idx):]
            dv = np.zeros((w.n, 3))
            K.apply_impulses(dv, a, b, c.normal, cs.tangent, cs.r_a, cs.r_b, w.inv_mass,
                             w.inv_inertia, p_n, p_t)
            dyn = self._dyn_idx
            end.velocity[dyn] += dv[dyn, :2]
            end.omega[dyn] += dv[dyn, 2]
        stats.impacts += int(np.count_nonzero(colliding & (p_n > 0)))
        self._warm.store(keys, p_n, p_t)
        return StepContacts(cs, p_n, p_t)

    def _solve(self, cs: ContactSet, order, starts, todo, b_n, b_t, box, lo, hi, keys, p_n,
               p_t) -> np.ndarray:
        """Islands with ``todo`` (the non-trivial ones): small ones by the numba Dantzig,
        large ones by PGS, each followed by Kawachi's second pass where a static contact
        saturated. Arrays b_n .. keys are in island order (``order``). Writes p_n / p_t and
        returns the islands whose Dantzig answer missed ``lcp_tol``."""
        w, st, stats = self.world, self.settings, self.stats
        c = cs.contacts
        data = (starts, c.body_a[order], c.body_b[order], c.normal[order], cs.tangent[order],
                cs.r_a[order], cs.r_b[order], w.inv_mass, w.inv_inertia, b_n, b_t, box)
        lens = np.diff(starts)
        isl = np.repeat(np.arange(len(lens)), lens)
        x_n, x_t = self._warm.lookup(keys)
        x_n[~todo[isl]] = 0.0           # trivial islands: zero impulses, not last step's
        x_t[~todo[isl]] = 0.0
        mu_d, mu_s = cs.mu_dynamic[order], cs.mu_static[order]
        rows = lens + np.add.reduceat(box, starts[:-1])
        small = todo & (rows <= st.direct_max_rows)
        large = todo & ~small
        v_t_new = np.zeros(len(b_n))
        failed = np.zeros(len(lens), bool)
        for _ in range(2):
            if small.any():
                res, work, codes = K.solve_small(small, *data, lo, hi, x_n, x_t, v_t_new)
                bad = small & (res > st.lcp_tol)
                ok = small & ~bad
                stats.record_batch(rows[ok], work[ok], res[ok], np.ones(ok.sum(), bool),
                                   'dantzig')
                failed |= bad
                for i in np.flatnonzero(bad):
                    stats.fallbacks += 1
                    if len(stats.messages) < 20:
                        stats.messages.append(_dantzig_message(res[i], codes[i]))
            if large.any():
                res, vres, work = K.solve_pgs(large, *data, lo, hi, x_n, x_t, v_t_new,
                                              np.zeros((w.n, 3)), st.pgs_tol_mps,
                                              st.pgs_max_sweeps, st.pgs_check, st.pgs_omega)
                conv = vres[large] <= st.pgs_tol_mps
                stats.record_batch(rows[large], work[large], res[large], conv, 'pgs')
                stats.pgs_solves += int(large.sum())
                stats.max_pgs_velocity_residual_mps = max(
                    stats.max_pgs_velocity_residual_mps, float(vres[large].max()))
                for i in np.flatnonzero(large)[~conv]:
                    if len(stats.messages) < 20:
                        stats.messages.append(
                            f'pgs: velocity residual {vres[i]:.3g} m/s (lcp residual '
                            f'{res[i]:.3g}) after {work[i]} sweeps ({rows[i]} rows)')
            # A static contact driven to its bound slides within the step: from then on the
            # dynamic coefficient acts, one-sided in the direction the contact now slips.
            solved = (small | large)[isl] & ~failed[isl]
            saturated = box & (lo == hi) & (lo > 0) & (np.abs(x_t) >= lo * x_n * (1 - 1e-9)) \
                & (x_n > 0) & (np.abs(v_t_new) > st.slip_tol_mps) & (mu_d < mu_s) & solved
            if not saturated.any():
                break
            again = np.zeros(len(lens), bool)
            again[isl[saturated]] = True
            small, large = small & again, large & again
            lo = np.where(saturated, np.where(v_t_new > 0, mu_d, 0.0), lo)
            hi = np.where(saturated, np.where(v_t_new < 0, mu_d, 0.0), hi)
        p_n[order] = x_n
        p_t[order] = x_t
        return np.flatnonzero(failed)


def _dantzig_message(residual: float, codes) -> str:
    msg = f'dantzig (numba): {_ABORTS[codes[0]] or f"residual {residual:.3g}"}'
    if codes[1]:
        msg += f'; normals-first retry: {_ABORTS[codes[1]]}'
    return msg + '; solved again by lcp.solve'
