"""event_driven collision events in degenerate and fast configurations.

* Blocks meeting face-on with exactly aligned corners: every corner lies on the line of a side
  face of the other block while the faces overlap, so no corner is ever strictly inside the
  other block; the collision must still be seen (Newton's cradle of the stability report).
* A part thrown at a thin wall faster than the wall's thickness per largest step: the steps
  shorten near the wall so the part cannot pass through it between two event tests, in
  closed-form phases and in integrated ones.
"""

import math

import numpy as np
import pytest

from feeder_sim.contact import lcp
from feeder_sim.model.builders import box, build, conveyor, scene_dict
from feeder_sim.simulator import Simulator
from feeder_sim.stepping.event_driven import _kernels as kern
from feeder_sim.stepping.event_driven.events import CandidateWatch
from feeder_sim.stepping.event_driven.stepper import EventSettings

HALF_M = 0.005        # half side of the 10 mm blocks
MASS_KG = 0.01


def block(name, x_m, y_m, vx_mps, vy_mps=0.0):
    return {'name': name, 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M), 'mass': MASS_KG,
            'pose': [x_m, y_m, 0.0], 'velocity': [vx_mps, vy_mps, 0.0], 'mu_static': 0.0,
            'mu_dynamic': 0.0, 'restitution': 1.0}


def run(bodies, duration_s, time_step_s=1e-2):
    sim = Simulator(build(scene_dict('blocks', bodies, 'event_driven', time_step_s,
                                     gravity=(0.0, 0.0))))
    sim.advance(duration_s)
    return sim


@pytest.mark.parametrize('time_step_s', [1e-2, 1e-4])
def test_aligned_blocks_exchange_velocities(time_step_s):
    # e = 1, equal masses, face-on: the moving block stops and the other leaves at 1 m/s.
    sim = run([block('a', -0.012, 0.0, 1.0), block('b', 0.0, 0.0, 0.0)], 0.01, time_step_s)
    assert sim.stats.impacts == 1
    assert np.allclose(sim.state.velocity[:, 0], (0.0, 1.0), rtol=0.0, atol=1e-9)
    # They met after 2 mm of travel, 2 ms in: a at -0.010 m since, b 8 mm on from 0.
    assert np.allclose(sim.state.position[:, 0], (-0.010, 0.008), rtol=0.0, atol=1e-9)


def test_newton_cradle_gives_the_simultaneous_answer():
    # Kawachi's simultaneous impulse LCP over both contacts (the touching pair enters with
    # v_N = 0): (-1/3, 2/3, 2/3) v, momentum and kinetic energy kept (e = 1).
    sim = run([block('a', -0.012, 0.0, 1.0), block('b', 0.0, 0.0, 0.0),
               block('c', 2 * HALF_M, 0.0, 0.0)], 0.01)
    v = sim.state.velocity[:, 0]
    assert np.allclose(v, (-1 / 3, 2 / 3, 2 / 3), rtol=0.0, atol=1e-9)
    assert abs(np.sum(v) - 1.0) <= 1e-12
    assert abs(0.5 * MASS_KG * np.sum(v ** 2) / (0.5 * MASS_KG) - 1.0) <= 1e-9


@pytest.mark.parametrize('start, velocity', [
    ((-2 * HALF_M, 0.0), (0.0, 1.0)),    # side by side, sliding past along the shared face
    ((0.0, 2 * HALF_M), (1.0, 0.0)),     # on top, sliding off along the shared face
])
def test_flush_blocks_sliding_past_each_other_do_not_collide(start, velocity):
    # Corners pass corners along the shared face line: nothing enters anything, so no impact
    # and the velocities stay exactly as they were.
    sim = run([block('a', *start, *velocity), block('b', 0.0, 0.0, 0.0)], 0.02)
    assert sim.stats.impacts == 0
    assert np.array_equal(sim.state.velocity[0], velocity)
    assert np.array_equal(sim.state.velocity[1], (0.0, 0.0))


