"""The compiled paths of ``time_stepping`` on a small pile against straightforward references.

Parts dropped on a walled vibrating track (as ``benchmarks/pile.py``, fewer parts) give every kind
of island: single parts landing, small stacks projected out of the track, piles for the projected
Gauss-Seidel. Each compiled path is checked against the code it replaced while the simulation runs:
the per-contact rows (``_island_kernels.contact_rows``) bit for bit against numpy, the position
projection (``solve_small`` on the normal rows) against ``lcp.solve`` island by island, the PGS
kernel bit for bit against a plain transcription, and the vectorised impulse log bit for bit
against a running sum per feature. The PGS answers themselves are held to Baraff-Dantzig, to
their assembled LCPs, and to a stack of boxes in closed form: resting (each interface carries
the weight above) and sliding as one body (x = a t^2 / 2), at the piles' step and at four times
it.
"""

import math

from hypothesis import given, settings
from hypothesis import strategies as hs
import numpy as np
from paths import DATA
import pytest

from feeder_sim.compiled.arena import heap_state
from feeder_sim.contact import _island_kernels as K
from feeder_sim.contact import lcp
from feeder_sim.contact._feature_kernels import sum_by_feature
from feeder_sim.contact.collision import evaluate_gaps
from feeder_sim.model.builders import build, conveyor
from feeder_sim.simulator import ContactReport, Simulator
from feeder_sim.simulator.impulse_log import ImpulseLog
import feeder_sim.stepping.time_stepping.stepper as TS


def pile(n_parts, seed=1, materials=False, friction_impulse=True, compiled=False, mu=0.5):
    """``n_parts`` 20 x 10 mm boxes in staggered rows above a walled 0.4 m track (50 Hz),
    stepped by the Python reference step (the stages these tests hold to their references)
    or, with ``compiled``, by the compiled whole step."""
    length = 0.4
    scene = conveyor(psi=math.radians(30.0), mu=mu, theta=0.0, gamma=1.2, frequency_hz=50.0,
                     method='time_stepping', time_step=1e-3, n_parts=n_parts, walls=True,
                     track_length=length, spacing=0.03, friction_impulse=friction_impulse)
    rng = np.random.default_rng(seed)
    per_row = int((length - 0.04) // 0.03)
    parts = [b for b in scene['bodies'] if b['type'] == 'dynamic']
    for i, body in enumerate(parts):
        row, col = divmod(i, per_row)
        in_row = min(per_row, len(parts) - row * per_row)
        pitch = (length - 0.04) / per_row
        x = (col - 0.5 * (in_row - 1)) * pitch + (0.25 * pitch if row % 2 else 0.0)
        y = 0.02 + 0.02 * row + rng.uniform(0.0, 0.004)
        body['pose'] = [float(x + rng.uniform(-0.003, 0.003)), float(y),
                        float(rng.uniform(-0.3, 0.3))]
        if materials:
            # unequal static / dynamic friction (Kawachi's second pass) and restitution
            body['mu_static'] = float(rng.uniform(0.3, 0.7))
            body['mu_dynamic'] = 0.7 * body['mu_static']
            body['restitution'] = float(rng.choice([0.0, 0.3]))
    return Simulator(build(scene), settings=TS.TimeStepSettings(compiled=compiled))


def same_bits(x, y):
    x, y = np.asarray(x), np.asarray(y)
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.mark.parametrize('materials, friction_impulse', [(False, True), (True, False)])
def test_contact_rows_kernel_gives_the_numpy_bits(materials, friction_impulse):
    sim = pile(24, materials=materials, friction_impulse=friction_impulse)
    stepper = sim._stepper
    kernel = stepper._contact_rows
    checked = []

    def rows(*args):
        got = kernel(*args)
        ref = stepper._contact_rows_reference(*args)
        assert len(got) == len(ref)
        for i, (x, y) in enumerate(zip(got[:-1], ref[:-1], strict=True)):
            assert same_bits(x, y), f'output {i} differs at t = {sim.t}'
        assert got[-1] == ref[-1]
        checked.append(len(got[0]))
        return got

    stepper._contact_rows = rows
    sim.advance(0.2)
    assert len(checked) > 100 and sum(checked) > 2000


@pytest.mark.parametrize('reuse', [False, True])
def test_compiled_projection_matches_lcp_solve(reuse):
    # From scratch, the compiled projection solves lcp.solve's problems with its pivots; on
    # the row states of the contacts' last projection (reuse_row_states) it solves the same
    # problems to the same answers with fewer pivots (measured: 6 126 against 6 579 in this
    # settling pile, whose islands change from step to step).
    sim = pile(30)
    stepper = sim._stepper
    stepper.settings.reuse_row_states = reuse
    compiled = stepper._project
    st = sim.stats
    worst = [0.0, 0.0]
    projected = []
    pivots = [0, 0]         # compiled, reference

    def project(cs, state, mask):
        w = sim.world
        topo = w.shapes.derived
        idx = np.flatnonzero(mask)
        gap = K.feature_gaps(heap_state(), idx, cs.contacts.vertex_a, cs.contacts.edge_b,
                             w.shapes.vertices, w.shapes.normals, topo.vertex_body, state.position,
                             np.cos(state.angle), np.sin(state.angle))
        ref_gap = evaluate_gaps(w.shapes, cs.contacts, state.position, state.angle)[0]
        assert same_bits(gap, ref_gap[idx])
        ref = state.copy()
        before = (st.lcp_solves, st.lcp_rows, st.pivots, st.fallbacks, st.unconverged)
        stepper._project_reference(cs, ref, mask)
        mid = (st.lcp_solves, st.lcp_rows, st.pivots, st.fallbacks, st.unconverged)
        compiled(cs, state, mask)
        after = (st.lcp_solves, st.lcp_rows, st.pivots, st.fallbacks, st.unconverged)
        want, got = np.subtract(mid, before), np.subtract(after, mid)
        # the same problems, without a fallback
        assert got[[0, 1, 3, 4]].tolist() == want[[0, 1, 3, 4]].tolist()
        assert got[2] == want[2] if not reuse else got[2] <= want[2]
        pivots[0] += int(got[2])
        pivots[1] += int(want[2])
        if after != mid:
            projected.append(after[0] - mid[0])
        worst[0] = max(worst[0], float(np.abs(state.position - ref.position).max()))
        worst[1] = max(worst[1], float(np.abs(state.angle - ref.angle).max()))

    stepper._project = project
    sim.advance(0.25)
    assert sum(projected) > 50              # islands projected
    assert worst[0] <= 1e-12 and worst[1] <= 1e-12
    assert pivots[0] < pivots[1] if reuse else pivots[0] == pivots[1]


def jacobian_rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia):
    """Rows of J for body a (``ja``) and body b (``jb``) and of M^-1 J^T (``ma``, ``mb``):
    the c normal rows, then the c tangential rows."""
    c = len(a)
    ja, jb, ma, mb = (np.empty((2 * c, 3)) for _ in range(4))
    for i in range(2 * c):
        k = i if i < c else i - c
        dx, dy = (normal[k] if i < c else tangent[k]).tolist()
        ja[i] = dx, dy, r_a[k, 0] * dy - r_a[k, 1] * dx
        jb[i] = -dx, -dy, -(r_b[k, 0] * dy - r_b[k, 1] * dx)
        ma[i] = inv_mass[a[k]] * ja[i, 0], inv_mass[a[k]] * ja[i, 1], inv_inertia[a[k]] * ja[i, 2]
        mb[i] = inv_mass[b[k]] * jb[i, 0], inv_mass[b[k]] * jb[i, 1], inv_inertia[b[k]] * jb[i, 2]
    return ja, jb, ma, mb


