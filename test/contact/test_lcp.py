"""The frictional LCP solver: exact small cases, the reference rod impact, random Delassus
problems, degenerate input and the fallback ladder."""

import json
import math
import time

import numpy as np
from paths import DATA
import pytest

from feeder_sim.contact.lcp import FrictionalLCP, LCPResult, residual, solve

ALL = ('dantzig', 'lemke', 'pgs', 'frictionless')


def cross(r, v):
    return r[0] * v[1] - r[1] * v[0]


def problem(A, b, normal_of, mu_lo=None, mu_hi=None):
    m = len(b)
    mu_lo = np.zeros(m) if mu_lo is None else mu_lo
    mu_hi = mu_lo if mu_hi is None else mu_hi
    return FrictionalLCP(np.asarray(A, float), np.asarray(b, float), np.asarray(normal_of),
                         np.asarray(mu_lo, float), np.asarray(mu_hi, float))


def friction_problem(W, b, mu_lo, mu_hi):
    """Rows [N_0..N_{c-1}, T_0..T_{c-1}] of a 2c x 2c Delassus problem."""
    c = len(mu_lo)
    return problem(W, b, np.r_[np.full(c, -1), np.arange(c)], np.r_[np.zeros(c), mu_lo],
                   np.r_[np.zeros(c), mu_hi])


# ---------------------------------------------------------------------------------------------
# exact small cases


@pytest.mark.parametrize('a, b', [(2.0, -3.0), (0.37, -1e-3), (5.0, 4.0), (1e-6, -2e6),
                                  (3.0, 0.0)])
def test_one_frictionless_contact_is_exact(a, b):
    for method in ('dantzig', 'lemke', 'pgs', 'frictionless'):
        res = solve(problem([[a]], [b], [-1]), methods=(method,))
        assert res.converged
        assert res.x[0] == max(0.0, -b / a)      # exactly, not approximately
        assert res.residual == 0.0


def box_on_flat():
    """1 kg box 0.02 x 0.01 m resting on its long face: contacts at the two bottom corners."""
    w, h, m = 0.02, 0.01, 1.0
    inertia = m * (w * w + h * h) / 12.0
    corners = [np.array([-w / 2, -h / 2]), np.array([w / 2, -h / 2])]
    n, t = np.array([0.0, 1.0]), np.array([1.0, 0.0])
    J = np.array([[*n, cross(r, n)] for r in corners] + [[*t, cross(r, t)] for r in corners])
    Minv = np.diag([1 / m, 1 / m, 1 / inertia])
    return J, J @ Minv @ J.T


@pytest.mark.parametrize('method', ['dantzig', 'lemke', 'pgs'])
def test_box_landing_flat_stops_with_static_friction(method):
    J, W = box_on_flat()
    v = np.array([0.05, -0.3, 0.0])        # sliding 5 cm/s while falling 30 cm/s
    mu = np.full(2, 0.5)                    # needs |p_T| / p_N = 1/6 < 0.5
    res = solve(friction_problem(W, J @ v, mu, mu), methods=(method,), tol=1e-12)
    assert res.converged
    v_post = W @ res.x + J @ v              # contact velocities after the impulse
    np.testing.assert_allclose(v_post, 0.0, atol=1e-9)
    assert res.x[:2].sum() == pytest.approx(0.3, rel=1e-9)     # m |v_y|; split indeterminate
    assert res.x[2:].sum() == pytest.approx(-0.05, rel=1e-9)
    assert np.all(np.abs(res.x[2:]) <= mu * res.x[:2] * (1 + 1e-9) + 1e-15)


@pytest.mark.parametrize('method', ['dantzig', 'lemke'])
def test_box_landing_flat_keeps_sliding_when_friction_saturates(method):
    J, W = box_on_flat()
    v = np.array([0.05, -0.3, 0.0])
    mu = np.full(2, 0.1)
    res = solve(friction_problem(W, J @ v, mu, mu), methods=(method,))
    assert res.converged
    v_post = W @ res.x + J @ v
    np.testing.assert_allclose(v_post[:2], 0.0, atol=1e-12)
    np.testing.assert_allclose(v_post[2:], 0.05 - 0.1 * 0.3, rtol=1e-9)
    np.testing.assert_allclose(res.x[2:], -0.1 * res.x[:2], rtol=1e-12)


def incline(theta_deg, mu, dt=1e-3, g=9.81):
    """Unit point mass on an incline: one step of gravity as an impulse LCP (t points up)."""
    th = math.radians(theta_deg)
    b = np.array([-g * math.cos(th) * dt, -g * math.sin(th) * dt])
    return problem(np.eye(2), b, [-1, 0], [0.0, mu], [0.0, mu]), th, g, dt