# A 10 mm part thrown at 10 m/s at a 1 mm wall whose near face is at x = 49.5 mm: head-on it
# meets it after 44.5 mm, at 4.45 ms, and leaves at -e v = -5 m/s.
WALL_X_M, WALL_HALF_M = 0.05, 0.0005
THROW_MPS, WALL_E = 10.0, 0.5
HIT_S = (WALL_X_M - WALL_HALF_M - HALF_M) / THROW_MPS
END_S = 0.03
G = 9.81


def thrown_scene(time_step_s, gravity=0.0, angle_rad=0.0, omega_radps=0.0, rocker=False):
    y_m = 0.1
    bodies = [
        {'name': 'wall', 'type': 'static', 'polygon': box(WALL_HALF_M, 0.1),
         'pose': [WALL_X_M, y_m, 0.0], 'mu_static': 0.3, 'mu_dynamic': 0.3,
         'restitution': WALL_E},
        {'name': 'part', 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M), 'mass': MASS_KG,
         'pose': [0.0, y_m, angle_rad], 'velocity': [THROW_MPS, 0.0, omega_radps],
         'mu_static': 0.3, 'mu_dynamic': 0.3, 'restitution': WALL_E}]
    if rocker:
        # A block tilted 0.1 rad on its corner, far away: it rocks, so every phase is
        # integrated rather than followed in closed form.
        tilt = 0.1
        bodies += [
            {'name': 'ground', 'type': 'static', 'polygon': box(1.0, 0.05),
             'pose': [0.0, -0.05, 0.0], 'mu_static': 0.8, 'mu_dynamic': 0.8},
            {'name': 'rocker', 'type': 'dynamic', 'polygon': box(0.01, 0.05), 'mass': 0.1,
             'pose': [-0.5, 0.05 * np.cos(tilt) + 0.01 * np.sin(tilt), tilt],
             'mu_static': 0.8, 'mu_dynamic': 0.8}]
    return scene_dict('thrown', bodies, 'event_driven', time_step_s, gravity=(0.0, gravity))


def thrown(time_step_s, **kw):
    sim = Simulator(build(thrown_scene(time_step_s, **kw)))
    sim.advance(END_S)
    return sim


@pytest.mark.parametrize('time_step_s', [1e-2, 1e-3])
def test_thrown_part_bounces_off_a_thin_wall(time_step_s):
    sim = thrown(time_step_s)
    x_hit = WALL_X_M - WALL_HALF_M - HALF_M
    assert sim.stats.impacts == 1
    assert abs(sim.state.velocity[1, 0] + WALL_E * THROW_MPS) <= 1e-9
    assert abs(sim.state.position[1, 0] - (x_hit - WALL_E * THROW_MPS * (END_S - HIT_S))) <= 1e-9
    assert sim.stats.max_penetration_m <= 1e-9


def test_spinning_part_thrown_at_a_thin_wall_does_not_depend_on_the_step():
    # Spinning, it meets the wall corner first and bounces twice; the exact answer does not
    # depend on the largest step, so a 10 ms step must give that of a 0.1 ms one.
    coarse, fine = (thrown(h, angle_rad=0.2, omega_radps=20.0) for h in (1e-2, 1e-4))
    assert coarse.state.position[1, 0] < 0.0 and coarse.state.velocity[1, 0] < 0.0
    assert np.allclose(coarse.state.position[1], fine.state.position[1], rtol=0.0, atol=1e-9)
    assert np.allclose(coarse.state.velocity[1], fine.state.velocity[1], rtol=0.0, atol=1e-9)
    assert coarse.stats.max_penetration_m <= 1e-9


def test_thrown_part_bounces_off_a_thin_wall_while_another_body_rocks():
    # Under gravity the part meets the wall head-on with v_y = -g t_hit; friction (mu 0.3
    # against a normal impulse of 1.5 m v) stops that slip, so it leaves at (-e v, 0) and
    # falls again from there.
    sim = thrown(1e-2, gravity=-G, rocker=True)
    fall_m = 0.5 * G * (HIT_S ** 2 + (END_S - HIT_S) ** 2)
    x_hit = WALL_X_M - WALL_HALF_M - HALF_M
    assert np.allclose(sim.state.velocity[1, :2], (-WALL_E * THROW_MPS, -G * (END_S - HIT_S)),
                       rtol=0.0, atol=1e-9)
    assert np.allclose(sim.state.position[1], (x_hit - WALL_E * THROW_MPS * (END_S - HIT_S),
                                               0.1 - fall_m), rtol=0.0, atol=1e-9)
    assert abs(sim.state.angle[3] - 0.1) > 1e-3      # the rocker did rock