def pgs_reference(select, starts, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n,
                  b_t, box, mu_lo, mu_hi, x_n, x_t, w_t, dv, tol, max_sweeps, check, omega,
                  momentum, height):
    """``pgs_in_order`` on each selected island's contacts sorted by ``height`` (stably)."""
    perm = np.arange(len(a))
    for isl in np.flatnonzero(select):
        r = perm[starts[isl]:starts[isl + 1]]
        r[:] = r[np.argsort(height[r], kind='stable')]
    s_x_n, s_x_t, s_w_t = x_n[perm], x_t[perm], w_t[perm]
    out = pgs_in_order(select, starts, a[perm], b[perm], normal[perm], tangent[perm], r_a[perm],
                       r_b[perm], inv_mass, inv_inertia, b_n[perm], b_t[perm], box[perm],
                       mu_lo[perm], mu_hi[perm], s_x_n, s_x_t, s_w_t, dv, tol, max_sweeps,
                       check, omega, momentum)
    x_n[perm], x_t[perm], w_t[perm] = s_x_n, s_x_t, s_w_t
    return out


def pgs_in_order(select, starts, a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n,
                 b_t, box, mu_lo, mu_hi, x_n, x_t, w_t, dv, tol, max_sweeps, check, omega,
                 momentum):
    """``solve_pgs`` as it was written before the sweep was tuned, in plain Python, with the
    conjugate gradient step of Silcowitz, Niebe and Erleben (2010) written as their paper
    states it (direction p, beta = |g_k|^2 / |g_k-1|^2, restart at beta > 1), the impulses
    projected after it."""
    c = len(a)
    g_n, g_t, p_n, p_t = (np.zeros(c) for _ in range(4))
    ja, jb, ma, mb = jacobian_rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia)
    diag = [ja[i, 0] * ma[i, 0] + ja[i, 1] * ma[i, 1] + ja[i, 2] * ma[i, 2] + jb[i, 0] * mb[i, 0]
            + jb[i, 1] * mb[i, 1] + jb[i, 2] * mb[i, 2] for i in range(2 * c)]
    step = [omega / d if d > 0.0 else 0.0 for d in diag]

    def row_w(i, k, bias):
        ia, ib = a[k], b[k]
        return (bias + ja[i, 0] * dv[ia, 0] + ja[i, 1] * dv[ia, 1] + ja[i, 2] * dv[ia, 2]
                + jb[i, 0] * dv[ib, 0] + jb[i, 1] * dv[ib, 1] + jb[i, 2] * dv[ib, 2])

    def row_add(i, k, d, into=dv):
        into[a[k]] += ma[i] * d
        into[b[k]] += mb[i] * d

    def residual(lo_c, hi_c):
        amax = bmax = xmax = 0.0
        for k in range(lo_c, hi_c):
            amax, bmax, xmax = max(amax, diag[k]), max(bmax, abs(b_n[k])), max(xmax, abs(x_n[k]))
            if box[k]:
                amax, bmax = max(amax, diag[k + c]), max(bmax, abs(b_t[k]))
                xmax = max(xmax, abs(x_t[k]))
        s_w = max(1e-300, max(bmax, amax * xmax))
        s_x = s_w / amax if amax > 0.0 else max(1e-300, xmax)
        r = rv = 0.0
        for k in range(lo_c, hi_c):
            w, x = row_w(k, k, b_n[k]), x_n[k]
            r = max(r, max(-x / s_x, max(-w / s_w, abs(x * w) / (s_x * s_w))))
            if diag[k] > 0.0:
                rv = max(rv, abs(x - max(x - w / diag[k], 0.0)) * diag[k])
            wt = w_t[k] = row_w(k + c, k, b_t[k])
            if box[k]:
                xj, xk = max(x, 0.0), x_t[k]
                dl, dh = xk + mu_lo[k] * xj, mu_hi[k] * xj - xk
                away = wt * max(dl, 0.0) if wt > 0.0 else -wt * max(dh, 0.0)
                r = max(r, max(-dl / s_x, max(-dh / s_x, away / (s_x * s_w))))
                if diag[k + c] > 0.0:
                    y = min(max(xk - wt / diag[k + c], -mu_lo[k] * xj), mu_hi[k] * xj)
                    rv = max(rv, abs(xk - y) * diag[k + c])
        return max(r, 0.0), rv

    def sweep(lo_c, hi_c):
        change = 0.0
        for k in range(lo_c, hi_c):
            xn = max_(x_n[k] - step[k] * row_w(k, k, b_n[k]))
            d = xn - x_n[k]
            if d != 0.0:
                change = max(change, abs(d) * diag[k])
                row_add(k, k, d)
                x_n[k] = xn
                g_n[k] += d
            i = k + c
            if x_n[k] == 0.0:
                d = -x_t[k]
                if d != 0.0:
                    change = max(change, abs(d) * diag[i])
                    row_add(i, k, d)
                    x_t[k] = 0.0
                    g_t[k] += d
            elif box[k]:
                xt = x_t[k] - step[i] * row_w(i, k, b_t[k])
                xt = min(max(xt, -mu_lo[k] * x_n[k]), mu_hi[k] * x_n[k])
                d = xt - x_t[k]
                if d != 0.0:
                    change = max(change, abs(d) * diag[i])
                    row_add(i, k, d)
                    x_t[k] = xt
                    g_t[k] += d
        return change

    def conjugate_step(lo_c, hi_c, bodies, dv0, P, rr_old):
        # the velocities follow the impulses: P = M^-1 J^T p body by body, and only the
        # part of a move the projection cuts off is pushed through its contact
        rr = sum(g_n[k] * g_n[k] + g_t[k] * g_t[k] for k in range(lo_c, hi_c))
        beta = rr / rr_old
        if not beta <= 1.0:
            P[bodies] = 0.0
            dv0[bodies] = dv[bodies]
            for arr in (p_n, p_t, g_n, g_t):
                arr[lo_c:hi_c] = 0.0
            return rr
        for i in bodies:
            step_i = beta * P[i]
            P[i] = (dv[i] - dv0[i]) + step_i
            dv[i] += step_i
        for k in range(lo_c, hi_c):
            free = x_n[k] + beta * p_n[k]
            xn = max_(free)
            if xn - free != 0.0:
                row_add(k, k, xn - free)
                row_add(k, k, xn - free, P)
            p_n[k] = g_n[k] + (xn - x_n[k])
            x_n[k], g_n[k] = xn, 0.0
            free = x_t[k] + beta * p_t[k]
            xt = min(max(free, -mu_lo[k] * xn), mu_hi[k] * xn) if box[k] else 0.0
            if xt - free != 0.0:
                row_add(k + c, k, xt - free)
                row_add(k + c, k, xt - free, P)
            p_t[k] = g_t[k] + (xt - x_t[k])
            x_t[k], g_t[k] = xt, 0.0
        dv0[bodies] = dv[bodies]
        return rr

    def max_(x):
        return 0.0 if x < 0.0 else x

    n_isl = len(starts) - 1
    res, vres, work = np.zeros(n_isl), np.zeros(n_isl), np.zeros(n_isl, np.int64)
    for isl in np.flatnonzero(select):
        lo_c, hi_c = starts[isl], starts[isl + 1]
        for k in range(lo_c, hi_c):
            if not (x_n[k] > 0.0):
                x_n[k] = 0.0
            x_t[k] = min(max(x_t[k], -mu_lo[k] * x_n[k]), mu_hi[k] * x_n[k]) if box[k] else 0.0
            row_add(k, k, x_n[k])
            row_add(k + c, k, x_t[k])
        r, rv = residual(lo_c, hi_c)
        bodies = sorted({int(i) for k in range(lo_c, hi_c) for i in (a[k], b[k])
                         if inv_mass[i] != 0.0 or inv_inertia[i] != 0.0})
        dv0, P = dv.copy(), np.zeros_like(dv)
        s, rr = 0, math.inf
        while rv > tol and s < max_sweeps:
            for _ in range(min(check, max_sweeps - s)):
                change = sweep(lo_c, hi_c)
                s += 1
            if change <= tol or s >= max_sweeps:
                r, rv = residual(lo_c, hi_c)
                if rv <= tol or s >= max_sweeps:
                    break
            if momentum:
                rr = conjugate_step(lo_c, hi_c, bodies, dv0, P, rr)
        res[isl], vres[isl], work[isl] = r, rv, s
    return res, vres, work


