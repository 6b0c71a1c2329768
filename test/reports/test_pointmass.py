"""The point-mass conveying reference (reports.pointmass) against physics reference §4."""

import math

import numpy as np
import pytest

import feeder_sim.reports.pointmass as pointmass
from feeder_sim.reports.pointmass import (
    Conveyor,
    dimensionless_speed,
    mean_speed,
    thresholds,
    trajectory,
)

GAMMAS = (0.5, 0.8, 1.0, 1.2, 1.5, 2.0)
# Reference section 4.3: (psi deg, mu, theta deg) -> V_m at GAMMAS (mu_s = mu_k = mu)
TABLE = {
    (20, 0.5, 0): (0.444, 0.820, 1.054, 1.284, 1.737, 3.605),
    (20, 0.5, 3): (0.268, 0.491, 0.630, 0.788, 1.190, 3.440),
    (20, 0.8, 0): (0.414, 1.093, 1.525, 1.925, 2.503, 4.275),
    (20, 0.8, 3): (0.348, 0.949, 1.312, 1.652, 2.160, 4.111),
    (30, 0.5, 0): (0.262, 0.688, 0.956, 1.207, 1.567, 2.686),
    (30, 0.5, 3): (0.195, 0.535, 0.734, 0.921, 1.221, 2.521),
    (30, 0.8, 0): (0.134, 0.617, 1.000, 1.400, 2.039, 3.196),
    (30, 0.8, 3): (0.104, 0.561, 0.921, 1.307, 1.931, 3.081),
}
# Entries this solver does not reproduce to the printed precision. Each is 0.20-0.21 % above the
# table (1.1-1.4 x the tolerance below); a plain velocity-level time stepper converges to this
# solver's value as its step shrinks (see test_independent_stepper_converges_to_this_solver),
# so these are read as step-size error of the 4000-steps/cycle stepper behind the table,
# within the 0.3 % the reference quotes between its own two solvers.
TABLE_MISMATCH = {
    (20, 0.5, 0, 1.2): 1.28663,
    (20, 0.5, 3, 1.2): 0.78961,
    (30, 0.5, 3, 1.0): 0.73548,
    (30, 0.5, 3, 1.2): 0.92286,
}


def case(psi_deg, mu, theta_deg, gamma, **kw):
    return Conveyor(psi=math.radians(psi_deg), theta=math.radians(theta_deg), mu_s=mu, mu_k=mu,
                    gamma=gamma, **kw)


def printed_tolerance(printed: float, decimals: int) -> float:
    """0.6 x the last printed digit + 0.1 % relative."""
    return 0.6 * 10.0 ** -decimals + 1e-3 * abs(printed)


TABLE_CASES = []
for (psi, mu, theta), row in TABLE.items():
    for gamma, value in zip(GAMMAS, row):
        marks = ()
        if (psi, mu, theta, gamma) in TABLE_MISMATCH:
            marks = pytest.mark.xfail(strict=True, reason='0.2 % above the table: step-size '
                                      'error of the table stepper, see TABLE_MISMATCH')
        TABLE_CASES.append(pytest.param(psi, mu, theta, gamma, value, marks=marks,
                                        id=f'psi{psi}-mu{mu}-theta{theta}-G{gamma}'))


@pytest.mark.parametrize('psi, mu, theta, gamma, expected', TABLE_CASES)
def test_reference_table(psi, mu, theta, gamma, expected):
    v = dimensionless_speed(case(psi, mu, theta, gamma), warmup_cycles=40, cycles=40)
    assert abs(v - expected) <= printed_tolerance(expected, 3), f'V_m = {v:.5f}'


@pytest.mark.parametrize('key', sorted(TABLE_MISMATCH))
def test_table_mismatches_are_small_and_known(key):
    psi, mu, theta, gamma = key
    expected = TABLE[psi, mu, theta][GAMMAS.index(gamma)]
    v = dimensionless_speed(case(psi, mu, theta, gamma))
    assert v == pytest.approx(TABLE_MISMATCH[key], abs=1e-5)
    assert 0.0015 < (v - expected) / expected < 0.0025


def plain_stepper(psi_deg, mu, theta_deg, gamma, steps_per_cycle, warmup=6, cycles=6):
    """Independent first-order velocity-level stepper (impulses, plastic contact, Coulomb)."""
    psi, theta = math.radians(psi_deg), math.radians(theta_deg)
    tan, g_cos = math.tan(theta), gamma / math.tan(psi)
    h = 2.0 * math.pi / steps_per_cycle
    u = z = w = x = x0 = 0.0
    for n in range((warmup + cycles) * steps_per_cycle):
        if n == warmup * steps_per_cycle:
            x0 = x
        s = math.sin((n + 1) * h)
        w += h * (-1.0 + gamma * s)
        u += h * (-tan + g_cos * s)
        if z <= 0.0:
            p_n = max(0.0, -w)
            w += p_n
            u = 0.0 if abs(u) <= mu * p_n else u - math.copysign(mu * p_n, u)
        z = max(z + h * w, 0.0)
        x += h * u
    return (x - x0) / (2.0 * math.pi * cycles)


@pytest.mark.parametrize('psi, mu, theta, gamma', [(30, 0.5, 3, 1.0), (30, 0.8, 3, 0.8),
                                                   (20, 0.5, 0, 0.5)])
def test_independent_stepper_converges_to_this_solver(psi, mu, theta, gamma):
    v = dimensionless_speed(case(psi, mu, theta, gamma))
    coarse = plain_stepper(psi, mu, theta, gamma, 2000)
    fine = plain_stepper(psi, mu, theta, gamma, 16000)
    assert abs(fine - v) < 0.5 * abs(coarse - v) + 1e-6
    assert fine == pytest.approx(v, rel=3e-4)