FALL_M, DROP_MPS = 30.0, 50.0


@pytest.mark.parametrize('time_step_s', [1e-3, 1e-2], ids=['default', 'coarse'])
@pytest.mark.parametrize('chained', [True, False])
def test_part_falling_fast_lands_where_free_fall_says_with_a_detection_per_frame(
        monkeypatch, chained, time_step_s):
    # Thrown down at 50 m/s towards a floor 30 m below, a 10 mm box covers 50-80 mm per 1 ms
    # step, more than its candidates' margin (a few body sizes). It must fly the parabola to
    # the floor and stay there (e = 0) with its candidate collisions detected again about
    # once per 10 ms frame, not several times per step.
    floor = {'name': 'floor', 'type': 'static', 'polygon': box(1.0, 0.05),
             'pose': [0.0, -FALL_M - 0.05, 0.0], 'mu_static': 0.5, 'mu_dynamic': 0.5}
    part = {'name': 'part', 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M),
            'mass': MASS_KG, 'pose': [0.0, 0.0, 0.0], 'velocity': [0.0, -DROP_MPS, 0.0],
            'mu_static': 0.5, 'mu_dynamic': 0.5, 'restitution': 0.0}
    sim = Simulator(build(scene_dict('fall', [floor, part], 'event_driven', time_step_s)),
                    settings=EventSettings(chained=chained))
    detections = []
    find = CandidateWatch.find

    def counted(watch, state, margin):
        detections.append(state.t)
        return find(watch, state, margin)

    monkeypatch.setattr(CandidateWatch, 'find', counted)
    drop = FALL_M - HALF_M              # the part's bottom face to the floor's top
    t_land = (-DROP_MPS + math.sqrt(DROP_MPS ** 2 + 2 * G * drop)) / G
    frames = 70
    for k in range(1, frames + 1):
        sim.advance_to(k * 0.01)
        t = min(sim.t, t_land)
        assert abs(sim.state.position[1, 1] - (-DROP_MPS * t - 0.5 * G * t * t)) <= 1e-9
    assert t_land < sim.t
    assert sim.stats.impacts == 1
    assert np.allclose(sim.state.velocity[1], 0.0, rtol=0.0, atol=1e-9)
    assert len(detections) <= 2 * frames, len(detections)


# --------------------------------------------------------------------------- compiled paths
# The per-event work of the closed-form conveying phases runs in compiled kernels; each is
# checked against the numpy / lcp.solve code it replaced, on the problems a vibrating track
# poses (sliding, and hopping with landings).

def conveying_run(monkeypatch, name, gamma):
    """Arguments and answers of every call of the kernel ``name`` while a box conveys."""
    calls = []
    kernel = getattr(kern, name)

    def record(*args):
        out = kernel(*args)
        calls.append((args, out))
        return out

    monkeypatch.setattr(kern, name, record)
    # unchained: the chain calls the kernels from compiled code, out of the recorder's sight
    sim = Simulator(build(conveyor(psi=math.radians(20.0), mu=0.5, theta=0.0, gamma=gamma,
                                   tolerance=1e-6)), settings=EventSettings(chained=False))
    sim.advance(0.2)
    monkeypatch.undo()
    return calls