def flat_pgs_args(args):
    """Copies of a ``solve_pgs`` call's arguments, flat as the transcriptions take them:
    0 arena, 1 select, 2-10 the ``IslandRows`` (2 starts, 3 a, 4 b, 5 normal, 6 tangent, 7 r_a,
    8 r_b, 9 inv_mass, 10 inv_inertia), 11-15 the ``RowProblem`` (11 b_n, 12 b_t, 13 box,
    14 mu_lo, 15 mu_hi), 16-18 the ``RowImpulses`` (16 x_n, 17 x_t, 18 w_t), 19 dv, 20-24 the
    ``PgsSettings`` (20 tol, 21 max_sweeps, 22 check, 23 omega, 24 momentum), 25 height."""
    ar, select, rows, problem, out, dv, pgs, height = args
    return [x.copy() if isinstance(x, np.ndarray) else x
            for x in (ar, select, *rows, *problem, *out, dv, *pgs, height)]


def pgs_args(flat):
    """The arguments of ``solve_pgs`` from ``flat_pgs_args``' list (its arrays, not copies)."""
    return (flat[0], flat[1], K.IslandRows(*flat[2:11]), K.RowProblem(*flat[11:16]),
            K.RowImpulses(*flat[16:19]), flat[19], K.PgsSettings(*flat[20:25]), flat[25])