@pytest.mark.parametrize('method', ['dantzig', 'lemke', 'pgs'])
def test_incline_static_friction_holds(method):
    p, th, g, dt = incline(30.0, 0.6)          # tan 30 = 0.577 < 0.6
    res = solve(p, methods=(method,), tol=1e-12)
    assert res.converged
    assert res.x[0] == pytest.approx(g * math.cos(th) * dt, rel=1e-12)
    assert res.x[1] == pytest.approx(g * math.sin(th) * dt, rel=1e-12)
    assert abs(res.w[1]) <= 1e-15


@pytest.mark.parametrize('method', ['dantzig', 'lemke', 'pgs'])
def test_incline_static_friction_saturates(method):
    p, th, g, dt = incline(20.0, 0.3)          # tan 20 = 0.364 > 0.3
    res = solve(p, methods=(method,), tol=1e-12)
    assert res.converged
    assert res.x[1] == pytest.approx(0.3 * res.x[0], rel=1e-12)   # |x_T| = mu x_N
    assert res.w[1] == pytest.approx(-g * dt * (math.sin(th) - 0.3 * math.cos(th)), rel=1e-9)


@pytest.mark.parametrize('sigma', [1.0, -1.0])
@pytest.mark.parametrize('mu, stops', [(0.2, False), (1e3, True)])
def test_one_sided_dynamic_friction_never_reverses_the_slip(sigma, mu, stops):
    # decoupled point mass: only friction acts on the slip, so it may slow it, stop it,
    # but never push it past zero
    b = np.array([-1.0, sigma * 0.5])
    lo, hi = (mu, 0.0) if sigma > 0 else (0.0, mu)
    res = solve(problem(np.eye(2), b, [-1, 0], [0.0, lo], [0.0, hi]))
    assert res.converged and res.method == 'dantzig'
    assert sigma * res.w[1] >= 0.0
    if stops:
        assert res.w[1] == 0.0 and res.x[1] == pytest.approx(-sigma * 0.5, rel=1e-15)
    else:
        assert res.w[1] == pytest.approx(sigma * (0.5 - 0.2), rel=1e-12)


def test_one_sided_friction_with_coupling_only_acts_against_the_slip():
    # coupled random problems: whenever the friction impulse is non-zero it opposes the
    # pre-impact slip and does not reverse it (w_T of the slip's sign or zero); the normal
    # impulse itself may still reverse the slip through W_TN (the rod case below)
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(200):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 4)), int(rng.integers(1, 5)))
        c = len(W) // 2
        slip = Jv[c:]
        mu = rng.uniform(0.1, 2.0, c)
        lo, hi = np.where(slip > 0, mu, 0.0), np.where(slip < 0, mu, 0.0)
        res = solve(friction_problem(W, Jv, lo, hi))
        if not res.converged:
            continue
        checked += 1
        sig = np.sign(slip)
        acting = np.abs(res.x[c:]) > 1e-9 * max(1.0, np.abs(res.x).max())
        assert np.all(sig[acting] * res.x[c:][acting] <= 0.0)
        scale = max(np.abs(Jv).max(), np.abs(W).max() * np.abs(res.x).max())
        assert np.all(sig[acting] * res.w[c:][acting] >= -1e-9 * scale)
    assert checked >= 190


# ---------------------------------------------------------------------------------------------
# reference section 2.3: uniform rod at 45 degrees, e = mu = 0.5


def rod_problem():
    W_tn = np.array([[2.5, -1.5], [-1.5, 2.5]])     # (T, N) order in the reference
    A = W_tn[::-1, ::-1]                             # (N, T)
    v_t, v_n, e = 0.0607, -2.5607, 0.5
    b = np.array([(1 + e) * v_n, v_t])
    # v_T > 0: one-sided dynamic friction (mu_d, 0), i.e. x_T in [-0.5 x_N, 0]
    return problem(A, b, [-1, 0], [0.0, 0.5], [0.0, 0.0]), A, np.array([v_n, v_t])