@pytest.mark.parametrize('gamma', [0.8, 1.5])
def test_compiled_dantzig_matches_lcp_solve(monkeypatch, gamma):
    calls = conveying_run(monkeypatch, 'lcp_dantzig', gamma)
    assert len(calls) >= 4
    for (W, b_full, friction, mu_lo, mu_hi, slave), (f, x, w, res, _, _, _) in calls:
        A, P, rows, normal_of, lo, hi = kern.reduce_lcp(W, friction, mu_lo, mu_hi, slave)
        ref = lcp.solve(lcp.FrictionalLCP(A, b_full[rows], normal_of, lo, hi), tol=1e-9)
        assert ref.method == 'dantzig' and res <= 1e-9
        assert abs(res - ref.residual) <= 1e-15
        scale = np.abs(ref.x).max()
        assert np.allclose(x, ref.x, rtol=0.0, atol=1e-12 * scale)
        assert np.allclose(f, P @ ref.x, rtol=0.0, atol=1e-12 * scale)
        assert np.allclose(w, A @ ref.x + b_full[rows], rtol=0.0,
                           atol=1e-12 * np.abs(b_full).max())


def conveying(gamma, theta_deg=0.0):
    return conveyor(psi=math.radians(20.0), mu=0.5, theta=math.radians(theta_deg), gamma=gamma,
                    tolerance=1e-6)


def dropped_tilted():
    """A block dropped 5 mm onto the ground at 0.3 rad: it lands on a corner and rocks."""
    return scene_dict('dropped', [
        {'name': 'ground', 'type': 'static', 'polygon': box(0.2, 0.01), 'pose': [0.0, -0.01, 0.0],
         'mu_static': 0.6, 'mu_dynamic': 0.5, 'restitution': 0.3},
        {'name': 'part', 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M), 'mass': MASS_KG,
         'pose': [0.0, 0.005 + HALF_M * (math.cos(0.3) + math.sin(0.3)), 0.3],
         'mu_static': 0.6, 'mu_dynamic': 0.5, 'restitution': 0.3}], 'event_driven', 1e-3)


def sliding_off_a_ledge():
    """A block sliding off the end of a ledge onto the floor 10 mm below, landing flat."""
    return scene_dict('ledge', [
        {'name': 'ledge', 'type': 'static', 'polygon': box(0.02, 0.005),
         'pose': [0.0, 0.005, 0.0], 'mu_static': 0.3, 'mu_dynamic': 0.2},
        {'name': 'floor', 'type': 'static', 'polygon': box(0.2, 0.005),
         'pose': [0.0, -0.005 - 0.01, 0.0], 'mu_static': 0.3, 'mu_dynamic': 0.2},
        {'name': 'part', 'type': 'dynamic', 'polygon': box(HALF_M, HALF_M), 'mass': MASS_KG,
         'pose': [0.0, 0.01 + HALF_M, 0.0], 'velocity': [0.6, 0.0, 0.0],
         'mu_static': 0.3, 'mu_dynamic': 0.2}], 'event_driven', 1e-3)


def tipping_from_stick():
    """A 10 x 60 mm block sticking (mu 0.3 > b / h = 1/6) on a platform driven 0.08 m at
    1.5 Hz, started with its velocity: it tips on its leading corner at 24.6 ms, where its
    trailing corner's force falls through zero (``kern.leaving``)."""
    amplitude, freq = 0.08, 1.5
    return scene_dict('tipping', [
        {'name': 'platform', 'type': 'kinematic', 'polygon': box(1.0, 0.01),
         'pose': [0.0, -0.01, 0.0], 'mu_static': 0.3, 'mu_dynamic': 0.3,
         'vibration': {'amplitude': amplitude, 'frequency': freq, 'angle': 0.0}},
        {'name': 'part', 'type': 'dynamic', 'polygon': box(0.005, 0.03), 'mass': MASS_KG,
         'pose': [0.0, 0.03, 0.0], 'velocity': [2 * math.pi * freq * amplitude, 0.0, 0.0],
         'mu_static': 0.3, 'mu_dynamic': 0.3}], 'event_driven', 1e-3)