def pgs_calls(sim, t_end):
    """Copies of the arguments of every ``solve_pgs`` call while ``sim`` advances to
    ``t_end`` (s), flat (``flat_pgs_args``)."""
    kernel, calls = TS.K.solve_pgs, []

    def solve_pgs(*args):
        calls.append(flat_pgs_args(args))
        return kernel(*args)

    TS.K.solve_pgs = solve_pgs
    try:
        sim.advance(t_end)
    finally:
        TS.K.solve_pgs = kernel
    return calls


def test_pgs_kernel_gives_the_bits_of_a_plain_transcription():
    sim = pile(24)
    sim._stepper.settings.direct_max_rows = 0      # every island to PGS
    sim.advance(0.15)
    calls = pgs_calls(sim, 0.16)
    kernel = TS.K.solve_pgs
    assert calls
    sweeps = 0
    for args in calls:
        ref_args = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
        got = kernel(*pgs_args(args))
        ref = pgs_reference(*ref_args[1:])          # (the kernel's first: its scratch arena)
        for x, y in zip(got, ref, strict=True):
            assert same_bits(x, y)
        for i in (16, 17, 18, 19):                  # x_n, x_t, w_t, dv
            assert same_bits(args[i], ref_args[i])
        sweeps += int(got[2].sum())
    assert sweeps > 100


class _RunningLog:
    """The impulse log as it was: a dict of running sums, features in order of appearance."""

    def __init__(self):
        self.rows = {}

    def add(self, sc):
        c = sc.cs.contacts
        for i in range(c.n):
            key = (int(c.vertex_a[i]), int(c.edge_b[i]))
            row = self.rows.get(key)
            if row is None:
                self.rows[key] = [c.point[i], c.normal[i], float(sc.normal_impulse[i]),
                                  float(sc.tangent_impulse[i]), int(c.body_a[i]),
                                  int(c.body_b[i])]
            else:
                row[0], row[1] = c.point[i], c.normal[i]
                row[2] += float(sc.normal_impulse[i])
                row[3] += float(sc.tangent_impulse[i])

    def take(self):
        rows = [r for r in self.rows.values() if r[2] > 0.0]
        self.rows = {}
        if not rows:
            z = np.zeros(0)
            return ContactReport(np.zeros((0, 2)), np.zeros((0, 2)), z, z.copy(),
                                 np.zeros(0, int), np.zeros(0, int))
        return ContactReport(*(np.array([r[i] for r in rows]) for i in range(6)))


def pgs_problems(mu, n_parts=40):
    """The arguments of every ``solve_pgs`` call of five steps of a settling pile, every island
    through PGS."""
    sim = pile(n_parts, mu=mu)
    sim._stepper.settings.direct_max_rows = 0
    sim.advance(0.2)
    return pgs_calls(sim, 0.205)


def run_pgs(args, tol, momentum, max_sweeps=100_000):
    args = [x.copy() if isinstance(x, np.ndarray) else x for x in args]
    args[20:22], args[24] = (tol, max_sweeps), momentum
    res, vres, sweeps = TS.K.solve_pgs(*pgs_args(args))
    return args, vres, sweeps


def island_problem(args, isl):
    """Island ``isl`` of a ``solve_pgs`` call assembled as ``dynamics.assemble`` lays it out:
    (the FrictionalLCP, its rows as (contact, is friction row))."""
    a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n, b_t, box, mu_lo, mu_hi = \
        args[3:16]
    c = len(a)
    ja, jb, ma, mb = jacobian_rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia)
    k = range(args[2][isl], args[2][isl + 1])
    rows = [(kp, False) for kp in k] + [(kp, True) for kp in k if box[kp]]
    g = [kp + c if f else kp for kp, f in rows]
    A = np.array([[(a[rows[p][0]] == a[rows[q][0]]) * ma[gp] @ ja[gq]
                   + (a[rows[p][0]] == b[rows[q][0]]) * ma[gp] @ jb[gq]
                   + (b[rows[p][0]] == a[rows[q][0]]) * mb[gp] @ ja[gq]
                   + (b[rows[p][0]] == b[rows[q][0]]) * mb[gp] @ jb[gq]
                   for q, gq in enumerate(g)] for p, gp in enumerate(g)])
    normal_of = [k.index(kp) if f else -1 for kp, f in rows]
    problem = lcp.FrictionalLCP(A, [b_t[kp] if f else b_n[kp] for kp, f in rows], normal_of,
                                [mu_lo[kp] if f else 0.0 for kp, f in rows],
                                [mu_hi[kp] if f else 0.0 for kp, f in rows])
    return problem, rows