@pytest.mark.parametrize('method', ['dantzig', 'lemke', 'pgs'])
def test_rod_impact_matches_the_hand_solution_and_gains_no_energy(method):
    p, W, u0 = rod_problem()
    res = solve(p, methods=(method,))
    assert res.converged and res.method == method
    # By hand: with x_T = 0, x_N = 1.5 * 2.5607 / 2.5 = 1.536420 makes w_N = 0, and then
    # w_T = 0.0607 - 1.5 x_N = -2.2439 <= 0 is allowed at the zero (upper) bound. Any
    # x_T < 0 would be friction pushing the slip further negative, i.e. reversing it.
    x_n = 1.5 * 2.5607 / 2.5
    assert res.x[0] == pytest.approx(x_n, abs=1e-9)
    assert res.x[1] == pytest.approx(0.0, abs=1e-9)
    assert res.w[1] == pytest.approx(0.0607 - 1.5 * x_n, abs=1e-9)
    p_imp = res.x
    d_ke = p_imp @ u0 + 0.5 * p_imp @ W @ p_imp        # KE change in contact coordinates
    assert d_ke <= 0.0
    # KE before: rod m = 1, J = 1/3, v_G = (-1, -1.5), omega = 1.5 -> 1.625 + 0.375 = 2.0
    assert 1.0 + d_ke / 2.0 == pytest.approx(0.509, abs=1e-3)
    # The law that keeps friction on at -mu x_N however the slip ends (column substitution,
    # one normal row) is the one that gains energy: KE ratio 1.084 as in the reference.
    slaved = solve(problem([[W[0, 0] - 0.5 * W[0, 1]]], [p.b[0]], [-1]))
    p_sl = slaved.x[0] * np.array([1.0, -0.5])
    assert p_sl == pytest.approx([1.1818, -0.5909], abs=1e-4)
    assert 1.0 + (p_sl @ u0 + 0.5 * p_sl @ W @ p_sl) / 2.0 == pytest.approx(1.084, abs=1e-3)


# ---------------------------------------------------------------------------------------------
# random Delassus problems


def random_delassus(rng, n_bodies, n_contacts):
    """Delassus W = J M^-1 J^T of random 2D bodies (mm-sized parts, 1 g .. 1 kg) touching each
    other or the ground, rows [N..., T...]; also J v for a random velocity v."""
    mass = 10.0 ** rng.uniform(-3, 0, n_bodies)
    size = 10.0 ** rng.uniform(-3, -1.5, n_bodies)
    inertia = mass * size ** 2 / 6.0
    minv = np.repeat(1.0 / mass, 3)
    minv[2::3] = 1.0 / inertia
    JN = np.zeros((n_contacts, 3 * n_bodies))
    JT = np.zeros_like(JN)
    for i in range(n_contacts):
        a = int(rng.integers(n_bodies))
        other = int(rng.integers(-1, n_bodies))
        ang = rng.uniform(0, 2 * np.pi)
        n = np.array([np.cos(ang), np.sin(ang)])
        t = np.array([-n[1], n[0]])
        r_a = rng.uniform(-1, 1, 2) * size[a]
        JN[i, 3 * a:3 * a + 3] = [*n, cross(r_a, n)]
        JT[i, 3 * a:3 * a + 3] = [*t, cross(r_a, t)]
        if other >= 0 and other != a:
            r_b = rng.uniform(-1, 1, 2) * size[other]
            JN[i, 3 * other:3 * other + 3] -= [*n, cross(r_b, n)]
            JT[i, 3 * other:3 * other + 3] -= [*t, cross(r_b, t)]
    J = np.vstack([JN, JT])
    W = (J * minv) @ J.T
    W = 0.5 * (W + W.T)
    v = rng.normal(size=3 * n_bodies) * np.repeat(np.r_[1.0], 3 * n_bodies)
    v[2::3] /= size
    return W, J @ v, J, minv


def random_friction_rows(rng, c, slip):
    """Random static (mu_s, mu_s) or one-sided dynamic rows (sign from the slip)."""
    mu = rng.uniform(0.0, 2.0, c)
    static = rng.random(c) < 0.5
    lo = np.where(static | (slip > 0), mu, 0.0)
    hi = np.where(static | (slip < 0), mu, 0.0)
    return lo, hi


def column_substituted(W, b, sliding, mu_d):
    """Force-problem form: sliding contacts' friction x_T = -mu_d sign(v_T) x_N is substituted
    into their normal columns and their friction rows dropped, so A is non-symmetric."""
    c = len(sliding)
    keep = np.r_[np.arange(c), c + np.flatnonzero(~sliding)]
    P = np.zeros((2 * c, len(keep)))
    P[keep, np.arange(len(keep))] = 1.0
    P[c + np.flatnonzero(sliding), np.flatnonzero(sliding)] = (
        -mu_d[sliding] * np.sign(b[c:][sliding]))
    return W[keep] @ P, b[keep], keep


