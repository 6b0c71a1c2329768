"""``time_stepping``: a velocity-level step with the frictional impulse LCP (throughput method).

Moreau's midpoint scheme: positions move half a step, contacts are found there, one
frictional impulse LCP per island gives the end-of-step velocities, positions move the other
half step with them (Moreau–Jean). In islands solved by pivoting a contact takes part when it
touches at the midpoint or would close its gap by the end of the step, with Newton's law
``v'_N + e min(v_N, 0) >= 0`` on the pre-step approach speed. Contacts are found again only at
the next midpoint, a whole step of travel later, so a contact of these islands that is within
that reach but does not close by the end of the step gets a speculative row
``v'_N + (gap + allow) / h >= 0``: its vertex sinks at most ``allow`` (half the narrow phase's
depth window, ``speculative_depth`` x ``collision.DEPTH_FRACTION`` x the thinner piece) by the
next midpoint, where the contact is then found on the face it entered. Without it a part that
moves further than a thin wall's half thickness per step (10 mm per step at a 1 mm wall) is
next seen past the wall's mid-plane, matched to its far face or missed, and goes through. The
row is only set up where ``gap + allow`` is within the reach, so slow parts, whose reach is far
below ``allow``, get no such row. The scheme lets a landing vertex sink by
up to ``h |v_N| / 2``; that penetration is removed by a position projection after the step,
never by a velocity bias, so a landing gains no energy. Both the depth a vertex reaches by the
midpoint and the gap from which a closing contact acts are at most half a step's approach, so
a step in which a pair of pieces could close by more than ``substep_depth`` x
``collision.DEPTH_FRACTION`` x the thinner piece in half a step is shortened first
(``_kernels.safe_step_inline``, counted in ``stats.substeps``): a part thrown at
1 000 m/s at a 1 um foil stops on its face at dt = 1 ms, and no contact acts from further than
that share of the thinner piece (``test_fast_parts.py``). The projection respects every
contact of the step outside piles, also those left out of the impulse problem, and moves no
point of a body more than twice its island's summed overlap. Piles (islands above
``direct_max_rows``, solved by PGS) keep speculative rows ``v'_N + 2 gap / h >= 0`` and a
velocity push-out of deep penetration, capped at ``push_max_mps`` (a jammed queue left 0.4 mm
deep was otherwise kicked at 0.8 m/s).

Friction follows Kawachi: static bounds ``mu_s p_N`` when the pre-step slip is zero; when it
slides, a one-sided bound ``mu_d p_N`` against the slip. Gravity and the drives act during the
step, so a slip can stop within it; Coulomb's law then holds it with ``mu_d`` up to that
instant and by the static law after it. In islands solved by pivoting the first answer tells
where the slip would stop (``_island_kernels.stop_within_step``: the slip falls linearly over
the step); the step is solved again with the slide's impulse ``-sigma mu_d phi p_N`` applied
and the rest of the step ``1 - phi`` under the static law from rest, so a slip that reverses
at a drive's turning point slides on with ``mu_d`` the other way, and one that can be held
sticks (``mu_s``, where ``mu_s > mu_d``). On that first answer the side that holds a contact
once it has stopped is bounded by ``mu_s p_N`` (``dynamics.friction_rows(restick=True)``),
which is also the law of piles (PGS islands). Kawachi's second pass
(``dynamics.second_pass``) solves an island again where a static bound was reached by a
contact that slips at the end of the step: it slides, one-sided with ``mu_d`` (times the
part of the step after its stop); in piles a sliding contact whose slip reverses although
``mu_s`` could hold it is one-sided again, as without the holding side.
Constant-acceleration motion (a block sliding on an incline) is integrated exactly.

Which solver serves which island
--------------------------------
Islands are groups of dynamic bodies joined by contacts (``_island_kernels.island_groups``); every
island's problem is the ``dynamics.assemble`` layout (normals, then the friction rows kept).

* no normal row with b < 0: zero impulses, counted as a trivial solve (as ``lcp.solve``);
* at most ``direct_max_rows`` (48) rows: Baraff-Dantzig pivoting, exact to ``lcp_tol`` on the
  ``lcp.residual`` scale: ``_lcp_kernels.dantzig``, a numba port of ``lcp``'s Dantzig pass (same
  sets, events, tie-breaking, cycling/fold handling, normals-first retry and polish; it takes the
  same pivots as ``lcp.solve`` on the problems checked, and the single box on a vibrating track
  gives the same conveying speed to the last bit). Compiled, it spares every pivot the Python
  bookkeeping of ``lcp.solve``, which would outweigh the rest of a small island's step
  (measured by ``benchmarks/throughput.py``). If its answer misses ``lcp_tol`` the island
  is solved again by the reference path (``solve_impulses``: ``lcp.solve`` and its Lemke /
  PGS / frictionless ladder) and counted in ``stats.fallbacks``. An island
  whose contacts all ended the step before in known row states is first solved in those
  states in one piece (``_lcp_kernels.solve_with_states``, the Dantzig pass's final polish;
  ``reuse_row_states``) and that answer is taken if its ``lcp.residual`` is <= 1e-12: a part
  resting or sliding as it did costs one small solve instead of its pivots (one part
  conveying at dt = 1e-4: about 0.4 pivots per step instead of 2). The position projection's
  islands (normal rows only) likewise start from the row states their contacts ended their
  last projection in (one part hopping at dt = 1e-4: 0.04 pivots per step in all instead of
  0.43). It is an answer of the same LCP; where the LCP has one, Dantzig's to round-off;
* larger islands (piles): projected Gauss-Seidel in velocity form
  (``_island_kernels.solve_pgs``, SOR factor ``pgs_omega``), warm-started with the previous
  step's impulses of the same vertex-edge features, each normal followed by its friction row, an
  island's contacts bottom-up (by height along gravity: consecutive rows then mostly belong to
  parts side by side, not to one body whose new velocity each must wait for; the sort pays
  for itself in piles solved to the tolerance, not in those stopped at 10 sweeps, of whose
  solve it is a larger share: ``benchmarks/throughput.py`` runs both), and every
  ``pgs_check`` sweeps a step of Silcowitz, Niebe and Erleben's nonsmooth nonlinear conjugate
  gradient (``pgs_momentum``; Silcowitz-Hansen, Niebe, Erleben, "A nonsmooth nonlinear conjugate
  gradient method for interactive contact force problems", The Visual Computer 26, 2010): the
  impulses move on along the previous direction, scaled by the ratio of the last two sweeps'
  squared changes, and are projected back into their bounds. With these steps the 200-part
  pile of ``benchmarks/throughput.py`` needs about 39 sweeps per solve instead of 62, the
  islands of its 1000-part pile 360-510 instead of 740-1 100, and a tight tolerance (1e-8 m/s)
  five to ten times fewer sweeps. Pivoting does not scale: every pivot solves the clamped
  system, so a 1 070-row island of a pile needs 1 250 pivots, each a solve of up to that
  many rows, where a PGS sweep is one pass over them. Above ~50 rows one Dantzig solve
  already costs more than a whole step of ``benchmarks/pile.py``. PGS stops when its
  velocity residual, the largest velocity change one more sweep would make (``A_ii |x_i -
  proj(x_i - w_i / A_ii)|``, m/s), is <= ``pgs_tol_mps``, or after ``pgs_max_sweeps``; an island
  that ends above the tolerance counts as unconverged. The ``lcp.residual`` of every PGS answer
  is recorded too (``stats.max_residual``); it is not the stopping test because it scales with
  the island's largest ``|b|`` (the approach speed of the fastest landing part). PGS answers are
  approximate (velocity errors up to ``pgs_tol_mps``), which is the usual price of a throughput
  method for piles.

Compiled paths and their references
-----------------------------------
``TimeStepper.advance`` runs whole steps in ``_kernels.advance``, many per call,
with the operations of ``TimeStepper.step`` in the same order: the same bits, frames, counters
and contact reports (test/stepping/test_pile.py, test/test_fingerprint.py). ``step`` stays as the
reference and takes the steps the kernel hands back: a Dantzig answer missing ``lcp_tol``
(the reference solves it again through ``lcp.solve``'s ladder and counts the fallback),
non-finite bounds (its error). The velocities speculative rows held back for restitution
(``_approach``) go into the kernel and come back with the warm start.
``TimeStepSettings(compiled=False)`` runs the reference alone.

The kernel's steps make no numpy allocation: their scratch arrays come from two arenas
(``feeder_sim.compiled.arena``) sized from the scene's vertex count and doubled when a step
needed more (that step is served from the heap meanwhile, with the same bits), and the arrays it
is given are borrowed, so no reference is counted along the way.

Within ``step``, the per-contact set-up (index set, Newton / push-out rows, Kawachi's bounds)
is ``_island_kernels.contact_rows``, with the bits of the numpy code it replaced
(``_contact_rows_reference``); the position projection of the small islands solves their
normal-row LCPs together with the compiled Dantzig (``_island_kernels.solve_small``),
``lcp.solve`` only for an island it cannot solve, where ``_project_reference`` solves each
island by ``lcp.solve`` with numpy Jacobians (same problems and pivots, positions within
~1e-18 m: the sums run in another order). test/stepping/test_pile.py checks both while a pile
falls and settles, and the PGS sweep against a plain transcription of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from feeder_sim.compiled.arena import grown_capacity, heap_state, new_arena, SHORT
from feeder_sim.contact import _island_kernels as K
from feeder_sim.contact import lcp
from feeder_sim.contact._collision_kernels import NarrowPhaseTolerances
from feeder_sim.contact._island_kernels import island_groups
from feeder_sim.contact.collision import (
    ANGLE_TOL,
    CONTACT_FIELDS,
    Contacts,
    DEPTH_FRACTION,
    evaluate_gaps,
    find_contacts,
    PARAM_TOL,
    TIE_REL,
)
from feeder_sim.contact.dynamics import (
    assemble,
    BOX,
    contact_set,
    ContactSet,
    friction_rows,
    island_jacobian,
    islands,
    MAX_MESSAGES,
    second_pass,
    SolverStats,
)
from feeder_sim.model.arrays import body_arrays, shape_arrays
from feeder_sim.model.world import State, World
from feeder_sim.stepping.protocol import CheckedSettings, StepContacts, StepperBase
from feeder_sim.stepping.time_stepping import _kernels as TK

# First size of each scratch arena of the compiled step (bytes): a single part's step needs
# ~20 kB; a pile's step ~1 kB per vertex. A step that needs more grows them for the next call.
_ARENA_BYTES = 64 * 1024
_ARENA_BYTES_PER_VERTEX = 1024


@dataclass
class TimeStepSettings(CheckedSettings):
    """Tuning of the time-stepping method (SI units); every value is checked when set."""

    LIMITS: ClassVar[dict[str, str]] = {
        'touch_m': '>= 0', 'projection_slop_m': '>= 0', 'projection_reach': '> 0',
        'slop_m': '>= 0', 'push_out': '[0, 1]', 'push_max_mps': '>= 0',
        'speculative_depth': '>= 0', 'substep_depth': '(0, 1]', 'slip_tol_mps': '>= 0',
        'lcp_tol': '> 0',
        'direct_max_rows': '>= 0', 'pgs_tol_mps': '>= 0', 'pgs_max_sweeps': '>= 1',
        'pgs_check': '>= 1', 'pgs_omega': '(0, 2)'}

    touch_m: float = 1e-9          # gap below which a contact is touching
    projection_slop_m: float = 1e-9  # penetration left by the projection (small islands)
    projection_reach: float = 2.0  # no point of a body moves more than this times the summed
    #                                penetration of its island in one projection: a wedged
    #                                part makes the normal rows nearly dependent and the
    #                                linearised move unbounded (a cup thrown 39 mm / 415 deg
    #                                by a 0.06 mm overlap); what is left goes next step
    slop_m: float = 1e-7           # penetration tolerated before push-out (piles)
    push_out: float = 0.2          # fraction of that penetration removed per step (piles)
    push_max_mps: float = 0.02     # cap on the push-out speed (piles): it stays in the
    #                                velocities, so uncapped a deep wedge (1/h times its depth)
    #                                throws parts apart
    speculative_depth: float = 0.5  # small islands: a contact that does not touch or close
    #                                by the end of the step may still close by the next
    #                                midpoint, where contacts are found again; its approach is
    #                                capped so that its vertex then sinks at most this
    #                                fraction of the narrow phase's depth window
    #                                (collision.DEPTH_FRACTION x the thinner piece): deeper,
    #                                a thin wall's vertex is matched to its far face or missed
    substep_depth: float = 0.5     # a step is shortened where a vertex could move more than
    #                                this fraction of the depth window relative to a piece it
    #                                is about to meet in half a step (fast parts, thin walls;
    #                                counted in stats.substeps): no contact then acts from
    #                                further away, nor does a vertex sink deeper, by the midpoint
    slip_tol_mps: float = 1e-9     # |v_T| below which a contact is sticking
    lcp_tol: float = 1e-9          # lcp.residual the Dantzig path must reach
    reuse_row_states: bool = True  # a small island whose contacts all come with the row
    #                                states of the step before (the projection: of their
    #                                last projection) is solved in those states in one
    #                                piece when that solves it (residual <= 1e-12);
    #                                False: Baraff-Dantzig from scratch every step
    direct_max_rows: int = 48      # islands with more LCP rows go to projected Gauss-Seidel
    pgs_tol_mps: float = 1e-3      # velocity residual (m/s) the PGS path must reach
    pgs_max_sweeps: int = 200
    pgs_check: int = 2             # PGS sweeps between convergence tests (and NNCG steps)
    compiled: bool = True          # whole steps in _kernels.advance; False: the
    #                                Python reference, step by step
    pgs_omega: float = 1.3         # over-relaxation of the large-island PGS (24 instead of
    #                                33 sweeps per solve in the 200-part pile, same result)
    pgs_momentum: bool = True      # a conjugate gradient step after each check (NNCG)


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
        settings.slip_tol_mps if slip_tol is None else slip_tol, restick=True)
    box = friction == BOX
    may_slide = box & (cs.mu_dynamic < cs.mu_static)
    # the stop within the step as TimeStepper._solve takes it
    c = cs.n
    sliding = box & (mu_lo != mu_hi) & ~colliding.any()
    offset, remain = np.zeros(c), np.ones(c)
    b_n, b_t = b_full[:c].copy(), b_full[c:].copy()
    impulse = None
    for attempt in range(3):
        asm = assemble(W, np.concatenate([b_n, b_t]), friction, mu_lo, mu_hi)
        result = lcp.solve(asm.problem, tol=settings.lcp_tol)
        stats.record(result)
        impulse = asm.full(result.x)
        v_t_new = b_t + (W @ impulse)[c:]
        if attempt == 2:
            break
        stopped = False
        if attempt == 0 and sliding.any():
            contacts = cs.contacts
            # one island of all the contacts (the mid-step velocities are not read here)
            rows = K.IslandRows(np.array([0, c]), contacts.body_a, contacts.body_b,
                                np.ascontiguousarray(contacts.normal), cs.tangent, cs.r_a,
                                cs.r_b, world.inv_mass, world.inv_inertia)
            slip_state = K.StepSlip(np.ascontiguousarray(v_t_pre), sliding, np.zeros((0, 2)),
                                    np.zeros(0), b_t, cs.mu_static, cs.mu_dynamic, offset,
                                    remain)
            stopped = K.stop_within_step(
                heap_state(), np.ones(1, bool), rows, K.RowProblem(b_n, b_t, box, mu_lo, mu_hi),
                K.RowImpulses(impulse[:c].copy(), impulse[c:].copy(), v_t_new), slip_state)[0]
        saturated, mu_lo, mu_hi = second_pass(mu_lo, mu_hi, impulse[:c], impulse[c:], v_t_new,
                                              cs.mu_static, cs.mu_dynamic,
                                              may_slide & ((remain < 1.0) == attempt),
                                              settings.slip_tol_mps, remain)
        if not (stopped or saturated.any()):
            break
    impulse[c:] += offset
    return impulse, jac.velocity_change(impulse)


class _Warm:
    """Impulses of the previous step by contact feature (vertex, edge), to warm-start PGS,
    and the row states of each contact's small-island answers, to solve its island again in
    one piece (``_island_kernels.solve_small``; -1: none): its velocity solve's, and its last
    position projection's (carried on while the contact is not projected)."""

    def __init__(self, n_vertices: int) -> None:
        self.n_vertices = n_vertices
        self.keys = np.zeros(0, np.int64)
        self.p_n = np.zeros(0)
        self.p_t = np.zeros(0)
        self.state = np.zeros(0, np.int64)
        self.projection_state = np.zeros(0, np.int64)

    def key(self, contacts) -> np.ndarray:
        return contacts.vertex_a.astype(np.int64) * self.n_vertices + contacts.edge_b

    def _find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where these features are in the table, and which are there at all."""
        pos = np.minimum(np.searchsorted(self.keys, keys), max(self.keys.size - 1, 0))
        return pos, (self.keys[pos] == keys if self.keys.size else np.zeros(keys.size, bool))

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Previous impulses and row states of these features (0 and -1 where one is new)."""
        if not self.keys.size:
            return np.zeros(keys.size), np.zeros(keys.size), np.full(keys.size, -1)
        pos, hit = self._find(keys)
        return (np.where(hit, self.p_n[pos], 0.0), np.where(hit, self.p_t[pos], 0.0),
                np.where(hit, self.state[pos], -1))

    def projection_states(self, keys: np.ndarray) -> np.ndarray:
        """The row states of these features' last projection (-1: none)."""
        if not self.keys.size:
            return np.full(keys.size, -1)
        pos, hit = self._find(keys)
        return np.where(hit, self.projection_state[pos], -1)

    def store(self, keys: np.ndarray, p_n: np.ndarray, p_t: np.ndarray,
              state: np.ndarray) -> None:
        projection = self.projection_states(keys)
        o = np.argsort(keys, kind='stable')
        self.keys, self.p_n, self.p_t, self.state = keys[o], p_n[o], p_t[o], state[o]
        self.projection_state = projection[o]

    def store_projection(self, keys: np.ndarray, states: np.ndarray) -> None:
        """The row states a projection ended in, of those of ``keys`` in the table."""
        pos, hit = self._find(keys)
        self.projection_state[pos[hit]] = states[hit]