def test_pgs_with_conjugate_steps_reaches_dantzigs_velocities_in_fewer_sweeps():
    """Without friction the bodies' velocity changes M^-1 J^T x are unique (they minimise the
    kinetic energy of the change under the contact constraints), so PGS at a tight tolerance
    must reach those of Baraff-Dantzig on the assembled problem, with the conjugate steps or
    without; with them in fewer sweeps. Angular velocities count times the parts' corner
    radius."""
    calls = pgs_problems(mu=0.0)
    radius = math.hypot(0.01, 0.005)                # the parts' corner radius, m
    worst, compared, sweeps = {False: 0.0, True: 0.0}, 0, {False: 0, True: 0}
    for args in calls:
        a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia, b_n = args[3:12]
        box = args[13]
        assert not box.any()                        # no friction rows at mu = 0
        ja, jb, ma, mb = jacobian_rows(a, b, normal, tangent, r_a, r_b, inv_mass, inv_inertia)
        got = {}
        for momentum in (False, True):
            out, vres, work = run_pgs(args, 1e-8, momentum)
            got[momentum] = out[19]
            sweeps[momentum] += int(work[args[1]].sum())
            assert (vres[args[1]] <= 1e-8).all()
        starts = args[2]
        for isl in np.flatnonzero(args[1]):
            k = np.arange(starts[isl], starts[isl + 1])
            problem, rows = island_problem(args, isl)
            result = lcp.solve(problem, methods=('dantzig',))
            assert result.method == 'dantzig' and result.residual <= 1e-9
            ref = np.zeros_like(args[19])
            for p, kp in enumerate(k):
                ref[a[kp]] += ma[kp] * result.x[p]
                ref[b[kp]] += mb[kp] * result.x[p]
            moving = np.unique(np.concatenate([a[k], b[k]]))
            for momentum in (False, True):
                err = np.abs(got[momentum][moving] - ref[moving]) * [1.0, 1.0, radius]
                worst[momentum] = max(worst[momentum], float(err.max()))
            compared += len(k)
    # measured: 1.0e-8 m/s for both over 613 contacts, in 48 016 and 4 954 sweeps
    assert compared > 60
    assert max(worst.values()) <= 1e-7             # m/s (10 x the velocity residual)
    assert sweeps[True] < 0.5 * sweeps[False]


def test_pgs_with_conjugate_steps_solves_a_frictional_pile_in_fewer_sweeps():
    """With friction the answer of a pile need not be unique. Each island's impulses must
    solve its LCP, assembled densely here, to the velocity residual asked for (the largest
    velocity change one more projected Gauss-Seidel step would make, A_ii |x_i -
    proj(x_i - w_i / A_ii)|), with the conjugate steps as without, in fewer sweeps, and lie
    within their bounds (every answer is a sweep's)."""
    calls = pgs_problems(mu=0.5)
    sweeps, worst, frictional = {False: 0, True: 0}, 0.0, 0
    for args in calls:
        for momentum in (False, True):
            out, vres, work = run_pgs(args, 1e-7, momentum)
            sweeps[momentum] += int(work[args[1]].sum())
            x_n, x_t = out[16], out[17]
            for isl in np.flatnonzero(args[1]):
                assert vres[isl] <= 1e-7
                problem, rows = island_problem(args, isl)
                x = np.array([x_t[k] if f else x_n[k] for k, f in rows])
                w = problem.A @ x + problem.b
                d = np.diag(problem.A)
                y = x - w / d
                of = problem.normal_of
                bound = np.where(of >= 0, x[np.maximum(of, 0)], 0.0)   # its normal impulse
                y = np.where(of >= 0, np.clip(y, -problem.mu_lo * bound, problem.mu_hi * bound),
                             np.maximum(y, 0.0))
                worst = max(worst, float(np.max(np.abs(x - y) * d)))
                frictional += int((of >= 0).sum())
                k = np.arange(args[2][isl], args[2][isl + 1])
                assert (x_n[k] >= 0.0).all()
                assert (x_t[k] >= -args[14][k] * x_n[k]).all()
                assert (x_t[k] <= args[15][k] * x_n[k]).all()
    # measured: 6.4e-8 m/s over 874 friction rows; 11 572 and 2 122 sweeps
    assert frictional > 100
    assert worst <= 1e-7 * (1 + 1e-6)               # m/s
    assert sweeps[True] < 0.5 * sweeps[False]


@pytest.mark.parametrize('reduce_steps', [64, 3])
def test_impulse_log_reports_the_running_sums(reduce_steps):
    sim = pile(30)
    log, ref = ImpulseLog(), _RunningLog()
    log._REDUCE_STEPS = reduce_steps            # 3: many reductions between two reports
    rng = np.random.default_rng(0)
    next_take, reports, rows = 40, 0, 0
    for k in range(300):
        sc = sim._stepper.step(sim.state)
        if sc is not None:
            log.add(sc)
            ref.add(sc)
        if k == next_take:
            next_take += int(rng.integers(1, 60))
            got, want = log.take(), ref.take()
            for f in ('point', 'normal', 'normal_impulse', 'tangent_impulse', 'body_a',
                      'body_b'):
                assert same_bits(getattr(got, f), getattr(want, f)), f
            reports += 1
            rows += got.n
    assert reports >= 5 and rows > 200
    assert log.take().n == ref.take().n


@settings(max_examples=60, deadline=None)
@given(hs.lists(hs.tuples(hs.sampled_from([0, 1, 7, 2**32, 2**32 + 1, 2**40 - 3, 2**62, 5 << 32]),
                          hs.sampled_from([0.0, -0.0, 1e-300, 0.1, -0.3, 2.5e3])),
                min_size=1, max_size=400))
def test_features_are_summed_like_a_running_sum(rows):
    # sum_by_feature, the impulse log's reduction, on keys chosen to share hash slots (equal
    # low or high bits) and impulses whose order of summation shows in the last bits, and
    # with signed zeros: the same bits as adding row by row from -0.0 in a dict, features in
    # order of first appearance.
    key = np.array([k for k, _ in rows], np.int64)
    p = np.array([v for _, v in rows])
    row_id = np.arange(len(rows))
    point = np.stack([row_id * 1.0, -row_id * 1.0], axis=1)
    want: dict[int, list] = {}
    for i, k in enumerate(key.tolist()):
        entry = want.setdefault(k, [-0.0, -0.0, i])
        entry[0] += p[i]
        entry[1] += 2.0 * p[i]
        entry[2] = i
    got = sum_by_feature(key, point, -point, p, 2.0 * p, row_id, row_id + 1)
    assert got[0].tolist() == list(want)
    assert same_bits(got[3], np.array([e[0] for e in want.values()]))
    assert same_bits(got[4], np.array([e[1] for e in want.values()]))
    latest = np.array([e[2] for e in want.values()])
    assert got[5].tolist() == latest.tolist() and got[6].tolist() == (latest + 1).tolist()
    assert same_bits(got[1], point[latest]) and same_bits(got[2], -point[latest])


