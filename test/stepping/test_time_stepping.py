"""``time_stepping`` regressions with analytic answers: bodies at rest stay at rest whatever
their mass ratio, and a fast part does not pass through a thin wall."""

import dataclasses
import math

import numpy as np
import pytest

from feeder_sim.model.builders import box, build, conveyor, scene_dict
from feeder_sim.simulator import Simulator
import feeder_sim.stepping.time_stepping.stepper as TS

G = 9.81


def _box(name, half_w, half_h, pose, mass):
    return {'name': name, 'type': 'dynamic', 'polygon': box(half_w, half_h), 'mass': mass,
            'pose': list(pose), 'mu_static': 0.5, 'mu_dynamic': 0.5}


def heavy_on_light(ratio: float) -> Simulator:
    """A 200 x 20 mm plank ``ratio`` times heavier than the two 10 mm boxes it rests on."""
    ground = {'name': 'ground', 'type': 'static', 'polygon': box(1.0, 0.05),
              'pose': [0.0, -0.05, 0.0], 'mu_static': 0.5, 'mu_dynamic': 0.5}
    bodies = [ground, _box('leg_left', 0.005, 0.005, (-0.08, 0.005, 0.0), 1e-3),
              _box('leg_right', 0.005, 0.005, (0.08, 0.005, 0.0), 1e-3),
              _box('plank', 0.1, 0.01, (0.0, 0.02, 0.0), 1e-3 * ratio)]
    return Simulator(build(scene_dict('heavy_on_light', bodies, 'time_stepping', 1e-3,
                                      gravity=(0.0, -G))))


def test_light_boxes_under_a_heavy_plank_stay_at_rest():
    # exact answer: nothing moves. Tolerance 1e-9 m / rad over 1 s (1000 steps): a corner
    # approach velocity of 1e-8 m/s per step, which the Dantzig pass once took for zero,
    # rocked the light boxes into the ground by 1e-9 m per 0.4 s and then kicked them by mm
    sim = heavy_on_light(1e6)
    p0, a0 = sim.state.position.copy(), sim.state.angle.copy()
    worst = 0.0
    for k in range(1, 11):
        sim.advance(0.1 * k)
        worst = max(worst, float(np.abs(sim.state.position - p0).max()),
                    float(np.abs(sim.state.angle - a0).max()))
    assert worst <= 1e-9
    assert sim.stats.max_penetration_m <= 1e-9


def test_reference_impulse_lcp_holds_the_light_boxes_still():
    # The first step's island solved by the reference path (lcp.solve): every body starts at
    # rest, so the impulses must cancel one step of gravity exactly, dv = (0, g h, 0) for
    # each. Tolerance 1e-10 m/s (1e-8 rad/s at a 5 mm corner lever); the global zero test
    # of the Dantzig pass left the light boxes at -4.9e-9 m/s and -9.8e-7 rad/s.
    sim = heavy_on_light(1e6)
    stepper = sim._stepper
    stepper.settings.compiled = False       # the Python step, whose island solve is watched
    h = sim.scene.solver.time_step
    seen = []

    def solve(cs, geo, todo, b_n, b_t, box, lo, hi, slip, colliding, half_vel, half_om, keys,
              p_n, p_t, p_state):
        (i,) = np.flatnonzero(todo)
        order = geo.order
        v_t_pre = np.zeros(cs.n)
        _, dv = TS.solve_impulses(sim.world, cs.subset(order), geo.island_bodies(i), b_n, b_t,
                                  v_t_pre, np.zeros(cs.n, bool), True, stepper.settings,
                                  sim.stats)
        seen.append(dv)
        return original(cs, geo, todo, b_n, b_t, box, lo, hi, slip, colliding, half_vel,
                        half_om, keys, p_n, p_t, p_state)

    original = stepper._solve
    stepper._solve = solve
    sim.advance(h)
    (dv,) = seen
    expected = np.tile([0.0, G * h, 0.0], (3, 1))
    assert np.abs(dv[:, :2] - expected[:, :2]).max() <= 1e-10
    assert np.abs(dv[:, 2]).max() <= 1e-8


WALL_X, WALL_HALF, PART_HALF = 0.05, 0.0005, 0.005