@pytest.mark.parametrize('gamma, expected, decimals', [(0.4, 0.0335, 4), (0.6, 0.272, 3),
                                                       (0.9, 0.808, 3), (2.5, 4.217, 3),
                                                       (3.0, 5.10, 2)])
def test_extra_points(gamma, expected, decimals):
    v = dimensionless_speed(case(30, 0.8, 0, gamma))
    assert abs(v - expected) <= printed_tolerance(expected, decimals), f'V_m = {v:.5f}'


def test_below_the_forward_threshold_nothing_moves():
    assert dimensionless_speed(case(30, 0.8, 0, 0.3)) == 0.0


@pytest.mark.parametrize('psi, mu, theta', sorted(TABLE))
def test_forward_sliding_threshold(psi, mu, theta):
    limit = thresholds(case(psi, mu, theta, 1.0))['forward']
    below = case(psi, mu, theta, 0.99 * limit)
    above = case(psi, mu, theta, 1.01 * limit)
    assert dimensionless_speed(below, warmup_cycles=2, cycles=4) == 0.0
    assert set(trajectory(below, 3 / below.frequency_hz, 600)['phase']) == {'stick'}
    assert dimensionless_speed(above, warmup_cycles=2, cycles=4) > 1e-6
    assert 'slide+' in set(trajectory(above, 3 / above.frequency_hz, 2000)['phase'])


@pytest.mark.parametrize('psi, mu, theta', [k for k in sorted(TABLE)
                                            if thresholds(case(*k, 1.0))['backward'] < 1.0])
def test_backward_sliding_threshold(psi, mu, theta):
    limit = thresholds(case(psi, mu, theta, 1.0))['backward']
    below = trajectory(case(psi, mu, theta, 0.99 * limit), 4 / 50.0, 4000)['phase']
    above = trajectory(case(psi, mu, theta, 1.01 * limit), 4 / 50.0, 4000)['phase']
    assert 'slide-' not in set(below)
    assert 'slide-' in set(above)


def test_worked_thresholds():
    t = thresholds(case(30, 0.8, 3, 1.0))
    assert (round(t['forward'], 3), round(t['backward'], 3)) == (0.337, 0.802)
    t = thresholds(case(20, 0.5, 3, 1.0))
    assert (round(t['forward'], 3), round(t['backward'], 3)) == (0.170, 0.199)


def test_hopping_starts_at_gamma_one():
    assert 'flight' not in set(trajectory(case(30, 0.8, 3, 0.99), 0.06, 3000)['phase'])
    assert 'flight' in set(trajectory(case(30, 0.8, 3, 1.01), 0.06, 3000)['phase'])


@pytest.mark.parametrize('psi, mu, theta, gamma', [(30, 0.8, 3, 0.6), (30, 0.8, 3, 1.2),
                                                   (20, 0.5, 0, 2.0), (30, 0.8, 0, 3.0)])
def test_speed_scales_as_one_over_frequency(psi, mu, theta, gamma):
    v = {f: mean_speed(case(psi, mu, theta, gamma, frequency_hz=f)) for f in (50.0, 100.0, 120.0)}
    dimless = [v[f] * 2 * math.pi * f / (9.81 * math.cos(math.radians(theta))) for f in v]
    assert max(dimless) - min(dimless) <= 1e-9 * abs(dimless[0])
    assert v[50.0] / v[100.0] == pytest.approx(2.0, rel=1e-9)


def test_frictionless_landing_adds_seven_to_nine_percent():
    for gamma, percent in ((1.2, 7), (1.5, 9)):
        rough = dimensionless_speed(case(30, 0.8, 0, gamma))
        smooth = dimensionless_speed(case(30, 0.8, 0, gamma, frictionless_landing=True))
        assert round(100 * (smooth / rough - 1)) == percent


@pytest.mark.parametrize('psi, mu, theta, gamma', [(20, 0.5, 3, 1.2), (30, 0.8, 0, 2.0),
                                                   (30, 0.8, 0, 4.0), (30, 0.8, 0, 4.6)])
def test_early_stop_at_periodic_state_changes_nothing(monkeypatch, psi, mu, theta, gamma):
    c = case(psi, mu, theta, gamma)
    fast = dimensionless_speed(c, warmup_cycles=40, cycles=40)
    monkeypatch.setattr(pointmass, 'MAX_PERIOD', 0)
    full = dimensionless_speed(c, warmup_cycles=40, cycles=40)
    assert fast == pytest.approx(full, rel=1e-10, abs=1e-12)


def test_trajectory_is_consistent_with_the_mean_speed():
    c = case(30, 0.8, 3, 1.2)
    n_cycles = 60
    tr = trajectory(c, n_cycles / c.frequency_hz, 20 * n_cycles + 1)
    per_cycle = tr['x'][::20]
    # last 40 cycles (the periodic state)
    slope = (per_cycle[-1] - per_cycle[-41]) / (40 / c.frequency_hz)
    assert slope == pytest.approx(mean_speed(c), rel=1e-9)
    assert np.all(tr['z'] >= -1e-15)
    assert {'stick', 'slide+', 'flight'} <= set(tr['phase'])


def test_mean_speed_units():
    c = case(30, 0.8, 3, 1.2)
    # reference section 0 item 7: 1.307 g_n / omega = 40.8 mm/s at 50 Hz
    assert mean_speed(c) * 1e3 == pytest.approx(40.8, abs=0.05)
    assert c.amplitude * 1e3 == pytest.approx(0.238, abs=5e-4)