def test_a_deep_wedge_in_a_pile_is_not_thrown_apart():
    """Piles push penetration out through the velocities; the push is capped, so a contact
    left 0.4 mm deep (as an unconverged PGS can leave a jammed queue) does not turn into a
    0.8 m/s kick (push_out * depth * 2 / h at h = 0.2 ms)."""
    from feeder_sim.model.scene import parse_scene
    box = [[-0.01, -0.005], [0.01, -0.005], [0.01, 0.005], [-0.01, 0.005]]
    mat = {'mu_static': 0.5, 'mu_dynamic': 0.5, 'restitution': 0.0}
    bodies = [{'name': 'floor', 'type': 'static', 'polygon': [[-1, -0.1], [1, -0.1], [1, 0],
                                                              [-1, 0]],
               'pose': [0.0, 0.0, 0.0], **mat}]
    y = 0.005
    for k in range(14):             # 14 stacked boxes: 15 interfaces, 60 rows > 48 -> PGS
        y += -0.0004 if k == 7 else 0.0
        bodies.append({'name': f'box_{k}', 'type': 'dynamic', 'polygon': box, 'mass': 0.01,
                       'pose': [0.001 * (k % 2), y, 0.0], **mat})
        y += 0.01
    scene = parse_scene({'bodies': bodies, 'solver': {'method': 'time_stepping',
                                                      'time_step': 2e-4}})
    sim = Simulator(scene)
    sim.advance(2e-4)
    assert sim.stats.pgs_solves == 1 and sim.stats.max_penetration_m == pytest.approx(4e-4)
    speed = np.hypot(*sim.state.velocity[1:].T)
    # at most the cap (push_max_mps, 0.02 m/s) and a step of gravity; uncapped: 0.77 m/s
    assert speed.max() <= 0.02 + 9.81 * 2e-4, speed.max()


def test_projection_of_a_wedged_cup_stays_within_its_overlap():
    """A cup tilted between two magazine walls, a corner 0.06 mm into the cup below: the normal
    rows are nearly dependent and the linearised projection moved the lower cup 39 mm and
    415 deg in one step. No point of a body may move more than ``projection_reach`` times its
    island's summed overlap."""

    import yaml

    from feeder_sim.model.scene import parse_scene

    here = DATA
    sim = Simulator(parse_scene(yaml.safe_load((here / 'wedged_cups.yaml').read_text())))
    st = sim.state
    st.t = 1.0657999999999153
    st.position[:] = [[-0.05880342189883539, 0.006242490914663512], [-0.05975, -0.002],
                      [-0.041749999999999995, 0.0538],
                      [-0.019250000000000003, 0.053799999999999994],
                      [-0.02690721851223886, 0.0060030789645076545],
                      [-0.02791234461838509, 0.017014717760373128]]
    st.angle[:] = [0.0, 0.0, 0.0, 0.0, 3.141025313684357, 3.2984685160165053]
    st.velocity[:] = [[0.03786461018217708, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0],
                      [0.037169288122609424, -0.0008375884096887781],
                      [-0.008698679733910978, -0.016678366627756347]]
    st.omega[:] = [0.0, 0.0, 0.0, 0.0, 0.15439207568236862, 1.5257331770017224]
    sim.world.apply_prescribed_motion(st)
    stepper = sim._stepper
    stepper.settings.compiled = False       # the Python step, whose projection is watched
    moves = []
    project = stepper._project

    def recording(cs, state, mask):
        before = state.copy()
        project(cs, state, mask)
        w = sim.world
        gap = evaluate_gaps(w.shapes, cs.contacts, before.position, before.angle)[0][mask]
        overlap = float(np.maximum(-gap, 0.0).sum())
        reach = (np.hypot(*(state.position - before.position).T)
                 + np.abs(state.angle - before.angle) * w.radius)
        moves.append((float(reach.max()), overlap))

    stepper._project = recording
    sim.advance(st.t + sim.scene.solver.time_step)
    (reach, overlap), = moves
    assert 0.0 < overlap < 1e-3
    # the summed overlap of the island bounds the move (2x: ``projection_reach``)
    assert reach <= stepper.settings.projection_reach * overlap * (1 + 1e-9)
    assert np.all(np.abs(sim.state.angle[4:] - [3.141, 3.298]) < 0.05)


# The partition orienter's magazine at 0.8786 s as the stepper left it before the projection
# respected the contacts left out of the velocity solve: five cups stacked with relative tilts
# of a few degrees, each pair touching at both ends.
MAGAZINE_T = 0.8785999999999359
MAGAZINE_CUPS = {   # name: (x, y, angle, vx, vy, omega)
    'cup_1': (-0.02753191001451683, 0.01772561879173554, 3.0684849805784604,
              0.004444145883508601, -0.011781468886746945, -0.8635301925061044),
    'cup_2': (-0.027301164335268628, 0.029711319871175274, 3.0655464875041667,
              0.007334892259380353, -0.020838963177421885, -2.146216662942655),
    'cup_3': (-0.03242750546580298, 0.041996137567246544, -0.06282920635013423,
              0.003707332061462769, -0.0376222266142593, 0.8653960573977564),
    'cup_4': (-0.02727943258868331, 0.05365813755632402, 3.074891666472756,
              0.003988612962791372, -0.044586779660973797, -0.4644282207743504),
    'cup_5': (-0.03241599650360312, 0.06596433233424477, -0.060709550527064,
              0.0028831375370132026, -0.052114206985042176, 0.5689164703169589),
}