def thrown_at_thin_wall(omega: float, angle: float, mu: float, h: float = 1e-3) -> Simulator:
    """A 10 mm part at 10 m/s towards a 1 mm wall, no gravity: 10 mm per step at h = 1 ms."""
    material = {'mu_static': mu, 'mu_dynamic': mu, 'restitution': 0.5}
    wall = {'name': 'wall', 'type': 'static', 'polygon': box(WALL_HALF, 0.1),
            'pose': [WALL_X, 0.0, 0.0], **material}
    part = {'name': 'part', 'type': 'dynamic', 'polygon': box(PART_HALF, PART_HALF),
            'mass': 0.01, 'pose': [0.0, 0.0, angle], 'velocity': [10.0, 0.0, omega], **material}
    return Simulator(build(scene_dict('thrown', [wall, part], 'time_stepping', h,
                                      gravity=(0.0, 0.0))))


@pytest.mark.parametrize('omega, angle, mu', [(0.0, 0.0, 0.0), (0.0, 0.2, 0.3),
                                              (20.0, 0.2, 0.3)])
def test_fast_part_bounces_off_a_thin_wall(omega, angle, mu):
    # A rigid part cannot pass the wall's near face (tolerance 1e-9 m: the projection's
    # slop) and leaves towards where it came from with no more than its kinetic energy.
    # The wall is thinner than one step's travel; found only at the midpoint where the part
    # is already inside it, the contact was taken on the far face or missed
    sim = thrown_at_thin_wall(omega, angle, mu)
    corners = np.array(box(PART_HALF, PART_HALF))
    e0 = sim.world.kinetic_energy(sim.state)
    reach = -np.inf
    while sim.t < 0.03 - 1e-12:
        sim.advance(sim.t + 1e-3)
        p, a = sim.state.position[1], sim.state.angle[1]
        x = p[0] + np.cos(a) * corners[:, 0] - np.sin(a) * corners[:, 1]
        reach = max(reach, float(x.max()))
    assert reach - (WALL_X - WALL_HALF) <= 1e-9
    assert sim.state.velocity[1, 0] < 0.0
    assert sim.world.kinetic_energy(sim.state) <= e0 * (1 + 1e-12)


def test_a_part_held_back_by_a_speculative_row_bounces_the_speed_it_came_in_with():
    # The flat, frictionless hit: 10 m/s into the wall, e = 0.5, so it must leave at exactly
    # 5 m/s with a quarter of its kinetic energy. The speculative row slowed it to what the
    # step allowed before it touched; bouncing that speed left it at 4.81 m/s.
    sim = thrown_at_thin_wall(0.0, 0.0, 0.0)
    e0 = sim.world.kinetic_energy(sim.state)
    sim.advance(0.03)
    assert abs(sim.state.velocity[1, 0] + 5.0) <= 1e-9
    assert abs(sim.state.velocity[1, 1]) <= 1e-12 and abs(sim.state.omega[1]) <= 1e-12
    assert abs(sim.world.kinetic_energy(sim.state) / e0 - 0.25) <= 1e-9


PLATE_HALF = 0.0005


def plates(gap_m: float) -> dict:
    """Two 1 x 20 mm plates ``gap_m`` apart, 10 m/s each towards the other, e = 0.5, no
    gravity."""
    material = {'mu_static': 0.3, 'mu_dynamic': 0.3, 'restitution': 0.5}
    bodies = [{'name': name, 'type': 'dynamic', 'polygon': box(PLATE_HALF, 0.01), 'mass': 0.01,
               'pose': [x, 0.0, 0.0], 'velocity': [v, 0.0, 0.0], **material}
              for name, x, v in (('left', -0.5 * gap_m - PLATE_HALF, 10.0),
                                 ('right', 0.5 * gap_m + PLATE_HALF, -10.0))]
    return build(scene_dict('plates', bodies, 'time_stepping', 1e-3, gravity=(0.0, 0.0)))


@pytest.mark.parametrize('gap_m', [0.018, 0.025, 0.0265, 0.028, 0.029, 0.045])
def test_thin_parts_thrown_at_each_other_bounce(gap_m):
    # Two 1 x 20 mm plates, 10 m/s each towards the other: they close 20 mm per 1 ms step,
    # twice as far as either moves. A contact search reaching 1.5 steps of the fastest part's
    # travel missed them from some starting gaps, and they passed through each other. Head
    # on with e = 0.5 each must leave at 5 m/s, never having overlapped beyond the slop.
    sim = Simulator(plates(gap_m))
    closest = np.inf
    while sim.t < 0.01 - 1e-12:
        sim.advance(sim.t + 1e-3)
        x = sim.state.position[:, 0]
        closest = min(closest, x[1] - x[0] - 2 * PLATE_HALF)
    assert closest >= -1e-9
    assert np.allclose(sim.state.velocity[:, 0], (-5.0, 5.0), rtol=0.0, atol=1e-9)


