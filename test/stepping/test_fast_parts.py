"""Fast parts and thin bodies: nothing passes through, no contact acts from afar.

A box (40 x 20 mm) is thrown in zero gravity at a static wall, at every speed a scene accepts
and walls down to the thinnest piece a scene accepts. The reference is plain kinematics: the
box flies straight until its leading face meets the wall's near face, where it stops
(restitution 0) or turns back. ``time_stepping`` shortens a step in which a pair could close
by more than its allowance (an eighth of the thinner piece's width) in half a step, so its
box must stop within that allowance of the face on both sides; ``event_driven`` stops on it.
"""

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from feeder_sim.contact.collision import DEPTH_FRACTION
from feeder_sim.model.builders import box, build
from feeder_sim.model.scene import MAX_SPEED_MPS, MIN_PIECE_WIDTH_M
from feeder_sim.simulator import Simulator
from feeder_sim.stepping import TimeStepSettings

HALF_W, HALF_H = 0.02, 0.01          # the box's half sizes, m
FACE_X = 0.1                         # the wall's near face, m
SPEEDS = [1.0, 10.0, 100.0, MAX_SPEED_MPS]
WALLS = [0.02, 1e-3, 1e-5, MIN_PIECE_WIDTH_M]
SHARE = TimeStepSettings().substep_depth * DEPTH_FRACTION


def thrown_at_wall(method: str, speed: float, wall_m: float, dt: float | None = None,
                   heading: float = 0.0, e: float = 0.0, **kw) -> Simulator:
    wall = {'name': 'wall', 'type': 'static',
            'polygon': [[FACE_X, -0.2], [FACE_X + wall_m, -0.2], [FACE_X + wall_m, 0.2],
                        [FACE_X, 0.2]],
            'pose': [0, 0, 0], 'mu_static': 0.3, 'mu_dynamic': 0.3, 'restitution': e}
    part = {'name': 'box', 'type': 'dynamic', 'polygon': box(HALF_W, HALF_H), 'mass': 0.01,
            'pose': [0.0, 0.0, 0.0],
            'velocity': [speed * math.cos(heading), speed * math.sin(heading), 0.0],
            'mu_static': 0.3, 'mu_dynamic': 0.3, 'restitution': e}
    solver = {'method': method}
    if dt:
        solver['time_step'] = dt
    return Simulator(build({'name': 'thrown', 'gravity': [0, 0], 'solver': solver,
                            'bodies': [wall, part]}), **kw)


def leading_x(sim: Simulator) -> float:
    """The x of the box's vertex furthest along +x, m."""
    x, a = sim.state.position[1, 0], sim.state.angle[1]
    corners = np.array(box(HALF_W, HALF_H))
    return float(x + np.max(corners[:, 0] * math.cos(a) - corners[:, 1] * math.sin(a)))


def fly(sim: Simulator, speed: float, frames: int = 60) -> list[float]:
    """Leading x at each of ``frames`` frames over three times the flight to the wall."""
    t_end = 3 * (FACE_X - HALF_W) / speed
    out = []
    for k in range(1, frames + 1):
        sim.advance_to(k * t_end / frames)
        out.append(leading_x(sim))
    return out


@pytest.mark.parametrize('dt', [1e-3, 1e-4])
@pytest.mark.parametrize('wall_m', WALLS)
@pytest.mark.parametrize('speed', SPEEDS)
def test_time_stepping_stops_on_the_face_at_every_speed(speed, wall_m, dt):
    sim = thrown_at_wall('time_stepping', speed, wall_m, dt)
    allow = SHARE * min(wall_m, 2 * HALF_H)
    track = fly(sim, speed)
    assert max(track) <= FACE_X + allow + 1e-12          # never deeper than the allowance
    assert track[-1] >= FACE_X - allow - 1e-12          # nor stopped further off the face
    assert abs(sim.state.velocity[1, 0]) <= 1e-9 * speed
    step = min(dt, 3 * (FACE_X - HALF_W) / speed / 60)     # frames may be shorter than dt
    fast = speed * step / 2 > allow
    assert (sim.stats.substeps > 0) == fast             # shortened only where it must be


@pytest.mark.parametrize('heading', [0.6, -1.0])
@pytest.mark.parametrize('speed', [50.0, MAX_SPEED_MPS])
def test_oblique_throws_slide_along_the_face_without_entering(speed, heading):
    # friction 0.3 cannot stop the slip along the face (tan(heading) > 0.3): the impact takes
    # at most 0.3 of the normal speed from it and the box slides on along the face
    sim = thrown_at_wall('time_stepping', speed, 1e-5, 1e-3, heading=heading)
    allow = SHARE * 1e-5
    track = fly(sim, speed * math.cos(heading))
    assert max(track) <= FACE_X + allow + 1e-12
    assert track[-1] >= FACE_X - allow - 1e-12
    assert sim.state.velocity[1, 0] == pytest.approx(0.0, abs=1e-9 * speed)
    left = speed * (abs(math.sin(heading)) - 0.3 * math.cos(heading))
    assert 0.5 * left <= sim.state.velocity[1, 1] * math.copysign(1, heading) <= 1.01 * left


@pytest.mark.parametrize('speed', [10.0, MAX_SPEED_MPS])
def test_a_bounce_turns_back_at_the_face(speed):
    sim = thrown_at_wall('time_stepping', speed, MIN_PIECE_WIDTH_M, 1e-3, e=0.5)
    track = fly(sim, speed)
    assert max(track) <= FACE_X + SHARE * MIN_PIECE_WIDTH_M + 1e-12
    assert sim.state.velocity[1, 0] == pytest.approx(-0.5 * speed, rel=1e-9)