def _deepest_overlap_between(sim, names):
    from feeder_sim.contact.collision import find_contacts
    w, st = sim.world, sim.state
    c = find_contacts(w.shapes, st.position, st.angle, w.dynamic, margin=0.0, depth=3e-3)
    idx = [w.names.index(n) for n in names]
    both = np.isin(c.body_a, idx) & np.isin(c.body_b, idx)
    return float(-c.gap[both].min(initial=0.0))


def test_projection_keeps_a_tilted_stack_out_of_itself():
    """Cups stacked with slight relative tilts touch at both ends of each pair. A step that
    solved only the end it saw closing projected that overlap out by turning the cup into the
    other end, and the next step did the reverse: the stack flip-flopped 0.1 mm deep. With the
    contacts the step left out kept as projection rows it stays out of itself."""
    sim = Simulator('orienter_partition')
    st = sim.state
    # the slide where it was then; the cup in flight and those below are far away
    sim.world.apply_prescribed_motion(st)
    st.t = MAGAZINE_T
    for name, (x, y, a, vx, vy, om) in MAGAZINE_CUPS.items():
        i = sim.world.names.index(name)
        st.position[i] = (x, y)
        st.angle[i] = a
        st.velocity[i] = (vx, vy)
        st.omega[i] = om
    cup_0 = sim.world.names.index('cup_0')
    st.position[cup_0] = (-0.007, -0.195)       # resting in the bin, out of the way
    st.angle[cup_0] = np.pi / 2
    st.velocity[cup_0] = 0.0
    st.omega[cup_0] = 0.0
    sim.world.apply_prescribed_motion(st)
    cups = list(MAGAZINE_CUPS)
    assert _deepest_overlap_between(sim, cups) > 1e-4     # as it was left: 0.2 mm
    worst = 0.0
    for k in range(1, 51):
        sim.advance(MAGAZINE_T + k * 2e-4)
        if k >= 5:      # the capped projection takes a few steps to remove the 0.2 mm
            worst = max(worst, _deepest_overlap_between(sim, cups))
    # without those rows: 0.13-0.19 mm, every other step
    assert worst < 1e-8, worst


@pytest.mark.parametrize('materials, friction_impulse, direct_max_rows', [
    (False, True, 48), (True, False, 48), (True, True, 0)])
def test_compiled_whole_step_gives_the_bits_of_the_reference_step(materials, friction_impulse,
                                                                  direct_max_rows):
    """Frames of the compiled whole step against the Python step, bit for bit: states,
    every counter and the contact reports. Restitution (half the parts) sends steps back to
    the Python step mid-frame; tiny report buffers make the kernel ask for larger ones."""
    runs = []
    for compiled in (True, False):
        sim = pile(24, materials=materials, friction_impulse=friction_impulse,
                   compiled=compiled)
        sim._stepper.settings.direct_max_rows = direct_max_rows
        if compiled:
            sim._stepper._reports = TS.TK.new_reports(1)
        frames = []
        for k in range(1, 31):
            sim.advance(k * 0.01)
            s, rep = sim.state, sim.take_contacts()
            frames.append([s.position.copy(), s.angle.copy(), s.velocity.copy(),
                           s.omega.copy(), rep.point, rep.normal, rep.normal_impulse,
                           rep.tangent_impulse, rep.body_a, rep.body_b])
        runs.append((frames, sim.stats.as_dict()))
    (got, got_stats), (ref, ref_stats) = runs
    for k, (x, y) in enumerate(zip(got, ref, strict=True)):
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            assert same_bits(u, v), f'frame {k}, field {i}'
    assert got_stats == ref_stats
    assert ref_stats['lcp_solves'] > 500 and ref_stats['steps'] == 300
    if direct_max_rows == 0:
        assert ref_stats['pgs_solves'] > 100


@pytest.mark.parametrize('n_parts', [1, 12, 60])
def test_the_compiled_step_allocates_nothing_per_step(n_parts):
    # Every scratch array of a compiled step comes from the stepper's arenas, so numba's
    # allocation count over one advance call is the same for 10 steps as for 100: what a call
    # costs (its arguments' wrappers, the warm impulses handed back), never a step. 60 parts
    # make a pile (PGS); 12 small islands (Dantzig); 1 part a single contact pair.
    from numba.core.runtime import _nrt_python, rtsys

    sim = pile(n_parts, compiled=True)
    sim.advance(0.3)                         # landed, and the arenas grown to what it takes
    stepper, h = sim._stepper, sim._stepper.spec.time_step
    counts = []
    _nrt_python.memsys_enable_stats()
    try:
        for steps in (10, 100):
            before = rtsys.get_allocation_stats().alloc
            code = stepper._advance_compiled(sim.state, sim.state.t + steps * h, [])
            assert code == TS.TK.DONE
            counts.append(rtsys.get_allocation_stats().alloc - before)
    finally:
        _nrt_python.memsys_disable_stats()
    assert stepper.stats.pgs_solves > 0 if n_parts == 60 else stepper.stats.lcp_solves > 0
    assert counts[0] == counts[1] < 100