# Gathering rows of (k, 2) arrays by an index array: ``ndarray.take(i, axis=0)`` copies the same
# values as ``a[i]`` with far less work per row (numpy's fancy indexing walks a 2-element
# subspace per row), and ``compress`` / ``np.add(..., where=)`` likewise do less than boolean
# and fancy indexing. A pile step gathers ~40 such arrays of hundreds of contacts, so the way of
# indexing shows in its cost.


def cap_moves(move: np.ndarray, radius_m: np.ndarray, limit_m) -> np.ndarray:
    """``move`` ((n, 3) rows of dx, dy, dangle) with each row scaled down so that no point of
    its body (of bounding ``radius_m``) travels more than ``limit_m``."""
    reach = np.hypot(move[:, 0], move[:, 1]) + np.abs(move[:, 2]) * radius_m
    scale = np.minimum(1.0, limit_m / np.maximum(reach, 1e-300))
    return move * scale[:, None]


def _take(contacts: Contacts, index: np.ndarray) -> Contacts:
    """``contacts.take(index)`` (the same arrays) by ``ndarray.take``."""
    return Contacts(*(getattr(contacts, f).take(index, axis=0) for f in CONTACT_FIELDS))


class _IslandGeometry:
    """The islands of one contact set (``island_groups``) and its contacts' kinematics in
    island order: what the island kernels share (``rows``, an ``IslandRows``)."""

    def __init__(self, world: World, cs: ContactSet, groups: tuple | None = None) -> None:
        c = cs.contacts
        self.cs = cs
        if groups is None:
            groups = island_groups(heap_state(), world.n, world.dynamic, c.body_a, c.body_b)
        self.order, self.starts, self.bodies, self.body_starts = groups
        o = self.order
        self.rows = K.IslandRows(self.starts, c.body_a.take(o), c.body_b.take(o),
                                 c.normal.take(o, axis=0), cs.tangent.take(o, axis=0),
                                 cs.r_a.take(o, axis=0), cs.r_b.take(o, axis=0),
                                 world.inv_mass, world.inv_inertia)

    def island_bodies(self, i: int) -> np.ndarray:
        return self.bodies[self.body_starts[i]:self.body_starts[i + 1]]