def _count_calls(obj, name: str) -> list:
    """A list that grows by one at every call of ``obj.name`` (which still runs)."""
    calls, method = [], getattr(obj, name)

    def counted(*args, **kw):
        calls.append(1)
        return method(*args, **kw)

    setattr(obj, name, counted)
    return calls


@pytest.mark.parametrize('case', ['wall flat', 'wall spinning', 'plates'])
def test_bouncing_steps_run_compiled_with_the_reference_bits(case):
    # Fast bouncy parts: shortened steps, and the velocities a speculative row held back
    # for the collision a step later (TimeStepper._approach) where one does. The compiled
    # step takes them all itself: no step goes back to Python, and every step has the
    # reference step's bits.
    runs = []
    for compiled in (True, False):
        if case == 'plates':
            sim = Simulator(plates(0.025), settings=TS.TimeStepSettings(compiled=compiled))
        else:
            omega, angle, mu = (0.0, 0.0, 0.0) if case == 'wall flat' else (20.0, 0.2, 0.3)
            scene = thrown_at_thin_wall(omega, angle, mu).scene
            sim = Simulator(scene, settings=TS.TimeStepSettings(compiled=compiled))
        stepper = sim._stepper
        python_steps = _count_calls(stepper, 'step')
        held, states = 0, []
        for k in range(1, 31):
            sim.advance(k * 1e-3)
            held += bool(stepper._approach)
            states.append(np.concatenate([sim.state.position.ravel(), sim.state.angle,
                                          sim.state.velocity.ravel(), sim.state.omega]))
        runs.append((np.array(states), len(python_steps), held, sim.stats.as_dict()))
    (got, got_python, got_held, got_stats), (ref, ref_python, ref_held, ref_stats) = runs
    assert got.tobytes() == ref.tobytes()
    assert got_stats == ref_stats
    # every step of the reference went through Python (the frames' and those shortened
    # where the part closes fast), none of the compiled run's
    assert got_python == 0 and ref_python == ref_stats['steps'] > 30
    assert got_held == ref_held


def test_a_hopping_pile_warm_starts_from_the_last_step_with_contacts():
    # Three boxes hopping on a track at Gamma 2.5 all leave it at once; each landing is
    # solved by PGS (direct_max_rows = 0), warm-started from the impulses of the last step
    # that had contacts, several steps back: the compiled step carries them (and the
    # held-back velocities) over the contact-free steps. Frames of 10 steps against the
    # reference step, bit for bit.
    runs = []
    for compiled in (True, False):
        scene = build(conveyor(psi=math.radians(20.0), mu=0.5, theta=0.0, gamma=2.5,
                               method='time_stepping', time_step=1e-3, n_parts=3,
                               spacing=0.05, track_length=0.4))
        sim = Simulator(scene, settings=TS.TimeStepSettings(compiled=compiled,
                                                            direct_max_rows=0))
        states = []
        for k in range(1, 21):
            sim.advance(k * 0.01)
            states.append(np.concatenate([sim.state.position.ravel(),
                                          sim.state.velocity.ravel()]))
        runs.append((np.array(states), sim.stats.as_dict()))
    (got, got_stats), (ref, ref_stats) = runs
    assert ref_stats['pgs_solves'] > 20
    assert got.tobytes() == ref.tobytes()
    assert got_stats == ref_stats


@pytest.mark.parametrize('dt', [1e-4, 1e-3])
@pytest.mark.parametrize('gamma', [0.5, 1.5])
def test_row_states_of_the_step_before_give_dantzigs_answer_without_its_pivots(gamma, dt):
    # One box on a track vibrating at 50 Hz, sliding on it (Gamma 0.5) or hopping (1.5), for
    # 0.5 s: solving each small island first in the row states of the step before, and each
    # position projection in those of the contacts' last projection (reuse_row_states), must
    # give Baraff-Dantzig's answers from scratch to round-off: states within 1e-15 m, m/s and
    # rad (measured: 3.5e-18 m, 2.4e-16 m/s, 3.7e-17 rad at most), with at most half of its
    # pivots (measured: 275 against 20 086 sliding and 169 against 10 106 hopping at dt 1e-4,
    # 421 against 2 055 and 196 against 915 at dt 1e-3).
    runs = {}
    for reuse in (True, False):
        sim = Simulator(build(conveyor(psi=math.radians(20.0), mu=0.5, theta=0.0, gamma=gamma,
                                       frequency_hz=50.0, method='time_stepping',
                                       time_step=dt, name='conveying')))
        sim._stepper.settings.reuse_row_states = reuse
        sim.advance(0.5)
        runs[reuse] = sim
    on, off = runs[True], runs[False]
    assert np.abs(on.state.position - off.state.position).max() <= 1e-15
    assert np.abs(on.state.velocity - off.state.velocity).max() <= 1e-15
    assert np.abs(on.state.angle - off.state.angle).max() <= 1e-15
    assert on.stats.steps == off.stats.steps and on.stats.fallbacks == 0
    assert off.stats.pivots > 0 and on.stats.pivots <= 0.5 * off.stats.pivots
    assert on.state.position[1, 0] > 0.005          # it conveys: 5 mm or more in 0.5 s