def test_arenas_too_small_give_the_same_steps_and_grow():
    # A step whose scratch does not fit its arena takes the rest from overflow blocks: the
    # same bits as a step with room, every block freed by the end of the call, and the
    # stepper doubles its arenas for the next call.
    from feeder_sim.compiled.arena import BLOCKS, N_BLOCKS, new_arena, SHORT

    roomy, cramped = pile(12, compiled=True), pile(12, compiled=True)
    small = (new_arena(64), new_arena(64))
    cramped._stepper._arenas = small
    roomy.advance(0.3)
    cramped.advance(0.3)
    assert roomy.state.position.tobytes() == cramped.state.position.tobytes()
    assert roomy.state.velocity.tobytes() == cramped.state.velocity.tobytes()
    assert all(a.buf.shape[0] > 1024 for a in cramped._stepper._arenas)
    for arena in small:
        assert arena.state[SHORT] > 0
        assert arena.state[N_BLOCKS] == 0 and arena.state[BLOCKS] == 0


G, PGS_TOL = 9.81, 1e-9      # m/s^2; the stacks' PGS velocity residual, m/s
STACK = 6
BOX_KG = 0.01


def box_stack(n_boxes, tilt_rad, h, mu_track, mu_boxes, momentum, compiled):
    """``n_boxes`` flat 40 x 5 mm boxes (10 g) stacked exactly touching on a level, still
    track, gravity tilted by ``tilt_rad``, every island through PGS to 1e-9 m/s."""
    scene = conveyor(psi=math.radians(30.0), mu=mu_track, theta=0.0, gamma=1.0,
                     frequency_hz=50.0, method='time_stepping', time_step=h, n_parts=n_boxes,
                     track_length=0.4, spacing=0.05)
    del scene['bodies'][0]['vibration']
    for k, body in enumerate(scene['bodies'][1:]):
        body['polygon'] = [[-0.02, -0.0025], [0.02, -0.0025], [0.02, 0.0025], [-0.02, 0.0025]]
        body['pose'] = [0.0, 0.0025 + 0.005 * k, 0.0]
        body['mu_static'] = body['mu_dynamic'] = mu_boxes
    scene['gravity'] = [G * math.sin(tilt_rad), -G * math.cos(tilt_rad)]
    return Simulator(build(scene), settings=TS.TimeStepSettings(
        compiled=compiled, direct_max_rows=0, pgs_tol_mps=PGS_TOL, pgs_max_sweeps=100_000,
        pgs_momentum=momentum))


@pytest.mark.parametrize('h', [1e-3, 4e-3])         # the piles' step, and four times it
@pytest.mark.parametrize('momentum', [True, False])
def test_a_resting_stack_carries_the_weight_above_each_interface(h, momentum):
    """Statics: tilted 15 deg (below the friction angle, and the stack stays upright), the
    boxes stay put and the impulse the layer below gives box k in each step is the weight
    of boxes k..n-1 times h, whatever the split between the corners (the PGS answer, the
    conjugate steps and the bottom-up order included). Bound: the velocity residual
    ``PGS_TOL`` of every box, ten times over, against one box's weight impulse."""
    sim = box_stack(STACK, math.radians(15.0), h, 0.5, 0.5, momentum, compiled=False)
    g = sim.world.gravity
    start = sim.state.position.copy()
    worst = 0.0
    for _ in range(int(round(0.1 / h))):
        sc = sim._stepper.step(sim.state)
        c = sc.cs.contacts
        on_a = sc.normal_impulse[:, None] * c.normal + sc.tangent_impulse[:, None] * sc.cs.tangent
        assert sim.stats.pgs_solves and not sim.stats.unconverged
        for k in range(STACK):
            upper, lower = k + 1, k             # body 0 is the track
            got = np.zeros(2)
            for q in range(len(on_a)):
                if {int(c.body_a[q]), int(c.body_b[q])} == {upper, lower}:
                    got += on_a[q] if c.body_a[q] == upper else -on_a[q]
            want = -(STACK - k) * BOX_KG * g * h
            worst = max(worst, float(np.abs(got - want).max()) / (BOX_KG * G * h))
    # measured: 4.5e-7 and 3.7e-7 (1 ms), 8.8e-8 and 4.6e-8 (4 ms); drift 1e-11 m
    assert worst <= 10 * STACK * PGS_TOL / (G * h)
    assert np.abs(sim.state.position - start).max() <= 1e-9


@pytest.mark.parametrize('h', [1e-3, 4e-3])
@pytest.mark.parametrize('momentum', [True, False])
def test_a_stack_slides_as_one_body_down_the_closed_form(h, momentum):
    """Dynamics: tilted 30 deg, the track's contact mu sqrt(0.2 x 0.8) = 0.4 < tan 30 deg, the
    boxes' 0.8 (each interface needs 0.4 of its normal impulse: they stick). The stack slides
    as one body with a = g (sin 30 - 0.4 cos 30) from rest: x = a t^2 / 2 and v = a t, which
    the midpoint scheme integrates exactly at constant acceleration, so what is left is
    the PGS tolerance. The compiled whole step, as a run takes it."""
    tilt = math.radians(30.0)
    sim = box_stack(STACK, tilt, h, 0.2, 0.8, momentum, compiled=True)
    x0, y0 = sim.state.position[1:, 0].copy(), sim.state.position[1:, 1].copy()
    sim.advance(0.1)
    acc = G * (math.sin(tilt) - math.sqrt(0.2 * 0.8) * math.cos(tilt))
    assert sim.stats.pgs_solves and not sim.stats.unconverged
    # measured: within 7e-10 of x, 5e-10 m/s of v, 1e-11 m of y at both steps
    assert np.allclose(sim.state.position[1:, 0] - x0, 0.5 * acc * sim.t ** 2, rtol=1e-8, atol=0)
    assert np.abs(sim.state.velocity[1:, 0] - acc * sim.t).max() <= 10 * PGS_TOL
    assert np.abs(sim.state.position[1:, 1] - y0).max() <= 1e-9