class _KernelCall:
    """A compiled kernel called through the machine code of the overload its previous call
    took. numba's dispatch types every argument in Python before each call, and for the
    80-odd arrays ``_kernels.advance`` takes that is most of what a call costs beyond its
    steps; a node at 100 frames per second pays it 100 times per simulated second, a control
    loop 1000 (``benchmarks/throughput.py``'s one-part cases at 10 ms and 1 ms frames). The
    entry point unboxes the same arguments without looking at their types, so it is only
    taken while they cannot have changed: every argument but the ``watched`` ones is made by
    the stepper with fixed types (times as floats, whatever number a caller gave), and the
    watched ones (the state's arrays, which callers may replace) must be the very objects of
    the call that chose the overload. Anything else, or a numba without the attributes used
    here, goes through the dispatcher."""

    def __init__(self, dispatcher) -> None:
        self._dispatcher = dispatcher
        self._entry = None
        self._watched: tuple = ()

    def __call__(self, args: tuple, watched: tuple):
        if self._entry is not None and len(watched) == len(self._watched) and all(
                a is b for a, b in zip(watched, self._watched)):
            return self._entry(*args)
        out = self._dispatcher(*args)
        self._entry, self._watched = self._entry_point(args), watched
        return out

    def forget(self) -> None:
        """Go through the dispatcher at the next call."""
        self._entry = None

    def _entry_point(self, args: tuple):
        """The compiled entry point for exactly these argument types, None if there is none
        (the dispatcher converted an argument to reach an overload)."""
        try:
            types = tuple(self._dispatcher.typeof_pyval(a) for a in args)
            return self._dispatcher.overloads[types].entry_point
        except (AttributeError, KeyError, TypeError, ValueError):
            return None