@pytest.mark.parametrize('scene', [
    lambda: conveying(0.3), lambda: conveying(0.8), lambda: conveying(1.5, 3.0),
    lambda: conveying(0.8, -3.0), lambda: conveying(3.0), lambda: thrown_scene(1e-2, gravity=-G),
    lambda: thrown_scene(1e-2, angle_rad=0.2, omega_radps=20.0), dropped_tilted,
    sliding_off_a_ledge, tipping_from_stick],
    ids=['sticking', 'sliding', 'hopping uphill', 'sliding downhill', 'hopping high',
         'thrown at a wall', 'thrown spinning', 'dropped tilted', 'sliding off a ledge',
         'tipping from stick'])
def test_chained_phases_give_the_general_paths_answers(scene):
    """One body's closed-form phases chained through its events in compiled code (a box
    sticking, sliding and hopping on a track, uphill and down, thrown at a wall, landing on a
    corner, sliding off a ledge) give what taking every event through the general path gives:
    the same events, collisions and LCPs, states equal to round-off and the same contact
    impulses in every 10 ms report."""
    runs = []
    for chained in (False, True):
        sim = Simulator(build(scene()), settings=EventSettings(chained=chained))
        impulses = []
        for k in range(1, 31):
            sim.advance(0.01 * k)
            report = sim.take_contacts()
            impulses.append((report.normal_impulse.sum(), report.tangent_impulse.sum()))
        runs.append((sim, np.array(impulses)))
    (general, p_general), (chained, p_chained) = runs
    for count in ('events', 'impacts', 'lcp_solves', 'trivial_solves', 'energy_fixes'):
        assert getattr(chained.stats, count) == getattr(general.stats, count), count
    assert general.stats.events >= 1
    assert np.abs(chained.state.position - general.state.position).max() <= 1e-13
    assert np.abs(chained.state.velocity - general.state.velocity).max() <= 1e-12
    scale = np.abs(p_general).max()
    assert np.abs(p_chained - p_general).max() <= 1e-12 * scale


def test_compiled_leaving_matches_numpy(monkeypatch):
    """``kern.leaving`` against its numpy transcription, on the modes held while a block
    sticks, starts to tip and pivots (with the drive's terms) and on random forces."""
    calls = []
    kernel = kern.leaving

    def record(*args):
        out = kernel(*args)
        calls.append((args, out))
        return out

    monkeypatch.setattr(kern, 'leaving', record)
    sim = Simulator(build(tipping_from_stick()), settings=EventSettings(chained=False))
    sim.advance(0.05)
    monkeypatch.undo()
    assert sim.state.angle[1] < -1e-3                     # it tipped
    assert any(out.any() for _, out in calls)             # at the trailing corner's event
    rng = np.random.default_rng(3)
    for _ in range(20):
        k, nd = int(rng.integers(1, 4)), int(rng.integers(0, 3))
        drives = kern.Drives(np.zeros((nd, 2)), np.zeros((nd, 2)), rng.uniform(0, 1e-3, nd),
                             rng.uniform(1, 600, nd), rng.uniform(0, 6, nd), 0.1)
        f_lcp = rng.choice([0.0, 1e-14, 0.5], k)
        calls.append(((rng.uniform(0, 1), drives, f_lcp, rng.normal(0, 1e-9, 2 * k),
                       rng.normal(0, 1e-9, (2 * k, nd)), 1e-12, 1e-10), None))
    for (t, drives, f_lcp, f0, f1, force_tol, limit), out in calls:
        _, _, amp, w, phase, t_ref = drives
        k = len(f_lcp)
        s = -amp * w ** 2 * np.sin(phase + w * (t - t_ref))
        want = (f_lcp <= force_tol) & (f0[:k] + f1[:k] @ s < -limit)
        got = kernel(t, drives, f_lcp, f0, f1, force_tol, limit) if out is None else out
        assert np.array_equal(got, want)


