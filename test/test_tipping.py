"""A tall block sticking on an accelerating platform tips at the instant the platform's
acceleration passes g b / h (every method).

The platform vibrates horizontally, x = A sin(omega t), and the block starts with the platform's
velocity, so it sticks while the acceleration a(t) = -A omega^2 sin(omega t) rises from zero.
With friction to spare (mu = 1 > b / h), the normal force at its trailing corner reaches zero
when |a| = g b / h, at t* = asin(g b / (h A omega^2)) / omega. Right after, the block pivots on
its leading corner: I_pivot theta'' = m (h |a(t)| - g b), so the angle grows as
h a'(t*) (t - t*)^3 / (6 (4/3)(b^2 + h^2)), with a' = A omega^3 cos(omega t*).
"""

import math

import pytest

from feeder_sim.model.builders import box, build, G, scene_dict
from feeder_sim.simulator import Simulator

B, H, FREQ, MU = 0.005, 0.02, 5.0, 1.0          # half width, half height (m), Hz
OMEGA = 2 * math.pi * FREQ
AMPLITUDE = 0.5 * G / OMEGA ** 2                # peak acceleration g / 2 > g b / h = g / 4
T_TIP = math.asin(G * B / (H * AMPLITUDE * OMEGA ** 2)) / OMEGA
JERK = AMPLITUDE * OMEGA ** 3 * math.cos(OMEGA * T_TIP)


def platform_scene(method: str, dt: float) -> Simulator:
    platform = {'name': 'platform', 'type': 'kinematic', 'polygon': box(0.2, 0.01),
                'pose': [0.0, -0.01, 0.0], 'mu_static': MU, 'mu_dynamic': MU,
                'restitution': 0.0,
                'vibration': {'amplitude': AMPLITUDE, 'frequency': FREQ, 'angle': 0.0,
                              'phase': 0.0}}
    block = {'name': 'block', 'type': 'dynamic', 'polygon': box(B, H), 'mass': 0.01,
             'pose': [0.0, H, 0.0], 'velocity': [AMPLITUDE * OMEGA, 0.0, 0.0],
             'mu_static': MU, 'mu_dynamic': MU, 'restitution': 0.0}
    scene = scene_dict('tip', [platform, block], method, dt)
    scene['track'] = 'platform'
    return Simulator(build(scene))


def onset_angle(delay_s: float) -> float:
    """|angle| delay_s after t*, leading order in the delay."""
    return H * JERK * delay_s ** 3 / (6 * (4 / 3) * (B ** 2 + H ** 2))


@pytest.mark.parametrize('method, dt, rel', [
    ('event_driven', 1e-3, 0.02), ('event_driven', 1e-2, 0.02),
    ('time_stepping', 1e-4, 0.03), ('time_stepping', 1e-3, 0.15)])
def test_a_sticking_block_tips_when_the_platform_acceleration_passes_g_b_over_h(method, dt,
                                                                               rel):
    sim = platform_scene(method, dt)
    sim.advance(T_TIP - 2e-3)
    assert abs(sim.state.angle[1]) < 1e-12         # flat while the trailing corner presses
    delay = 2e-3
    sim.advance(T_TIP + delay)
    # 2 % covers the next order of the onset series (its relative size is ~ omega delay)
    assert abs(sim.state.angle[1]) == pytest.approx(onset_angle(delay), rel=rel)


def test_impulse_based_tips_with_the_others():
    # micro-collisions rock the block by ~1e-6 rad before t*; 30 ms later it has tipped
    # as far as the event-driven answer
    ib, ed = platform_scene('impulse_based', 1e-3), platform_scene('event_driven', 1e-3)
    t = T_TIP + 0.03
    ib.advance(t)
    ed.advance(t)
    assert abs(ed.state.angle[1]) > 1e-2
    assert ib.state.angle[1] == pytest.approx(ed.state.angle[1], rel=0.02)


def rocking_on_a_track(method: str, dt: float, drive_angle: float, track_angle: float,
                       freq: float, peak_g: float) -> Simulator:
    """The tall block standing on a track vibrating along ``drive_angle`` (from the track),
    starting at rest while the track moves: it slips, sticks, and rocks on its corners."""
    amplitude = peak_g * G / (2 * math.pi * freq) ** 2
    c, s = math.cos(track_angle), math.sin(track_angle)
    track = {'name': 'track', 'type': 'kinematic', 'polygon': box(0.2, 0.01),
             'pose': [0.01 * s, -0.01 * c, track_angle], 'mu_static': MU, 'mu_dynamic': MU,
             'restitution': 0.0,
             'vibration': {'amplitude': amplitude, 'frequency': freq, 'angle': drive_angle,
                           'phase': 0.0}}
    block = {'name': 'block', 'type': 'dynamic', 'polygon': box(B, H), 'mass': 0.01,
             'pose': [-H * s, H * c, track_angle], 'mu_static': MU, 'mu_dynamic': MU,
             'restitution': 0.0}
    return Simulator(build(scene_dict('rock', [track, block], method, dt)))


@pytest.mark.timeout(120)
@pytest.mark.parametrize('drive_deg, track_deg, freq, peak_g', [
    (20.0, 0.0, 50.0, 1.5),        # a feeder track's drive line, hopping and rocking
    (20.0, 3.0, 50.0, 1.2),        # a bowl's 3 deg track
    (30.0, 0.0, 20.0, 0.8),        # slower and steeper
])
def test_rocking_on_vibrating_tracks_matches_a_fine_time_step(drive_deg, track_deg, freq,
                                                             peak_g):
    # the peak tilt over 0.4 s, event_driven at its scene step against time stepping at
    # 20 us (converged: within 0.1 % of its peak tilt at 10 us)
    tilts = {}
    for method, dt in (('event_driven', 1e-3), ('time_stepping', 2e-5)):
        sim = rocking_on_a_track(method, dt, math.radians(drive_deg), math.radians(track_deg),
                                 freq, peak_g)
        tilt = 0.0
        for k in range(1, 81):
            sim.advance_to(0.005 * k)
            tilt = max(tilt, abs(sim.state.angle[1] - math.radians(track_deg)))
        tilts[method] = tilt
    assert tilts['time_stepping'] > 1e-3                    # it does rock
    assert tilts['event_driven'] == pytest.approx(tilts['time_stepping'], rel=0.02)