class TimeStepper(StepperBase):
    """Advances a state by fixed steps of ``spec.time_step``."""

    settings_type = TimeStepSettings
    name = 'time_stepping'
    fixed_steps = True
    error_setting = 'time_step'
    order = 1             # Moreau's midpoint step: first order in the step

    def prepare(self) -> None:
        world = self.world
        self._radius = world.radius
        self._dyn = world.dynamic
        self._dyn_idx = np.flatnonzero(self._dyn)
        self._dyn_col = self._dyn[:, None]      # where= mask of (n, 2) arrays
        self._driven = world.driven
        self._g = float(np.linalg.norm(world.gravity))
        self._warm = _Warm(len(world.shapes.vertices))
        self._projected = np.zeros(0, bool)
        # contacts of this step left out of the velocity solve, with the midpoint positions
        # (for the projection; see _with_spare)
        self._spare: tuple[Contacts, np.ndarray] | None = None
        # body pair -> the pair's (vx, vy, omega) before a speculative row held it back last
        # step: its Newton rows bounce the speed it came in with
        self._approach: dict[tuple[int, int], np.ndarray] = {}
        self._geo: _IslandGeometry | None = None
        self._compiled = (body_arrays(world), shape_arrays(world))
        self._reports = TK.new_reports(256)
        # the compiled step's counters, maxima and messages, reused from call to call
        self._io = (np.zeros(len(TK.INT_COUNTERS), np.int64), np.zeros(len(TK.FLOAT_MAXIMA)),
                    np.zeros((MAX_MESSAGES, 4)), np.zeros(1, np.int64))
        self._no_approach = TK.no_approach()
        self._advance_kernel = _KernelCall(TK.advance)
        self._settings_memo: tuple[tuple, TK.StepSettings] | None = None
        # the compiled step's scratch (two: a step's warm-start impulses live in its arena
        # while the next step runs in the other); grown when a step needed more
        size = _ARENA_BYTES + _ARENA_BYTES_PER_VERTEX * len(self.world.shapes.vertices)
        self._arenas = (new_arena(size), new_arena(size))

    def _compiled_settings(self) -> TK.StepSettings:
        """The settings as the compiled step takes them, made again whenever the settings or
        the spec's step changed (tests and studies change settings on a live stepper)."""
        st, spec = self.settings, self.spec
        key = (st, st.version, spec.time_step, spec.friction_impulse)
        if self._settings_memo is None or self._settings_memo[0] != key:
            self._settings_memo = (key, self._make_compiled_settings())
        return self._settings_memo[1]

    def _make_compiled_settings(self) -> TK.StepSettings:
        st, spec = self.settings, self.spec
        narrow = NarrowPhaseTolerances(
            bp_margin_m=2.0 * PARAM_TOL * self.world.shapes.derived.max_edge_length,
            margin_m=0.0, depth_m=-1.0, depth_fraction=DEPTH_FRACTION, tie_rel=TIE_REL,
            param_tol=float(PARAM_TOL), angle_tol=float(ANGLE_TOL))
        return TK.StepSettings(
            float(spec.time_step), float(st.touch_m), float(st.projection_slop_m),
            float(st.projection_reach), float(st.slop_m), float(st.push_out),
            float(st.push_max_mps), st.speculative_depth * DEPTH_FRACTION,
            st.substep_depth * DEPTH_FRACTION,
            float(st.slip_tol_mps), float(st.lcp_tol), bool(st.reuse_row_states),
            int(st.direct_max_rows),
            float(st.pgs_tol_mps), int(st.pgs_max_sweeps), int(st.pgs_check),
            float(st.pgs_omega), bool(st.pgs_momentum), bool(spec.friction_impulse), narrow)

    def margin(self, state: State, h: float) -> tuple[float, float]:
        """Distances a vertex can close on an edge in one step (m): ``(search, base)``.

        ``base`` is 1.5 steps of the fastest body's travel plus the fastest other's (the
        track's); ``search`` also covers two parts closing on each other faster than that
        (thrown at each other), and is the contact search's margin. Beyond ``base`` only the
        contacts of pairs that can close that far are kept (``_within_reach``)."""
        w = self.world
        v_max, v_kin, _, closing = K.speed_bounds(state.velocity, state.omega, self._radius,
                                                  self._dyn)
        for i in self._driven:
            d = w.drives[i]
            v_kin = max(v_kin, 2 * np.pi * d.frequency_hz * d.amplitude_m * 2)
        slack = 10 * self.settings.touch_m
        base = 1.5 * h * (v_max + v_kin + self._g * h) + slack
        return 1.5 * h * (max(v_max + v_kin, closing) + self._g * h) + slack, base

    def _within_reach(self, contacts: Contacts, state: State, h: float,
                      base: float) -> Contacts:
        """The contacts within ``base`` (see ``margin``), and those beyond it between two
        parts whose relative motion can close the gap in one step. Parts falling together
        are far from closing: their contacts would only join islands (a pile's, solved as
        one)."""
        far = contacts.gap > base
        if not far.any():
            return contacts
        a, b = contacts.body_a, contacts.body_b
        v, spin = state.velocity, np.abs(state.omega) * self._radius
        closing = np.hypot(*(v[a] - v[b]).T) + spin[a] + spin[b]
        reach = 1.5 * h * (closing + self._g * h) + 10 * self.settings.touch_m
        both = self.world.dynamic[a] & self.world.dynamic[b]
        return _take(contacts, np.flatnonzero(~far | (both & (contacts.gap <= reach))))

    def advance(self, state: State, t_end: float) -> list[StepContacts]:
        """Step ``state`` to ``t_end`` (s) by ``spec.time_step``, the last step shortened to land
        on ``t_end``; the contacts of every step that had any."""
        h = self.spec.time_step
        reports: list[StepContacts] = []
        # A remainder below 1e-9 steps is round-off of a frame length that is a multiple of the
        # step: it costs no extra short step.
        while t_end - state.t > 1e-9 * h:
            if self.settings.compiled:
                code = self._advance_compiled(state, t_end, reports)
                if code == TK.DONE:
                    break
                if code == TK.GROW:
                    self._reports = TK.new_reports(2 * len(self._reports.gap))
                    continue
            # the reference step: where the kernel hands a step back, or not compiled. It
            # leaves the warm start and the held-back velocities in arrays of its own making:
            # the next call goes through numba's dispatcher again
            report = self.step(state, self.safe_step(state, min(h, t_end - state.t)))
            self._advance_kernel.forget()
            if report is not None:
                reports.append(report)
        return reports

    def safe_step(self, state: State, h: float) -> float:
        """The step the state can take, at most ``h`` (s): shorter where a pair of pieces could
        close faster than the scheme resolves (``_kernels.safe_step_inline``),
        counted in ``stats.substeps``."""
        bodies, shapes = self._compiled
        step = TK.safe_step(heap_state(), float(h), state.position, state.angle,
                            state.velocity, state.omega, bodies, shapes,
                            self.world.drive_segments(state.t), self._compiled_settings())
        self.stats.substeps += step < h
        return step

    def _advance_compiled(self, state: State, t_end: float,
                          reports: list[StepContacts]) -> int:
        """Steps of ``_kernels.advance`` towards ``t_end``; their contacts are
        appended to ``reports`` as one entry (rows in step order). Returns the kernel's code."""
        stats, rep = self.stats, self._reports
        ints, floats, msgs, n_msgs = self._io
        rep.counts[:] = 0
        ints[:] = 0
        for k, name in enumerate(TK.FLOAT_MAXIMA):
            floats[k] = getattr(stats, name)
        n_msgs[0] = 0
        warm = TK.Warm(self._warm.keys, self._warm.p_n, self._warm.p_t, self._warm.state,
                       self._warm.projection_state)
        held = self._approach
        approach = self._no_approach if not held else TK.Approach(
            np.array([p[0] for p in held], np.int64), np.array([p[1] for p in held], np.int64),
            np.concatenate(list(held.values())))
        bodies, shapes = self._compiled
        arrays = (state.position, state.angle, state.velocity, state.omega)
        code, t, warm, approach = self._advance_kernel(
            (float(state.t), float(t_end), *arrays, bodies, shapes,
             self.world.drive_segments(state.t),
             self._compiled_settings(), warm, approach, ints, floats, rep,
             msgs[:max(0, len(msgs) - len(stats.messages))], n_msgs,
             (self._arenas[0].state, self._arenas[1].state)), arrays)
        self._approach = {} if not approach.lo.size else {
            (lo, hi): approach.vel[2 * p:2 * p + 2] for p, (lo, hi) in
            enumerate(zip(approach.lo.tolist(), approach.hi.tolist(), strict=True))}
        if self._arenas[0].state[SHORT] or self._arenas[1].state[SHORT]:
            self._arenas = tuple(new_arena(grown_capacity(a)) for a in self._arenas)
        state.t = t
        (self._warm.keys, self._warm.p_n, self._warm.p_t, self._warm.state,
         self._warm.projection_state) = warm
        for name, value in zip(TK.INT_COUNTERS, ints.tolist(), strict=True):
            if not value:
                continue
            if name == 'max_lcp_rows':
                stats.max_lcp_rows = max(stats.max_lcp_rows, value)
            else:
                setattr(stats, name, getattr(stats, name) + value)
        for name, value in zip(TK.FLOAT_MAXIMA, floats.tolist(), strict=True):
            setattr(stats, name, value)
        for vres, res, sweeps, rows in msgs[:n_msgs[0]].tolist():
            stats.messages.append(f'pgs: velocity residual {vres:.3g} m/s (lcp residual '
                                  f'{res:.3g}) after {int(sweeps)} sweeps ({int(rows)} rows)')
        rows = int(rep.counts[0])
        if rows:
            r = slice(0, rows)
            contacts = Contacts(rep.body_a[r].copy(), rep.piece_a[r].copy(),
                                rep.vertex_a[r].copy(), rep.body_b[r].copy(),
                                rep.piece_b[r].copy(), rep.edge_b[r].copy(),
                                rep.point[r].copy(), rep.normal[r].copy(), rep.gap[r].copy(),
                                rep.edge_param[r].copy())
            cs = ContactSet(contacts, rep.tangent[r].copy(), rep.r_a[r].copy(),
                            rep.r_b[r].copy(), rep.mu_static[r].copy(),
                            rep.mu_dynamic[r].copy(), rep.restitution[r].copy())
            reports.append(StepContacts(cs, rep.normal_impulse[r].copy(),
                                        rep.tangent_impulse[r].copy()))
        return code

    def reset(self) -> None:
        """Nothing here depends on the prescribed motion beyond the current step."""

    def step(self, state: State, h: float | None = None) -> StepContacts | None:
        """Advance ``state`` in place by h (default: the scene's time step)."""
        w = self.world
        h = self.spec.time_step if h is None else h
        dyn = self._dyn_idx
        t0 = state.t
        mid = state.copy()
        mid.t = t0 + 0.5 * h
        # mid.position[dyn] += 0.5 h state.velocity[dyn], and the angles, in one kernel
        K.drift(dyn, state.position, state.angle, state.velocity, state.omega, 0.5 * h,
                mid.position, mid.angle)
        w.apply_prescribed_motion(mid)

        # free end-of-step velocities; driven bodies' positions and velocities at t0 + h
        end = State(t0 + h, mid.position.copy(), mid.angle, mid.velocity.copy(),
                    mid.omega.copy())
        # end.velocity[dyn] += h g (where= masks, not fancy indexing: see _take)
        np.add(end.velocity, h * w.gravity, out=end.velocity, where=self._dyn_col)
        w.apply_prescribed_motion(end)

        margin, base = self.margin(state, h)
        contacts = find_contacts(w.shapes, mid.position, mid.angle, self._dyn, margin=margin)
        if contacts.n and margin > base:
            contacts = self._within_reach(contacts, state, h, base)
        report = self._contacts(contacts, state, mid, end, h, margin) if contacts.n else None

        state.t = end.t
        # state.position[dyn] = mid.position[dyn] + 0.5 h end.velocity[dyn], and the angles
        K.drift(dyn, mid.position, mid.angle, end.velocity, end.omega, 0.5 * h,
                state.position, state.angle)
        np.copyto(state.velocity, end.velocity, where=self._dyn_col)    # [dyn] = [dyn]
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
        # max over dynamic bodies of omega^2 r
        spin = K.speed_bounds(state.velocity, state.omega, self._radius, self._dyn)[2]
        return max(self.settings.slip_tol_mps, h * spin)

    def _project(self, cs: ContactSet, state: State, mask: np.ndarray) -> None:
        """Move penetrating bodies out along their contact normals; velocities are untouched.

        The midpoint scheme lets a landing vertex sink by up to h |v_N| / 2. Correcting that
        with a velocity bias would inject kinetic energy, so positions are projected instead:
        the smallest mass-weighted move (a frictionless LCP on the normal rows) that brings
        every contact (with ``mask``) back to within ``projection_slop_m``.

        The islands with a deep contact are solved together by the compiled Dantzig
        (``_island_kernels.solve_small`` with no friction rows: the normal rows of each island, the
        problem ``_project_reference`` gives ``lcp.solve``); an island whose answer misses
        ``lcp_tol`` is solved again by ``lcp.solve`` and its whole ladder, as before.
        """
        w, st = self.world, self.settings
        topo = w.shapes.derived
        cos, sin = np.cos(state.angle), np.sin(state.angle)

        def end_gaps(cs: ContactSet, mask: np.ndarray) -> np.ndarray:
            # gaps at the end of the step of the contacts that may be projected (bits as
            # evaluate_gaps); islands with a deep contact hold nothing but such contacts
            idx = np.flatnonzero(mask)
            c = cs.contacts
            gap = np.zeros(c.n)
            gap[idx] = K.feature_gaps(heap_state(), idx, c.vertex_a, c.edge_b, w.shapes.vertices,
                                      w.shapes.normals, topo.vertex_body, state.position,
                                      cos, sin)
            return gap

        gap = end_gaps(cs, mask)
        deep = gap < -st.projection_slop_m
        if not deep.any():
            return
        if self._spare is not None:
            cs, mask = self._with_spare(cs, mask)
            gap = end_gaps(cs, mask)
            deep = gap < -st.projection_slop_m
        geo = self._island_geometry(cs)
        order, starts = geo.order, geo.starts
        k = len(order)
        sel = np.logical_or.reduceat(deep[order], starts[:-1])
        zeros = np.zeros(k)
        x_n = np.zeros(k)
        # each island is solved first in the row states of its contacts' last projection
        keys = self._warm.key(cs.contacts)[order]
        states_in = (self._warm.projection_states(keys) if st.reuse_row_states
                     else np.full(k, -1))
        states_out = np.full(k, -1)
        # the normal rows alone: no friction row, no bounds
        res, work, codes = K.solve_small(
            heap_state(), sel, geo.rows,
            K.RowProblem(gap[order] + st.projection_slop_m, zeros, np.zeros(k, bool), zeros,
                         zeros),
            K.RowImpulses(x_n, np.zeros(k), np.zeros(k)), states_in, states_out)
        bad = sel & (res > st.lcp_tol)
        ok = sel & ~bad
        taken = np.repeat(ok, np.diff(starts))
        self._warm.store_projection(keys[taken], states_out[taken])
        self.stats.record_batch((starts[1:] - starts[:-1])[ok], work[ok], res[ok],
                                np.ones(int(ok.sum()), bool), 'dantzig')
        if bad.any():
            for i in np.flatnonzero(bad):
                # the reference path for this island: lcp.solve's whole ladder (it records
                # the fallback and its message)
                lo_c, hi_c = starts[i], starts[i + 1]
                idx = order[lo_c:hi_c]
                x_n[lo_c:hi_c] = self._project_island(cs, idx, geo.island_bodies(i), gap[idx])
        dv = np.zeros((w.n, 3))
        K.apply_impulses(heap_state(), dv, geo.rows, x_n, zeros)
        depth = np.add.reduceat(np.maximum(-gap[order], 0.0) * deep[order], starts[:-1])
        b = geo.bodies
        dv[b] = cap_moves(dv[b], self._radius[b],
                          st.projection_reach * np.repeat(depth, np.diff(geo.body_starts)))
        # state.position[dyn] += dv[dyn, :2]; state.angle[dyn] += dv[dyn, 2]
        np.add(state.position, dv[:, :2], out=state.position, where=self._dyn_col)
        np.add(state.angle, dv[:, 2], out=state.angle, where=self._dyn)

    def _project_island(self, cs: ContactSet, idx: np.ndarray, bodies: np.ndarray,
                        gap: np.ndarray) -> np.ndarray:
        """Normal impulses of the projection LCP of one island by ``lcp.solve`` (recorded)."""
        st = self.settings
        jac = island_jacobian(self.world, cs.subset(idx), bodies)
        k = len(idx)
        W = jac.delassus()[:k, :k]
        problem = lcp.FrictionalLCP(W, gap + st.projection_slop_m, np.full(k, -1),
                                    np.zeros(k), np.zeros(k))
        result = lcp.solve(problem, tol=st.lcp_tol)
        self.stats.record(result)
        return result.x

    def _project_reference(self, cs: ContactSet, state: State, mask: np.ndarray) -> None:
        """``_project`` island by island through ``lcp.solve`` and numpy Jacobians: the
        reference the compiled path is checked against (test/stepping/test_pile.py)."""
        w, st = self.world, self.settings
        gap, _ = evaluate_gaps(w.shapes, cs.contacts, state.position, state.angle)
        deep = (gap < -st.projection_slop_m) & mask
        if not deep.any():
            return
        if self._spare is not None:
            cs, mask = self._with_spare(cs, mask)
            gap, _ = evaluate_gaps(w.shapes, cs.contacts, state.position, state.angle)
            deep = (gap < -st.projection_slop_m) & mask
        for bodies, idx in islands(w, cs):
            if not deep[idx].any():
                continue
            x = self._project_island(cs, idx, bodies, gap[idx])
            jac = island_jacobian(w, cs.subset(idx), bodies)
            move = jac.velocity_change(np.concatenate([x, np.zeros(len(idx))]))
            depth = np.maximum(-gap[idx], 0.0)[deep[idx]].sum()
            move = cap_moves(move, self._radius[bodies], st.projection_reach * depth)
            state.position[bodies] += move[:, :2]
            state.angle[bodies] += move[:, 2]

    def _outside_piles(self, spare: Contacts, mid_position: np.ndarray, pile_a: np.ndarray,
                       pile_b: np.ndarray):
        """``(spare, mid_position)`` without the contacts of bodies in a pile (piles are
        not projected), or None when nothing is left."""
        in_pile = np.zeros(self.world.n, bool)
        in_pile[pile_a] = True
        in_pile[pile_b] = True
        in_pile &= self._dyn
        ok = np.flatnonzero(~(in_pile[spare.body_a] | in_pile[spare.body_b]))
        return (_take(spare, ok), mid_position) if len(ok) else None

    def _with_spare(self, cs: ContactSet, mask: np.ndarray) -> tuple[ContactSet, np.ndarray]:
        """``cs`` and ``mask`` with the contacts found this step but left out of the velocity
        solve (apart, and not closing): the projection must not push a body through them.
        A part resting on two points that the step saw touching at only one of them was
        projected out at that one and rotated into the other, every other step."""
        if self._spare is None:
            return cs, mask
        spare, mid_position = self._spare
        extra = contact_set(self.world, State(0.0, mid_position, None, None, None), spare)
        c1, c2 = cs.contacts, extra.contacts
        both = ContactSet(Contacts(*(np.concatenate([getattr(c1, f), getattr(c2, f)])
                                     for f in CONTACT_FIELDS)),
                          *(np.concatenate([getattr(cs, f), getattr(extra, f)])
                            for f in ('tangent', 'r_a', 'r_b', 'mu_static', 'mu_dynamic',
                                      'restitution')))
        return both, np.concatenate([mask, np.ones(spare.n, bool)])

    def _island_geometry(self, cs: ContactSet) -> _IslandGeometry:
        """The islands of ``cs`` and its contacts' geometry in island order (cached for the
        contact set of the current step, which the velocity solve and the projection share)."""
        geo = self._geo
        if geo is None or geo.cs is not cs:
            geo = self._geo = _IslandGeometry(self.world, cs)
        return geo

    # ---------------------------------------------------------------------------------------

    def _contacts(self, contacts, state: State, mid: State, end: State, h: float,
                  reach_m: float) -> StepContacts | None:
        """Solve every island's impulse LCP; adds the velocity changes to ``end``."""
        w, st, stats = self.world, self.settings, self.stats
        # Small islands (solved exactly by pivoting) use the Moreau-Jean index set: a contact
        # takes part when it touches at the midpoint or would close its gap by the end of the
        # step, under Newton's law, and penetration is removed afterwards by a position
        # projection, so no velocity is spent on it. Piles (islands above direct_max_rows,
        # solved by PGS) keep speculative rows and a velocity push-out, which PGS handles
        # robustly at their size. (``_contact_rows_reference`` spells this out in numpy.)
        groups = island_groups(heap_state(), w.n, self._dyn, contacts.body_a, contacts.body_b)
        slip_tol = self._slip_tol(state, h)
        rows = self._contact_rows(contacts, groups, state, mid, end, h, slip_tol, reach_m)
        keep = rows[0]
        self._spare = None
        if not len(keep):
            return None
        if len(keep) < contacts.n:
            left_out = np.ones(contacts.n, bool)
            left_out[keep] = False
            self._spare = (_take(contacts, np.flatnonzero(left_out)), mid.position)
            contacts = _take(contacts, keep)
            groups = None       # dropping contacts may split islands
        (tangent, r_a, r_b, mu_s, mu_d, restitution, v_n_free, v_t_free, v_t_pre, pile,
         colliding, b_n, box, mu_lo, mu_hi, gap_min) = rows[1:]
        cs = ContactSet(contacts, tangent, r_a, r_b, mu_s, mu_d, restitution)
        # islands and island-ordered kinematics, shared with the projection after the step
        geo = self._geo = _IslandGeometry(w, cs, groups)
        c = contacts
        a, b = c.body_a, c.body_b
        stats.max_penetration_m = max(stats.max_penetration_m, float(-gap_min))
        self._projected = ~pile
        if self._spare is not None and pile.any():
            self._spare = self._outside_piles(*self._spare, a[pile], b[pile])
        keys = self._warm.key(c)
        p_n = np.zeros(c.n)
        p_t = np.zeros(c.n)
        p_state = np.full(c.n, -1)
        bouncy = restitution > 0.0
        if bouncy.any():
            # speculative rows: neither a pile's nor a Newton row (the kernel's index set)
            spec = ~pile & (c.gap > st.touch_m) & (c.gap + 0.5 * h * v_n_free > st.touch_m)
            if self._approach:
                b_n = self._restore_approach(cs, b_n, ~pile & ~spec & bouncy, state)

        order, starts = geo.order, geo.starts
        n_isl = len(starts) - 1
        stats.islands += n_isl
        # an island whose normal rows all have b >= 0 is answered by zero impulses
        b_no = b_n[order]
        neg = np.minimum.reduceat(b_no, starts[:-1]) < 0.0
        stats.record_trivial(n_isl - int(np.count_nonzero(neg)))
        if neg.any():
            # the bodies' free velocities at mid-step (the friction law's time course)
            half_vel = mid.velocity.copy()
            np.add(half_vel, 0.5 * h * w.gravity, out=half_vel, where=self._dyn_col)
            failed = self._solve(cs, geo, neg, b_no, v_t_free[order],
                                 box[order], mu_lo[order], mu_hi[order], v_t_pre[order],
                                 colliding[order], half_vel, state.omega, keys[order], p_n,
                                 p_t, p_state)
            for i in failed:
                # the numba Dantzig missed the tolerance: the reference path (lcp.solve's
                # whole ladder) solves the island again
                idx = order[starts[i]:starts[i + 1]]
                impulse, _ = solve_impulses(
                    w, cs.subset(idx), geo.island_bodies(i), b_n[idx],
                    v_t_free[idx], v_t_pre[idx], colliding[idx], self.spec.friction_impulse,
                    st, stats, slip_tol)
                p_n[idx], p_t[idx] = impulse[:len(idx)], impulse[len(idx):]
                p_state[idx] = -1
            dv = np.zeros((w.n, 3))
            # (in the contact order: no island's start is read)
            K.apply_impulses(heap_state(), dv, K.IslandRows(
                starts, a, b, c.normal, cs.tangent, cs.r_a, cs.r_b, w.inv_mass,
                w.inv_inertia), p_n, p_t)
            # end.velocity[dyn] += dv[dyn, :2]; end.omega[dyn] += dv[dyn, 2]
            np.add(end.velocity, dv[:, :2], out=end.velocity, where=self._dyn_col)
            np.add(end.omega, dv[:, 2], out=end.omega, where=self._dyn)
        stats.impacts += int(np.count_nonzero(colliding & (p_n > 0)))
        self._approach = (self._held_back(cs, spec & bouncy & (p_n > 0.0), state)
                          if bouncy.any() else {})
        self._warm.store(keys, p_n, p_t, p_state)
        return StepContacts(cs, p_n, p_t)

    def _held_back(self, cs: ContactSet, held: np.ndarray,
                   state: State) -> dict[tuple[int, int], np.ndarray]:
        """Velocities before the push of the body pairs whose speculative rows pushed
        (``held``): ``(lower body, upper body) -> (vx, vy, omega)`` of each, from the first step
        that held them back. Their parts arrive slowed to what the row allowed, and the
        collision must bounce the speed they came in with (10 m/s at e = 0.5 left at 4.81, not
        5 m/s). Kept per body pair, not per contact: the collision may be found on another
        vertex-edge pair than the one that held the part back (two parts thrown face to face)."""
        c = cs.contacts
        before = self._approach
        out: dict[tuple[int, int], np.ndarray] = {}
        for a, b in zip(c.body_a[held].tolist(), c.body_b[held].tolist()):
            pair = (min(a, b), max(a, b))
            if pair not in out:
                out[pair] = before.get(pair, np.array([[*state.velocity[i], state.omega[i]]
                                                       for i in pair]))
        return out

    def _restore_approach(self, cs: ContactSet, b_n: np.ndarray, newton: np.ndarray,
                          state: State) -> np.ndarray:
        """``b_n`` with the Newton rows of the pairs held back before (``_held_back``) using
        the normal velocity those velocities give at the contact in ``e min(v_N, 0)``."""
        known = self._approach
        c = cs.contacts
        idx = np.array([i for i in np.flatnonzero(newton).tolist()
                        if (min(c.body_a[i], c.body_b[i]), max(c.body_a[i], c.body_b[i]))
                        in known], dtype=int)
        if not len(idx):
            return b_n
        a, b = c.body_a[idx], c.body_b[idx]
        v_now, _ = K.contact_velocities(a, b, c.normal[idx], cs.r_a[idx], cs.r_b[idx],
                                        state.velocity, state.omega)
        velocity, omega = state.velocity.copy(), state.omega.copy()
        came_in = np.empty(len(idx))
        for j, i in enumerate(idx.tolist()):
            pair = (min(a[j], b[j]), max(a[j], b[j]))
            velocity[list(pair)] = known[pair][:, :2]
            omega[list(pair)] = known[pair][:, 2]
            came_in[j] = K.contact_velocities(a[j:j + 1], b[j:j + 1], c.normal[i:i + 1],
                                              cs.r_a[i:i + 1], cs.r_b[i:i + 1], velocity,
                                              omega)[0][0]
        b_n = b_n.copy()
        b_n[idx] += cs.restitution[idx] * (np.minimum(np.minimum(came_in, v_now), 0.0)
                                           - np.minimum(v_now, 0.0))
        return b_n

    def _contact_rows(self, contacts, groups: tuple, state: State, mid: State, end: State,
                      h: float, slip_tol: float, reach_m: float) -> tuple:
        """Which contacts take part and their LCP rows, by ``_island_kernels.contact_rows``: (kept
        indices, tangent, r_a, r_b, mu_static, mu_dynamic, restitution, v_n_free, v_t_free,
        v_t_pre, pile, colliding, b_n, box, mu_lo, mu_hi, smallest gap). ``reach_m`` is the
        distance a point can travel in the step (the contact search's margin)."""
        w, st = self.world, self.settings
        c = contacts
        settings = K.RowSettings(
            h_s=h, touch_m=st.touch_m, max_rows=st.direct_max_rows, push_out=st.push_out,
            push_max_mps=st.push_max_mps, slop_m=st.slop_m,
            collide_speed_mps=-2.0 * self._g * h, slip_tol_mps=slip_tol,
            friction_impulse=bool(self.spec.friction_impulse),
            spec_depth=st.speculative_depth * DEPTH_FRACTION, reach_m=reach_m)
        return K.contact_rows(
            heap_state(), c.body_a, c.body_b, c.point, c.normal, c.gap, groups[0], groups[1],
            mid.position, end.velocity, end.omega, state.velocity, state.omega, w.mu_static,
            w.mu_dynamic, w.restitution, c.piece_a, c.piece_b, w.shapes.derived.piece_width,
            settings)

    def _contact_rows_reference(self, contacts, groups: tuple, state: State, mid: State,
                                end: State, h: float, slip_tol: float, reach_m: float) -> tuple:
        """``_contact_rows`` in numpy (``contact_set``, ``contact_velocities``,
        ``friction_rows``): the reference the kernel is checked against
        (test/stepping/test_pile.py)."""
        w, st = self.world, self.settings
        cs = contact_set(w, mid, contacts)
        # free end-of-step velocities at the midpoint configuration
        v_n_free, v_t_free = K.contact_velocities(contacts.body_a, contacts.body_b,
                                                  contacts.normal, cs.r_a, cs.r_b,
                                                  end.velocity, end.omega)
        gap = contacts.gap
        order0, starts0 = groups[0], groups[1]
        lens0 = np.diff(starts0)
        size = np.empty(contacts.n, np.int64)
        size[order0] = np.repeat(lens0, lens0)
        pile = 2 * size > st.direct_max_rows
        newton_set = pile | (gap <= st.touch_m) | (gap + 0.5 * h * v_n_free <= st.touch_m)
        width = w.shapes.derived.piece_width
        allow = (st.speculative_depth * DEPTH_FRACTION) * np.minimum(
            width[contacts.piece_a], width[contacts.piece_b])
        spec = ~newton_set & (gap + allow <= reach_m)
        keep = np.flatnonzero(newton_set | spec)
        contacts, cs = contacts.take(keep), cs.subset(keep)
        v_n_free, v_t_free, gap, pile = v_n_free[keep], v_t_free[keep], gap[keep], pile[keep]
        allow, spec = allow[keep], spec[keep]
        v_n_pre, v_t_pre = K.contact_velocities(contacts.body_a, contacts.body_b,
                                                contacts.normal, cs.r_a, cs.r_b,
                                                state.velocity, state.omega)
        touching = gap <= st.touch_m
        colliding = (touching | ~pile) & (v_n_pre < -2.0 * self._g * h)
        newton = v_n_free + cs.restitution * np.minimum(v_n_pre, 0.0)
        push = np.minimum(st.push_out * np.maximum(-gap - st.slop_m, 0.0) * 2.0 / h,
                          st.push_max_mps)
        b_n = np.where(~pile, np.where(spec, v_n_free + (gap + allow) / h, newton),
                       np.where(touching, newton - push, v_n_free + 2.0 * gap / h))
        friction, mu_lo, mu_hi = friction_rows(cs, v_t_pre, colliding,
                                               self.spec.friction_impulse, slip_tol,
                                               restick=True)
        return (keep, cs.tangent, cs.r_a, cs.r_b, cs.mu_static, cs.mu_dynamic, cs.restitution,
                v_n_free, v_t_free, v_t_pre, pile, colliding, b_n, friction == BOX, mu_lo, mu_hi,
                float(gap.min(initial=np.inf)))

    def _solve(self, cs: ContactSet, geo: _IslandGeometry, todo, b_n, b_t, box, lo, hi, slip,
               colliding, half_vel, half_om, keys, p_n, p_t, p_state) -> np.ndarray:
        """Islands with ``todo`` (the non-trivial ones): small ones by the numba Dantzig
        (or in one piece on the row states they had), large ones by PGS. In small islands a
        slip that stops within the step is held by ``mu_d`` up to that instant and by the
        static law after it (``_island_kernels.stop_within_step``); then Kawachi's second
        pass where a static bound saturated, and a static contact that holds on average but
        not throughout breaks away within the step (``breakaway_within_step``). Arrays b_n ..
        slip and keys are in island order (``order``; ``slip`` the pre-step slip, m/s;
        ``half_vel`` / ``half_om`` the bodies' free velocities at mid-step; not in an island
        with a ``colliding`` contact). Writes p_n / p_t
        and the small islands' row states p_state, and returns the islands whose Dantzig
        answer missed ``lcp_tol``."""
        w, st, stats = self.world, self.settings, self.stats
        order, starts = geo.order, geo.starts
        lens = starts[1:] - starts[:-1]
        isl = np.repeat(np.arange(len(lens)), lens)
        mu_s, mu_d = cs.mu_static[order], cs.mu_dynamic[order]
        # contacts Kawachi's second pass may concern (none where mu_d == mu_s)
        may_slide = box & (mu_d < mu_s)
        rows = lens + np.add.reduceat(box, starts[:-1])
        small = todo & (rows <= st.direct_max_rows)
        large = todo & ~small
        x_n, x_t, states_in = self._warm.lookup(keys)
        if not st.reuse_row_states:
            states_in[:] = -1
        if large.any():
            # the order PGS sweeps a pile in: bottom-up (_kernels._heights)
            point = cs.contacts.point[order]
            height = -(point[:, 0] * w.gravity[0] + point[:, 1] * w.gravity[1])
            # PGS starts from the previous step's impulses (Dantzig from scratch)
            if not todo.all():
                x_n[~todo[isl]] = 0.0   # trivial islands: zero impulses, not last step's
                x_t[~todo[isl]] = 0.0
        else:
            x_n, x_t = np.zeros(len(keys)), np.zeros(len(keys))
        states = np.full(len(keys), -1)
        v_t_new = np.zeros(len(b_n))
        failed = np.zeros(len(lens), bool)
        # friction_rows gives a contact sliding into the step one-sided bounds; an island
        # with an impact keeps Kawachi's impact law
        steady = small & (np.add.reduceat(colliding.astype(np.int64), starts[:-1]) == 0)
        sliding = box & (lo != hi) & steady[isl]
        offset = np.zeros(len(keys))
        remain = np.ones(len(keys))
        v_t_end = b_t.copy()        # the free end slip, before a stop's impulse shifts b_t
        out = K.RowImpulses(x_n, x_t, v_t_new)
        slip_state = K.StepSlip(slip, sliding, half_vel, half_om, v_t_end, mu_s, mu_d, offset,
                                remain)
        pgs = K.PgsSettings(st.pgs_tol_mps, st.pgs_max_sweeps, st.pgs_check, st.pgs_omega,
                            st.pgs_momentum)
        for attempt in range(3):
            # (second_pass gives new bounds: the problem as it stands now)
            problem = K.RowProblem(b_n, b_t, box, lo, hi)
            if small.any():
                res, work, codes = K.solve_small(heap_state(), small, geo.rows, problem, out,
                                                 states_in, states)
                bad = small & (res > st.lcp_tol)
                ok = small & ~bad
                stats.record_batch(rows[ok], work[ok], res[ok], np.ones(ok.sum(), bool),
                                   'dantzig')
                failed |= bad
                for i in np.flatnonzero(bad):
                    stats.fallbacks += 1
                    if len(stats.messages) < MAX_MESSAGES:
                        stats.messages.append(lcp.dantzig_message(res[i], codes[i]))
            if large.any():
                res, vres, work = K.solve_pgs(heap_state(), large, geo.rows, problem, out,
                                              np.zeros((w.n, 3)), pgs, height)
                conv = vres[large] <= st.pgs_tol_mps
                stats.record_batch(rows[large], work[large], res[large], conv, 'pgs')
                stats.pgs_solves += int(large.sum())
                stats.max_pgs_velocity_residual_mps = max(
                    stats.max_pgs_velocity_residual_mps, float(vres[large].max()))
                for i in np.flatnonzero(large)[~conv]:
                    if len(stats.messages) < MAX_MESSAGES:
                        stats.messages.append(
                            f'pgs: velocity residual {vres[i]:.3g} m/s (lcp residual '
                            f'{res[i]:.3g}) after {work[i]} sweeps ({rows[i]} rows)')
            if attempt == 2:
                break
            if attempt == 0 and sliding.any():
                redo = K.stop_within_step(heap_state(), small & ~failed, geo.rows, problem, out,
                                          slip_state)
            else:
                redo = np.zeros(len(lens), bool)
            # after the first answer on friction_rows' bounds, after the second on the
            # contacts that stopped within the step
            solved = (small | large)[isl] & ~failed[isl]
            saturated, lo, hi = second_pass(lo, hi, x_n, x_t, v_t_new, mu_s, mu_d,
                                            may_slide & solved & ((remain < 1.0) == attempt),
                                            st.slip_tol_mps, remain)
            redo[isl[saturated]] = True
            if sliding.any() or attempt == 0:
                redo |= K.breakaway_within_step(
                    heap_state(), steady & small & ~failed, geo.rows,
                    K.RowProblem(b_n, b_t, box, lo, hi), out, slip_state, attempt == 1)
            if not redo.any():
                break
            small, large = small & redo, large & redo
        x_t = np.where(offset != 0.0, x_t + offset, x_t)
        p_n[order] = x_n
        p_t[order] = x_t
        p_state[order] = states
        return np.flatnonzero(failed)