def closed_form_reference(normal, r_a, r_b, body_a, body_b, dynamic, inv_mass, inv_inertia,
                          friction, sigma, mu_d, omega, radius, spin_limit, alpha_limit,
                          gravity, drive_of, drive_u):
    """The numpy code ``closed_form_mode`` replaced (``EventDriven._closed_form``)."""
    k, nd = len(normal), len(drive_u)
    bodies = np.unique(body_a)
    _, J, minv, W = kern.contact_jacobian(normal, r_a, r_b, body_a, body_b, dynamic, inv_mass,
                                          inv_inertia, bodies)
    rows_of = np.where(friction == kern.STICK, kern.BOX_ROW,
                       np.where(friction == kern.SLIDE, kern.SLAVED_ROW, 0))
    A, P, rows, _, _, _ = kern.reduce_lcp(W, rows_of.astype(np.int64), np.zeros(k),
                                          np.zeros(k), -sigma * mu_d)
    ok = not np.any(np.abs(omega[bodies]) * radius[bodies] > spin_limit)
    tangent = normal[:, ::-1] * (-1.0, 1.0)
    rel = np.zeros((k, 2, 1 + nd))
    rel[:, :, 0] = gravity
    for i in np.flatnonzero(drive_of[body_b] >= 0):
        rel[i, :, 1 + drive_of[body_b[i]]] = -drive_u[drive_of[body_b[i]]]
    rhs = np.concatenate([np.einsum('kj,kjc->kc', normal, rel),
                          np.einsum('kj,kjc->kc', tangent, rel)])
    x = np.linalg.lstsq(A, -rhs[rows], rcond=1e-12)[0]
    f = P @ x
    dv = (minv[:, None] * (J.T @ f)).reshape(len(bodies), 3, 1 + nd)
    ok = ok and not np.any(np.abs(dv[:, 2, :]) > (alpha_limit / radius[bodies])[:, None])
    return ok, bodies, dv, f


@pytest.mark.parametrize('gamma', [0.8, 1.5])
def test_compiled_closed_form_matches_numpy(monkeypatch, gamma):
    calls = conveying_run(monkeypatch, 'closed_form_mode', gamma)
    assert len(calls) >= 5
    for args, (ok, bodies, dv, f) in calls:
        ok_ref, bodies_ref, dv_ref, f_ref = closed_form_reference(*args)
        assert ok == ok_ref
        assert np.array_equal(bodies, bodies_ref)
        assert np.allclose(dv, dv_ref, rtol=0.0, atol=1e-12 * np.abs(dv_ref).max())
        assert np.allclose(f, f_ref, rtol=0.0, atol=1e-12 * np.abs(f_ref).max())


def test_contact_groups_and_candidate_masks_match_numpy():
    rng = np.random.default_rng(7)
    for _ in range(50):
        k = int(rng.integers(0, 7))
        a, b = rng.integers(0, 3, k), rng.integers(0, 3, k)
        angle = rng.choice([0.0, 0.5, math.pi], k) + rng.choice([0.0, 1e-12, 1e-6], k)
        normal = np.stack([np.cos(angle), np.sin(angle)], 1)
        group = np.full(k, -1)       # the numpy transcription of _groups
        for i in range(k):
            if group[i] < 0:
                # one line: the same tangent on each body (parallel normals, same order, or
                # opposite normals, bodies swapped)
                same = (np.minimum(a, b) == min(a[i], b[i])) & \
                    (np.maximum(a, b) == max(a[i], b[i])) & \
                    (np.abs(normal @ (-normal[i, 1], normal[i, 0])) < 1e-9) & \
                    ((normal @ normal[i] > 0) == (a == a[i])) & (group < 0)
                group[same] = group.max(initial=-1) + 1
        assert np.array_equal(kern.contact_groups(a, b, normal), group)
        friction = rng.integers(0, 3, k)
        stick = friction == kern.STICK
        compact = np.full(k, -1)
        _, compact[stick] = np.unique(group[stick], return_inverse=True)
        got, n = kern.sticking_groups(group, friction)
        assert np.array_equal(got, compact) and n == compact.max(initial=-1) + 1
        vertex, piece = rng.integers(0, 5, 12), rng.integers(0, 3, 12)
        hv, hp = rng.integers(0, 5, k), rng.integers(0, 3, k)
        keep = ~np.isin(vertex * 3 + piece, hv * 3 + hp)
        assert np.array_equal(kern.held_mask(vertex, piece, hv, hp), keep)