def test_compiled_and_reference_steps_agree_when_steps_are_shortened():
    runs = []
    for compiled in (True, False):
        sim = thrown_at_wall('time_stepping', 300.0, 1e-4, 1e-3,
                             settings=TimeStepSettings(compiled=compiled))
        fly(sim, 300.0, frames=6)
        runs.append((sim.state.position.copy(), sim.state.velocity.copy(), sim.stats.substeps,
                     sim.stats.steps))
    (p0, v0, s0, n0), (p1, v1, s1, n1) = runs
    assert s0 == s1 > 0 and n0 == n1
    np.testing.assert_allclose(p0, p1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(v0, v1, rtol=0, atol=1e-12)


def test_two_parts_thrown_at_each_other_meet():
    # a 10 um plate and a box closing at 1 000 m/s, both free
    plate = {'name': 'plate', 'type': 'dynamic', 'mass': 0.001, 'pose': [0.05, 0.0, 0.0],
             'polygon': [[0.0, -0.03], [1e-5, -0.03], [1e-5, 0.03], [0.0, 0.03]],
             'velocity': [-500.0, 0.0, 0.0], 'mu_static': 0.3, 'mu_dynamic': 0.3,
             'restitution': 0.0}
    part = {'name': 'box', 'type': 'dynamic', 'polygon': box(HALF_W, HALF_H), 'mass': 0.01,
            'pose': [0.0, 0.0, 0.0], 'velocity': [500.0, 0.0, 0.0], 'mu_static': 0.3,
            'mu_dynamic': 0.3, 'restitution': 0.0}
    sim = Simulator(build({'name': 'meet', 'gravity': [0, 0],
                           'solver': {'method': 'time_stepping', 'time_step': 1e-3},
                           'bodies': [plate, part]}))
    sim.advance_to(1e-3)
    # inelastic: one common velocity, momentum kept, the plate in front of the box
    momentum = 0.001 * -500.0 + 0.01 * 500.0
    np.testing.assert_allclose(sim.state.velocity[:, 0], momentum / 0.011, rtol=1e-9)
    gap = (sim.state.position[0, 0] - 5e-6) - (sim.state.position[1, 0] + HALF_W)  # centres
    assert -SHARE * 1e-5 - 1e-12 <= gap <= SHARE * 1e-5 + 1e-12


@pytest.mark.parametrize('wall_m', [0.02, MIN_PIECE_WIDTH_M])
@pytest.mark.parametrize('speed', [1.0, MAX_SPEED_MPS])
def test_event_driven_stops_on_the_face(speed, wall_m):
    sim = thrown_at_wall('event_driven', speed, wall_m)
    track = fly(sim, speed, frames=6)
    assert max(track) <= FACE_X + 1e-9
    assert track[-1] == pytest.approx(FACE_X, abs=1e-9)


@pytest.mark.parametrize('speed', [10.0, MAX_SPEED_MPS])
def test_impulse_based_never_passes(speed):
    sim = thrown_at_wall('impulse_based', speed, 1e-5)
    track = fly(sim, speed, frames=6)
    assert max(track) <= FACE_X + 1e-5
    assert sim.state.velocity[1, 0] <= 0.0


# the guarantee itself: in free flight over half the step safe_step allows, no pair of pieces
# goes deeper into each other (along its separating axis) than the allowance


def separation(a: np.ndarray, b: np.ndarray) -> float:
    """The largest separation of two convex polygons along their edge normals (m)."""
    best = -np.inf
    for p, q in ((a, b), (b, a)):
        edges = np.roll(p, -1, axis=0) - p
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        d = np.einsum('kd,kjd->kj', normals, q[None, :, :] - p[:, None, :])
        best = max(best, float(d.min(axis=1).max()))
    return best


def outline(sim: Simulator, i: int, position, angle) -> np.ndarray:
    local = sim.world.shapes.vertices[sim.world.shapes.piece_start[i]:
                                      sim.world.shapes.piece_start[i + 1]]
    c, s = math.cos(angle), math.sin(angle)
    return position + local @ np.array([[c, s], [-s, c]])


@settings(max_examples=60, deadline=None)
@given(speed=st.floats(0.1, MAX_SPEED_MPS), heading=st.floats(-math.pi, math.pi),
       spin=st.floats(-200.0, 200.0), gap=st.floats(0.0, 0.5), foil=st.sampled_from(WALLS),
       dt=st.sampled_from([1e-2, 1e-3, 1e-4]))
def test_safe_step_keeps_every_pair_within_its_allowance(speed, heading, spin, gap, foil, dt):
    sim = thrown_at_wall('time_stepping', 0.0, foil, dt)
    # the box starts `gap` before the face (its leading corner), thrown at any heading
    sim.state.position[1] = [FACE_X - HALF_W - gap - 1e-9, 0.0]
    sim.state.velocity[1] = [speed * math.cos(heading), speed * math.sin(heading)]
    sim.state.omega[1] = spin
    stepper = sim._stepper
    h = stepper.safe_step(sim.state, dt)
    assert 0.0 < h <= dt
    allow = SHARE * min(foil, 2 * HALF_H)
    wall = outline(sim, 0, sim.state.position[0], 0.0)
    p0, v, a0 = sim.state.position[1].copy(), sim.state.velocity[1].copy(), sim.state.angle[1]
    start = separation(wall, outline(sim, 1, p0, a0))
    for t in np.linspace(0.0, 0.5 * h, 41):
        now = separation(wall, outline(sim, 1, p0 + v * t, a0 + spin * t))
        assert now >= min(start, 0.0) - allow - 1e-12