def test_random_problems_report_converged_only_when_the_residual_is_small():
    rng = np.random.default_rng(2024)
    counts = dict.fromkeys(('trivial', *ALL), 0)
    physical = dict.fromkeys(('trivial', *ALL), 0)
    for trial in range(300):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 5)), int(rng.integers(1, 9)))
        c = len(W) // 2
        b = Jv if trial % 2 else rng.normal(size=2 * c) * np.abs(Jv).max()
        lo, hi = random_friction_rows(rng, c, b[c:])
        if trial % 3 == 0:
            # sliding contacts eliminated by column substitution (non-symmetric A)
            sliding = rng.random(c) < 0.5
            A, bb, keep = column_substituted(W, b, sliding, rng.uniform(0, 1, c))
            nk = len(keep) - c
            p = problem(A, bb, np.r_[np.full(c, -1), np.flatnonzero(~sliding)],
                        np.r_[np.zeros(c), lo[~sliding]], np.r_[np.zeros(c), hi[~sliding]])
            assert nk == (~sliding).sum()
        else:
            p = friction_problem(W, b, lo, hi)
        res = solve(p)
        assert isinstance(res, LCPResult)
        assert np.isfinite(res.x).all() and np.isfinite(res.w).all()
        assert res.residual == pytest.approx(residual(p, res.x), rel=1e-12, abs=1e-300)
        np.testing.assert_allclose(res.w, p.A @ res.x + p.b, rtol=0, atol=1e-12 * (
            np.abs(p.b).max() + np.abs(p.A).max() * np.abs(res.x).max()))
        if res.converged:
            assert res.residual <= 1e-9
            assert res.fallbacks == sum(f in res.message for f in ALL)
            counts[res.method] += 1
            if trial % 2 and trial % 3:
                physical[res.method] += 1
        else:
            assert res.fallbacks == 4 and res.message
    # physical problems (b = J v, no substitution) are solvable and go to Dantzig
    assert physical['dantzig'] + physical['trivial'] == sum(physical.values()) == 100
    assert counts['dantzig'] + counts['trivial'] >= 250


def test_dantzig_solves_frictionless_psd_problems():
    rng = np.random.default_rng(11)
    ok = total = 0
    for _ in range(400):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 5)), int(rng.integers(1, 9)))
        c = len(W) // 2
        # b = J v always has a solution (KKT of min |v'|_M subject to J_N v' >= 0)
        res = solve(problem(W[:c, :c], Jv[:c], np.full(c, -1)), methods=('dantzig',))
        if res.method == 'trivial':
            continue
        total += 1
        ok += res.converged
    assert total >= 300
    assert ok >= 0.99 * total


def test_frictionless_pd_problems_have_one_answer_that_all_methods_find():
    rng = np.random.default_rng(5)
    compared = 0
    for _ in range(150):
        nb = int(rng.integers(1, 5))
        c = int(rng.integers(1, 3 * nb + 1))
        W, Jv, _, _ = random_delassus(rng, nb, c)
        A = W[:c, :c]
        ev = np.linalg.eigvalsh(A)
        if ev[0] < 1e-4 * ev[-1]:
            continue        # not safely positive definite
        b = Jv[:c] if compared % 2 else rng.normal(size=c) * np.abs(Jv).max()
        p = problem(A, b, np.full(c, -1))
        ref = solve(p, methods=('dantzig',), tol=1e-12)
        assert ref.converged
        for method in ('lemke', 'pgs', 'frictionless'):
            res = solve(p, methods=(method,), tol=1e-12, max_pivots=20000)
            if res.converged:
                np.testing.assert_allclose(res.x, ref.x, rtol=0,
                                           atol=1e-8 * max(1.0, np.abs(ref.x).max()))
        compared += 1
    assert compared >= 60


def test_dantzig_solves_physical_frictional_problems():
    # b = J v with static and one-sided rows: the problems the simulator poses
    rng = np.random.default_rng(12)
    ok = total = 0
    for _ in range(400):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 5)), int(rng.integers(1, 9)))
        c = len(W) // 2
        lo, hi = random_friction_rows(rng, c, Jv[c:])
        res = solve(friction_problem(W, Jv, lo, hi), methods=('dantzig',))
        if res.method == 'trivial':
            continue
        total += 1
        ok += res.converged
    assert total >= 300
    assert ok >= 0.99 * total


def box_stack(rng, n_boxes):
    """Boxes 20 x 10 mm stacked on the ground, two corner contacts per face (redundant pairs
    with identical tangent rows), falling with random sideways and spin velocities."""
    w, h = 0.02, 0.01
    mass = 10.0 ** rng.uniform(-3, 0, n_boxes)
    minv = np.repeat(1.0 / mass, 3)
    minv[2::3] = 12.0 / (mass * (w * w + h * h))
    n, t = np.array([0.0, 1.0]), np.array([1.0, 0.0])
    JN, JT = [], []
    for i in range(n_boxes):
        for side in (-1, 1):
            jn, jt = np.zeros(3 * n_boxes), np.zeros(3 * n_boxes)
            r_a = np.array([side * w / 2 * rng.uniform(0.5, 1.0), -h / 2])
            jn[3 * i:3 * i + 3] = [*n, cross(r_a, n)]
            jt[3 * i:3 * i + 3] = [*t, cross(r_a, t)]
            if i > 0:
                r_b = np.array([r_a[0] + rng.uniform(-2e-3, 2e-3), h / 2])
                jn[3 * i - 3:3 * i] -= [*n, cross(r_b, n)]
                jt[3 * i - 3:3 * i] -= [*t, cross(r_b, t)]
            JN.append(jn)
            JT.append(jt)
    J = np.array(JN + JT)
    v = np.zeros(3 * n_boxes)
    v[1::3] = -9.81e-3
    v[0::3] = rng.normal(size=n_boxes) * rng.choice([0.0, 1e-3, 0.1])
    v[2::3] = rng.normal(size=n_boxes) * rng.choice([0.0, 0.1])
    return (J * minv) @ J.T, J @ v