def hopping_boxes(**settings) -> Simulator:
    """Three boxes hopping on a 50 Hz track (Gamma 2.5), stepped by the compiled step."""
    scene = build(conveyor(psi=math.radians(20.0), mu=0.5, theta=0.0, gamma=2.5,
                           method='time_stepping', time_step=1e-3, n_parts=3, spacing=0.05,
                           track_length=0.4))
    return Simulator(scene, settings=TS.TimeStepSettings(**settings))


def test_frames_through_the_kernels_entry_point_give_the_dispatchers_bits():
    # A frame after the first calls the compiled step's entry point directly (no typing of its
    # arguments); a caller that replaces the state's arrays between frames sends every call
    # through numba's dispatcher again. 1 ms frames (one step each) of three hopping boxes:
    # the same bits both ways, and the replaced arrays are the ones stepped.
    runs = []
    for replace in (False, True):
        sim = hopping_boxes(direct_max_rows=0)
        kernel = sim._stepper._advance_kernel
        states = []
        for k in range(1, 101):
            if replace:
                s = sim.state
                s.position, s.angle = s.position.copy(), s.angle.copy()
                s.velocity, s.omega = s.velocity.copy(), s.omega.copy()
            sim.advance(k * 1e-3)
            assert kernel._entry is not None
            assert kernel._watched[0] is sim.state.position
            states.append(np.concatenate([sim.state.position.ravel(), sim.state.angle,
                                          sim.state.velocity.ravel(), sim.state.omega]))
        runs.append((np.array(states), sim.stats.as_dict()))
    (fast, fast_stats), (dispatched, dispatched_stats) = runs
    assert fast_stats['pgs_solves'] > 20 and fast_stats['steps'] == 100
    assert fast.tobytes() == dispatched.tobytes()
    assert fast_stats == dispatched_stats


def test_settings_changed_on_a_live_stepper_reach_the_compiled_step():
    # The compiled step's settings are made once and again after any assignment to a setting,
    # a new settings object, or a new time step: each change shows in what the steps do.
    sim = hopping_boxes(direct_max_rows=0)
    stepper = sim._stepper
    sim.advance(0.1)
    assert sim.stats.unconverged == 0 and sim.stats.steps == 100
    stepper.settings.pgs_max_sweeps = 1        # one sweep cannot converge a landing
    sim.advance(0.2)
    assert sim.stats.unconverged > 0
    stepper.settings = TS.TimeStepSettings(direct_max_rows=0)
    missed = sim.stats.unconverged
    sim.advance(0.3)
    assert sim.stats.unconverged == missed and sim.stats.steps == 300
    stepper.spec = dataclasses.replace(stepper.spec, time_step=5e-4)
    sim.advance(0.4)
    assert sim.stats.steps == 500


def test_frames_after_reference_steps_go_through_the_dispatcher_again():
    # Reference steps leave the warm start and held-back velocities in arrays of their own
    # making: the compiled step's next call re-dispatches, and the frames match a run that
    # stayed compiled, bit for bit.
    runs = []
    for switch in (False, True):
        sim = hopping_boxes(direct_max_rows=0)
        stepper, kernel = sim._stepper, sim._stepper._advance_kernel
        for k in range(1, 61):
            if switch:
                stepper.settings.compiled = not (20 < k <= 40)
            sim.advance(k * 1e-3)
            if switch and k == 40:
                assert kernel._entry is None
        assert kernel._entry is not None
        runs.append(np.concatenate([sim.state.position.ravel(), sim.state.velocity.ravel()]))
    assert runs[0].tobytes() == runs[1].tobytes()
