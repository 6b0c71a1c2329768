"""Sliding where no contact force is consistent (Painlevé), and very high friction.

A contact that slides on a ray along which its normal velocity would fall
(K_NN - mu sigma K_TN < 0 in its collision matrix) has no consistent contact force: it takes an
impulse although it does not approach, Génot & Brogliato's tangential impact. The reference
here integrates that impulse from the Darboux-Keller equations in small normal-impulse steps,
independently of the method's closed form. A box thrown along the floor with mu above its
aspect ratio (2 for a 2:1 box) must tip and tumble, never slide on without friction.
"""

import math

import numpy as np
import pytest

from feeder_sim.model.builders import box_part, build, G, ground, scene_dict
from feeder_sim.simulator import Simulator

L, T, THETA, MU = 0.1, 0.001, math.radians(60.0), 1.5
MASS = 0.01                                   # box_part's default, kg


def rod_scene(method: str, dt: float) -> Simulator:
    y = L * math.sin(THETA) + T * math.cos(THETA)
    bodies = [ground(mu=MU), box_part('rod', L, T, (0.0, y, THETA), (-1.0, 0.0, 0.0), mu=MU)]
    return Simulator(build(scene_dict('painleve', bodies, method, dt)))


def darboux_keller(r: np.ndarray, v: np.ndarray, mu: float, inertia: float,
                   steps: int = 200_000) -> tuple[np.ndarray, float]:
    """Velocity and spin after a tangential impact of a body's point ``r`` (from its centre)
    on the floor (normal +y, tangent -x), from rest in the normal direction, with restitution
    0: explicit integration in p_N of du/dp_N = K (f_T, 1), f_T = -mu sign(u_T) while it
    slides, the sticking ray once u_T = 0, until u_N is back to 0."""
    n, t = np.array([0.0, 1.0]), np.array([-1.0, 0.0])

    def point_velocity(v, w):
        return v + w * np.array([-r[1], r[0]])

    def kick(p):
        return p / MASS, (r[0] * p[1] - r[1] * p[0]) / inertia

    # the collision matrix by its definition: velocity change of the point per unit impulse
    K = np.empty((2, 2))
    for j, e in enumerate((t, n)):
        dv, dw = kick(e)
        du = point_velocity(dv, dw)
        K[0, j], K[1, j] = du @ t, du @ n
    u = np.array([point_velocity(v, 0.0) @ t, 0.0])
    assert K[1, 1] - mu * np.sign(u[0]) * K[1, 0] < 0           # a Painlevé ray
    p = np.zeros(2)
    dp = MASS * abs(u[0]) / (1 + mu) / steps
    for _ in range(50 * steps):
        if abs(u[0]) > 1e-12 and u[1] <= 0:
            f_t = -mu * np.sign(u[0])
        elif u[1] < 0:
            f_t = -K[0, 1] / K[0, 0]            # sticking holds: |K_TN| <= mu K_TT here
            u[0] = 0.0
        else:
            break
        step = dp
        du = K @ np.array([f_t, 1.0])
        if abs(u[0]) > 1e-12 and np.sign(u[0] + du[0] * step) != np.sign(u[0]):
            step = -u[0] / du[0]                # land exactly on the end of the slip
        if u[0] == 0.0 and u[1] + du[1] * step > 0:
            step = -u[1] / du[1]
        u = u + du * step
        p = p + np.array([f_t, 1.0]) * step
    dv, dw = kick(p[0] * t + p[1] * n)
    return v + dv, dw


@pytest.mark.parametrize('dt', [1e-2, 1e-1], ids=['default', 'coarse'])
def test_a_sliding_rod_without_consistent_forces_takes_the_tangential_impact(dt):
    sim = rod_scene('event_driven', dt)
    body = sim.world.dynamic.nonzero()[0][0]
    # the tip: the rod's lowest corner
    corners = np.array([[-L, -T], [L, -T], [L, T], [-L, T]])
    c, s = math.cos(THETA), math.sin(THETA)
    world = corners @ np.array([[c, s], [-s, c]])
    r = world[np.argmin(world[:, 1])]
    inertia = MASS * ((2 * L) ** 2 + (2 * T) ** 2) / 12
    v_ref, w_ref = darboux_keller(r, np.array([-1.0, 0.0]), MU, inertia)
    h = 1e-7
    sim.advance(h)
    v = sim.state.velocity[body] - h * np.array([0.0, -G])
    assert sim.stats.tangential_impacts == 1
    assert np.allclose(v, v_ref, atol=2e-5)
    assert sim.state.omega[body] == pytest.approx(w_ref, abs=2e-4)
    # the impulse dissipates: kinetic energy falls
    assert sim.world.kinetic_energy(sim.state) < 0.5 * MASS * 1.0


@pytest.mark.parametrize('method, dt', [('time_stepping', 1e-5), ('impulse_based', 1e-4)])
def test_every_method_gives_the_same_rod_motion(method, dt):
    # the other two methods reach the tangential impact by their own means
    ed, other = rod_scene('event_driven', 1e-2), rod_scene(method, dt)
    for t in (0.01, 0.05):
        ed.advance(t)
        other.advance(t)
        assert np.allclose(ed.state.position, other.state.position, atol=3e-5)
        assert np.allclose(ed.state.velocity, other.state.velocity, atol=3e-3)


def thrown_box(method: str, mu: float, dt: float) -> Simulator:
    bodies = [ground(mu=mu),
              box_part('box', 0.01, 0.005, (0.0, 0.005, 0.0), (1.0, 0.0, 0.0), mu=mu)]
    return Simulator(build(scene_dict('thrown', bodies, method, dt)))


@pytest.mark.timeout(300)
@pytest.mark.parametrize('mu', [3.0, 10.0])
@pytest.mark.parametrize('dt', [1e-2, 1e-1], ids=['default', 'coarse'])
def test_a_box_thrown_with_high_friction_tumbles_and_stops(mu, dt):
    ed = thrown_box('event_driven', mu, dt)
    ts = thrown_box('time_stepping', mu, 1e-4)
    energy = []
    for k in range(1, 51):
        ed.advance(0.01 * k)
        energy.append(ed.world.kinetic_energy(ed.state) + ed.world.potential_energy(ed.state))
    ts.advance(0.5)
    # no drive and e = 0: mechanical energy never rises
    assert np.all(np.diff(energy) <= 1e-12)
    assert ed.stats.frictionless_answers == 0 and ed.stats.unresolved_force_lcps == 0
    assert ed.stats.inexact() == {}
    assert np.linalg.norm(ed.state.velocity[1]) < 1e-6
    # it tipped over the leading edge onto its other long face, where time stepping puts it
    assert abs(math.cos(ed.state.angle[1])) == pytest.approx(1.0, abs=1e-9)
    assert ed.state.position[1, 0] == pytest.approx(ts.state.position[1, 0], abs=5e-4)
    # sliding alone would stop after v0^2 / (2 mu g): tumbling carries it further
    assert ed.state.position[1, 0] > 1.0 / (2 * mu * G)


def test_a_fallback_that_loses_friction_is_reported_once(caplog):
    sim = thrown_box('event_driven', 3.0, 1e-2)
    sim.stats.frictionless_answers = 2           # as the fallback ladder counts them
    with caplog.at_level('ERROR', logger='feeder_sim'):
        sim.advance(0.01)
        sim.advance(0.02)
    lines = [r.getMessage() for r in caplog.records if 'without friction' in r.getMessage()]
    assert len(lines) == 1 and 'friction was lost' in lines[0]