@pytest.mark.parametrize('mu', [0.3, 0.8, 100.0])
def test_dantzig_handles_redundant_contacts_of_stacked_boxes(mu):
    rng = np.random.default_rng(int(mu * 10))
    for _ in range(40):
        W, b = box_stack(rng, int(rng.integers(1, 6)))
        c = len(b) // 2
        static = rng.random(c) < 0.5
        lo = np.where(static | (b[c:] > 0), mu, 0.0)
        hi = np.where(static | (b[c:] < 0), mu, 0.0)
        res = solve(friction_problem(W, b, lo, hi))
        assert res.converged and res.fallbacks == 0
        assert res.method in ('trivial', 'dantzig')
        v_post = W @ res.x + b
        assert v_post[:c].min() >= -1e-9 * np.abs(b).max()


def test_moving_bound_is_exact_where_frozen_bounds_would_violate_coulomb():
    # Two contacts on one body. Dantzig treats the more negative contact first; when its
    # friction ends saturated and treating the other contact then lowers its normal impulse,
    # a bound frozen at the first value (ODE's findex) would leave |x_T| > mu x_N. The moving
    # bound keeps |x_T| = mu x_N exactly.
    rng = np.random.default_rng(3)
    mu = 0.3
    moved = 0
    for _ in range(300):
        W, Jv, _, _ = random_delassus(rng, 1, 2)
        if Jv[:2].min() >= 0:
            continue
        res = solve(friction_problem(W, Jv, np.full(2, mu), np.full(2, mu)),
                    methods=('dantzig',))
        assert res.converged
        first = int(np.argmin(Jv[:2]))
        rows = [first, 2 + first]
        alone = solve(problem(W[np.ix_(rows, rows)], Jv[rows], [-1, 0], [0, mu], [0, mu]))
        x_n0, x_t0 = alone.x
        x_n, x_t = res.x[first], res.x[2 + first]
        if abs(x_t0) >= mu * x_n0 * (1 - 1e-12) and x_n < x_n0 * (1 - 1e-6) \
                and abs(x_t) >= mu * x_n * (1 - 1e-12):
            moved += 1
            assert abs(x_t) == pytest.approx(mu * x_n, rel=1e-12)
            assert abs(x_t) < mu * x_n0           # the frozen bound would be violated
        assert np.all(np.abs(res.x[2:]) <= mu * res.x[:2] * (1 + 1e-12))
    assert moved >= 5


# ---------------------------------------------------------------------------------------------
# degenerate input


def timed(p, **kw):
    t0 = time.perf_counter()
    res = solve(p, **kw)
    assert time.perf_counter() - t0 < 1.0
    assert np.isfinite(res.x).all() and np.isfinite(res.w).all() and np.isfinite(res.residual)
    return res


def test_zero_rows():
    J, W = box_on_flat()
    b = J @ np.array([0.05, -0.3, 0.0])
    W = W.copy()
    W[1, :] = W[:, 1] = 0.0                        # a normal row that does nothing
    res = timed(friction_problem(W, b * [1, 0, 1, 1], np.full(2, 0.5), np.full(2, 0.5)))
    assert res.converged
    W[3, :] = W[:, 3] = 0.0                        # and a dead friction row
    res = timed(friction_problem(W, b * [1, 0, 1, 0], np.full(2, 0.5), np.full(2, 0.5)))
    assert res.converged
    # a zero normal row with b < 0 has no solution: reported, never raised
    res = timed(problem(np.zeros((2, 2)), [-1.0, 0.5], [-1, -1]))
    assert not res.converged and res.message


def test_duplicated_contacts():
    J, _ = box_on_flat()
    JN, JT = J[:2], J[2:]
    J4 = np.vstack([JN, JN, JT, JT])               # every contact reported twice
    W = J4 @ np.diag([1.0, 1.0, 1 / 4.1667e-5]) @ J4.T
    b = J4 @ np.array([0.05, -0.3, 2.0])
    for mu in (0.0, 0.5, 100.0):
        res = timed(friction_problem(W, b, np.full(4, mu), np.full(4, mu)))
        assert res.converged
        v_post = W @ res.x + b
        assert np.all(v_post[:4] >= -1e-9 * np.abs(b).max())


@pytest.mark.parametrize('scale_a, scale_b', [(1e-12, 1.0), (1e12, 1.0), (1.0, 1e-12),
                                              (1.0, 1e12), (1e-12, 1e-12), (1e12, 1e12)])
def test_extreme_scales(scale_a, scale_b):
    rng = np.random.default_rng(9)
    for _ in range(5):
        W, Jv, _, _ = random_delassus(rng, 2, 4)
        W, Jv = W / np.abs(W).max(), Jv / np.abs(Jv).max()
        lo, hi = random_friction_rows(rng, 4, Jv[4:])
        ref = solve(friction_problem(W, Jv, lo, hi))
        res = timed(friction_problem(W * scale_a, Jv * scale_b, lo, hi))
        assert res.converged == ref.converged
        if ref.converged and ref.method == res.method == 'dantzig':
            np.testing.assert_allclose(res.x * scale_a / scale_b, ref.x, rtol=1e-6,
                                       atol=1e-9 * np.abs(ref.x).max())


def test_large_friction_and_large_problem_stay_fast():
    rng = np.random.default_rng(1)
    W, Jv, _, _ = random_delassus(rng, 4, 8)
    res = timed(friction_problem(W, Jv, np.full(8, 100.0), np.full(8, 100.0)))
    assert res.converged
    W, Jv, _, _ = random_delassus(rng, 30, 60)     # 120 unknowns
    lo, hi = random_friction_rows(rng, 60, Jv[60:])
    res = timed(friction_problem(W, Jv, lo, hi))
    assert res.converged and res.method == 'dantzig'      # needs the fold handling


# ---------------------------------------------------------------------------------------------
# fast path, validation, fallback accounting


def test_trivial_fast_path():
    J, W = box_on_flat()
    res = solve(friction_problem(W, J @ np.array([0.3, 0.2, 0.0]), np.full(2, 0.5),
                                 np.full(2, 0.5)))
    assert (res.method, res.pivots, res.fallbacks, res.converged) == ('trivial', 0, 0, True)
    np.testing.assert_array_equal(res.x, 0.0)
    empty = solve(problem(np.zeros((0, 0)), np.zeros(0), np.zeros(0, int)))
    assert empty.method == 'trivial' and empty.x.shape == (0,)


@pytest.mark.parametrize('field, kwargs', [
    ('A', dict(A=np.eye(3))),
    ('A', dict(A=np.array([[np.nan, 0.0], [0.0, 1.0]]))),
    ('b', dict(b=np.array([np.inf, 0.0]))),
    ('mu_lo', dict(mu_lo=np.array([0.0, -0.1]))),
    ('mu_hi', dict(mu_hi=np.array([0.0]))),
    ('normal_of', dict(normal_of=np.array([1, 0]))),
    ('normal_of', dict(normal_of=np.array([0, -1]))),
    ('normal_of', dict(normal_of=np.array([-1, 5]))),
    ('normal_of', dict(normal_of=np.array([-1, 1]))),
])
def test_malformed_input_is_rejected_naming_the_field(field, kwargs):
    args = dict(A=np.eye(2), b=np.array([-1.0, 0.0]), normal_of=np.array([-1, 0]),
                mu_lo=np.array([0.0, 0.5]), mu_hi=np.array([0.0, 0.5]))
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        FrictionalLCP(**args)


def test_unknown_method_is_rejected():
    for methods in (('simplex',), (), 'pgs'):
        with pytest.raises(ValueError, match='method'):
            solve(rod_problem()[0], methods=methods)


def test_pgs_alone():
    p, th, g, dt = incline(30.0, 0.6)
    res = solve(p, methods=('pgs',))
    assert res.converged and res.method == 'pgs' and res.fallbacks == 0
    assert res.pivots >= 1 and res.message == ''


def test_painleve_problem_falls_through_the_ladder_without_raising():
    # one sliding contact eliminated by column substitution: A_eff = A_NN - mu A_NT < 0
    W = np.array([[1.0, 2.0], [2.0, 5.0]])          # (N, T), PSD
    mu = 0.8
    a_eff = W[0, 0] - mu * W[0, 1]                  # -0.6
    assert a_eff < 0
    res = solve(problem([[a_eff]], [-1.0], [-1]))   # w = a x - 1 < 0 for every x >= 0
    assert not res.converged
    assert res.fallbacks == 4 and res.message.count(':') >= 4
    assert np.isfinite(res.x).all() and res.x[0] >= 0.0
    for name in ALL:
        assert name in res.message


def test_fallback_is_counted_when_dantzig_is_capped():
    rng = np.random.default_rng(4)
    W, Jv, _, _ = random_delassus(rng, 3, 6)
    lo, hi = random_friction_rows(rng, 6, Jv[6:])
    p = friction_problem(W, Jv, lo, hi)
    res = solve(p, max_pivots=1, methods=('dantzig', 'lemke'))
    assert res.fallbacks >= 1 and 'dantzig' in res.message
    assert res.pivots >= 1
    full = solve(p, methods=('dantzig', 'lemke'))
    assert full.converged


def test_residual_definition():
    p = rod_problem()[0]
    x = solve(p).x
    assert residual(p, x) <= 1e-15
    assert residual(p, np.array([-0.1, 0.0])) > 0.0        # negative normal impulse
    assert residual(p, x + [0.0, 0.1]) > 0.0               # friction above its upper bound
    assert residual(p, np.array([np.nan, 0.0])) == math.inf
    # invariant under scaling A, b and x consistently
    q = problem(p.A * 1e6, p.b * 1e-3, p.normal_of, p.mu_lo, p.mu_hi)
    y = np.array([1.4, -0.2])
    assert residual(q, y * 1e-9) == pytest.approx(residual(p, y), rel=1e-12)
    # large problems use the vectorised branch: same value
    big = problem(np.kron(np.eye(10), p.A), np.tile(p.b, 10), np.tile([-1, 0], 10)
                  + np.repeat(np.arange(10) * 2, 2) * np.tile([0, 1], 10),
                  np.tile(p.mu_lo, 10), np.tile(p.mu_hi, 10))
    assert residual(big, np.tile(y, 10)) == pytest.approx(residual(p, y), rel=1e-12)


def test_compiled_dantzig_gives_the_answers_of_the_python_reference():
    # The numba port (contact._lcp_kernels.dantzig) against lcp.solve's Dantzig pass on random
    # frictional Delassus problems: it converges wherever the reference does, to a solution,
    # and takes the same pivots on all but at most 1 % of the problems (measured: 1 of 256, 24
    # pivots against 22; on an AMD EPYC, whose LAPACK rounds the reference's solves
    # differently, 17 against 16). Where the pivots agree, so do the impulses, within 1e-9 of
    # their scale (measured: 6e-12); where they do not, a frictional LCP's solution need not
    # be unique and the two may each have found another one (the EPYC's case: residuals 9e-17
    # and 3e-17, impulses 60 % apart).
    # Run from a heap state and from scratch arenas of two sizes (one that holds some problems,
    # one that holds all), it gives the same bits: where its scratch comes from changes no
    # arithmetic.
    import numba

    from feeder_sim.compiled.arena import borrow, heap_state, new_arena, PEAK, release, SHORT
    from feeder_sim.contact._lcp_kernels import dantzig as inner_dantzig

    @numba.njit
    def run(state, A, b, nof, lo, hi, max_pivots):   # the kernel has no Python wrapper
        return inner_dantzig(borrow(state), A, b, nof, lo, hi, max_pivots)

    @numba.njit
    def run_copied(state, A, b, nof, lo, hi, max_pivots):
        release(state, 0)
        x, pivots, code, retry, _ = inner_dantzig(borrow(state), A, b, nof, lo, hi,
                                                  max_pivots)
        return x.copy(), pivots, code, retry

    heap, small, large = heap_state(), new_arena(2048), new_arena(1 << 20)

    def dantzig(A, b, nof, lo, hi, max_pivots):
        out = run(heap, A, b, nof, lo, hi, max_pivots)
        for arena in (small, large):
            x, pivots, code, retry = run_copied(arena.state, A, b, nof, lo, hi, max_pivots)
            assert (pivots, code, retry) == out[1:4]
            assert x.tobytes() == out[0].tobytes()
        return out

    rng = np.random.default_rng(7)
    compared = same_pivots = same_impulses = 0
    for _ in range(300):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 5)), int(rng.integers(1, 9)))
        c = len(W) // 2
        lo, hi = random_friction_rows(rng, c, Jv[c:])
        p = friction_problem(W, Jv, lo, hi)
        ref = solve(p, methods=('dantzig',))
        if ref.method == 'trivial' or not ref.converged:
            continue
        x, pivots, _, _, _ = dantzig(p.A, p.b, p.normal_of, p.mu_lo, p.mu_hi,
                                     50 * len(p.b) + 50)
        compared += 1
        same_pivots += pivots == ref.pivots
        assert residual(p, x) <= 1e-9
        same = np.allclose(x, ref.x, rtol=0, atol=1e-9 * np.abs(ref.x).max())
        same_impulses += same
        assert same or pivots != ref.pivots
    assert compared >= 200
    assert same_impulses >= 0.99 * compared
    assert small.state[SHORT] > 0 and large.state[SHORT] == 0   # the fallback was exercised
    assert 0 < large.state[PEAK] < 1 << 20
    assert same_pivots >= 0.99 * compared


@pytest.mark.parametrize('friction', [True, False])
def test_a_solve_on_given_row_states_is_taken_only_where_it_solves_the_lcp(friction):
    # _lcp_kernels.solve_with_states, which time_stepping tries first on an island whose
    # contacts come with the row states of the step before (friction rows: the velocity
    # solve; normal rows only: the position projection). On random problems:
    # * on the states Dantzig ended in, it is Dantzig's answer within 1e-9 of its scale
    #   wherever it is taken (residual <= STATES_TOL), and it is taken on >= 90 % of them
    #   (measured: 283 of 283 with friction, 249 of 249 without);
    # * on the states of another problem (the same contacts, new velocities), whatever it
    #   takes solves the LCP by the Python reference's residual (<= 1e-11), and wrong
    #   states are turned down (measured: 86 of 283 and 113 of 249 taken).
    import numba

    from feeder_sim.compiled.arena import borrow, heap_state
    from feeder_sim.contact._island_kernels import STATES_TOL
    from feeder_sim.contact._lcp_kernels import dantzig as inner_dantzig
    from feeder_sim.contact._lcp_kernels import solve_with_states as inner_states

    @numba.njit
    def run_dantzig(state, A, b, nof, lo, hi):
        x, _, code, _, st = inner_dantzig(borrow(state), A, b, nof, lo, hi, 50 * b.shape[0] + 50)
        return x, code, st.copy()

    @numba.njit
    def run_states(state, A, b, nof, lo, hi, st):
        return inner_states(borrow(state), A, b, nof, lo, hi, st)

    heap = heap_state()
    rng = np.random.default_rng(11)
    own = taken_own = other = taken_other = 0
    for _ in range(300):
        W, Jv, _, _ = random_delassus(rng, int(rng.integers(1, 5)), int(rng.integers(1, 9)))
        c = len(W) // 2
        lo, hi = random_friction_rows(rng, c, Jv[c:])
        later = Jv + rng.normal(0.0, 0.3, Jv.shape) * np.abs(Jv).max()
        if friction:
            p, q = friction_problem(W, Jv, lo, hi), friction_problem(W, later, lo, hi)
        else:
            p, q = (problem(W[:c, :c], v[:c], np.full(c, -1), np.zeros(c), np.zeros(c))
                    for v in (Jv, later))
        x, code, st = run_dantzig(heap, p.A, p.b, p.normal_of, p.mu_lo, p.mu_hi)
        if code != 0 or not residual(p, x) <= 1e-9 or not (p.b < 0).any():
            continue
        own += 1
        y, _, r = run_states(heap, p.A, p.b, p.normal_of, p.mu_lo, p.mu_hi, st)
        if r <= STATES_TOL:
            taken_own += 1
            np.testing.assert_allclose(y, x, rtol=0, atol=1e-9 * np.abs(x).max())
        # the same contacts a step later: other free velocities
        other += 1
        z, _, r = run_states(heap, q.A, q.b, q.normal_of, q.mu_lo, q.mu_hi, st)
        if r <= STATES_TOL:
            taken_other += 1
            assert residual(q, z) <= 1e-11
    assert own >= 150
    assert taken_own >= 0.9 * own
    assert 0 < taken_other < other


def _velocity_residual(problem: FrictionalLCP, x: np.ndarray) -> float:
    """The largest velocity change (m/s) one projected Gauss-Seidel step would make from x,
    ``A_ii |x_i - proj(x_i - w_i / A_ii)|``: absolute, so an answer's size cannot hide it."""
    A, b = problem.A, problem.b
    w = A @ x + b
    out = 0.0
    for i in range(len(b)):
        d = A[i, i]
        if d <= 0.0:
            continue
        j = problem.normal_of[i]
        if j < 0:
            y = max(x[i] - w[i] / d, 0.0)
        else:
            xj = max(x[j], 0.0)
            y = min(max(x[i] - w[i] / d, -problem.mu_lo[i] * xj), problem.mu_hi[i] * xj)
        out = max(out, abs(x[i] - y) * d)
    return out


def test_an_answer_to_a_wedged_cup_does_not_hide_its_velocity_error_in_its_size():
    # A cup wedged under the orienter's hook (orienter_hook_fed, time_stepping, t = 20.277 s):
    # W has a 6-dimensional null space, so a squeeze along it solves the LCP as well. Lemke
    # answered 2.4e9 N s with a scale-free residual of 1e-14, accepted, reported and used to
    # warm-start the next steps, which threw three cups out at 16 km/s at t = 23.5 s. The
    # answer taken must meet the problem's own velocity scale (max |b| = 11 mm/s); PGS gets
    # 2.4e-5 N s at most.
    data = json.loads((DATA / 'wedged_cup_lcp.json').read_text())
    problem = FrictionalLCP(np.array(data['A']), np.array(data['b']),
                            np.array(data['normal_of']), np.array(data['mu_lo']),
                            np.array(data['mu_hi']))
    result = solve(problem, tol=1e-9)
    assert _velocity_residual(problem, result.x) <= 1e-3 * np.abs(problem.b).max()
    assert np.abs(result.x).max() < 1e-3
