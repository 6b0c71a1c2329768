"""The energy invariant, asserted after every step or event (``check_energy``).

Between impacts with e <= 1 and without drive work the parts' mechanical energy never rises.
The check must catch a rise where it happens (a restitution above 1 slipped past the
validator: the impact gains (e^2 - 1) of the landing energy), must not fire on a passive
scene that keeps its energy, and must not count what a moving drive gives a part.
"""

from dataclasses import replace
import math
import subprocess
import sys

import pytest
import yaml

from feeder_sim.model.builders import box_part, build, G, ground, scene_dict
from feeder_sim.simulator import EnergyInvariantError, Simulator

METHODS = ('time_stepping', 'event_driven', 'impulse_based')
DROP_M = 5e-3                          # the box's lowest face starts this far above the floor
HALF = 5e-3


def dropped_box(method: str, e: float, *, time_step: float = 1e-3, mu: float = 0.0) -> dict:
    bodies = [ground(mu=mu, e=min(e, 1.0)),
              box_part('box', HALF, HALF, (0.0, HALF + DROP_M, 0.0), mu=mu, e=min(e, 1.0))]
    return scene_dict('dropped', bodies, method, time_step)


def with_restitution(scene_dict_: dict, e: float):
    """The scene with restitution ``e`` on every body, past the validator's [0, 1] bound."""
    scene = build(scene_dict_)
    return replace(scene, bodies=tuple(replace(b, restitution=e) for b in scene.bodies))


@pytest.mark.parametrize('method', METHODS)
def test_an_impact_that_gains_energy_is_caught_at_the_impact(method):
    sim = Simulator(with_restitution(dropped_box(method, 1.0), 1.5), check_energy=1e-3)
    t_impact = math.sqrt(2 * DROP_M / G)
    with pytest.raises(EnergyInvariantError, match=r'mechanical energy rose by .* at t = '):
        sim.advance(0.1)
    # caught at the impact (event_driven: at its instant; a time-stepped method: within the
    # step that contains it, or the next where a collision is spread over two)
    h = sim.scene.solver.time_step
    slack = 1e-9 if method == 'event_driven' else 2 * h
    assert t_impact - 1e-9 <= sim.t <= t_impact + slack
    assert sim.energy_check.largest_rise > 1e-3


@pytest.mark.parametrize('method', METHODS)
def test_an_elastic_bounce_passes_a_tight_check(method):
    # e = 1, mu = 0, landing flat: the energy is kept (to round-off for event_driven, to the
    # scheme's exactness in free flight for the midpoint time step)
    sim = Simulator(build(dropped_box(method, 1.0)), check_energy=1e-9)
    sim.advance(0.2)
    assert sim.stats.impacts >= 3                  # bounces (per corner or per event)
    assert sim.energy_check.checks >= 8
    assert sim.energy_check.largest_rise <= 1e-9


@pytest.mark.parametrize('method', METHODS)
def test_drive_work_is_not_counted_but_flight_above_the_drive_is(method):
    # a box on a platform shaken vertically at 3 g: the drive throws it up every period
    f, gamma = 20.0, 3.0
    amplitude = gamma * G / (2 * math.pi * f) ** 2
    bodies = [{**ground(mu=0.5), 'type': 'kinematic',
               'vibration': {'amplitude': amplitude, 'frequency': f, 'angle': math.pi / 2}},
              box_part('box', HALF, HALF, (0.0, HALF, 0.0), mu=0.5)]
    h = 1e-4 if method == 'time_stepping' else 1e-3
    sim = Simulator(build(scene_dict('shaken', bodies, method, h)), check_energy=1e-6)
    e0 = sim.mechanical_energy()
    highest = e0
    for k in range(1, 31):
        sim.advance(0.01 * k)
        highest = max(highest, sim.mechanical_energy())
    check = sim.energy_check
    # the drive did work: at 3 g the box leaves the platform every period
    assert highest - e0 > 1e-2 * check.scale_j
    assert check.rebased > 0                       # contact with the moving platform
    assert check.checks > 2 * check.rebased        # and flight, checked
    assert check.largest_rise <= 1e-6


def test_the_environment_variable_sets_the_check(monkeypatch):
    monkeypatch.setenv('FEEDER_SIM_CHECK_ENERGY', '2e-7')
    sim = Simulator(build(dropped_box('event_driven', 0.5)))
    assert sim.energy_check is not None and sim.energy_check.tolerance == 2e-7
    monkeypatch.setenv('FEEDER_SIM_CHECK_ENERGY', 'tight')
    with pytest.raises(ValueError, match='FEEDER_SIM_CHECK_ENERGY must be a tolerance'):
        Simulator(build(dropped_box('event_driven', 0.5)))


def test_reset_takes_the_reference_again():
    sim = Simulator(build(dropped_box('event_driven', 0.0)), check_energy=1e-9)
    sim.advance(0.1)                               # landed: energy lost
    sim.reset()                                    # back up: the energy is the start's again
    sim.advance(0.1)
    assert sim.energy_check.largest_rise <= 1e-9


def test_cli_runs_with_the_check_and_refuses_a_bad_tolerance(tmp_path):
    scene = tmp_path / 'dropped.yaml'
    scene.write_text(yaml.safe_dump(dropped_box('event_driven', 0.5)))
    ok = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'run', str(scene),
                         '--duration', '0.1', '--check-energy', '1e-9'],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    bad = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'run', str(scene),
                          '--duration', '0.1', '--check-energy', '-1'],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0
    lines = [x for x in bad.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and 'check_energy must be a tolerance >= 0' in lines[0], bad.stderr


def test_time_steppings_rise_while_tumbling_is_first_order_in_the_step():
    # a 20 x 10 mm box thrown at 1 m/s with mu = 3 tips over its leading edge and tumbles:
    # the midpoint rule's linear velocity constraint on the pivoting corner lifts it by about
    # (omega h)^2 R per step, so the largest rise over the tumble falls like h
    rise = {}
    for h in (1e-3, 1e-4):
        bodies = [ground(mu=3.0), box_part('box', 0.01, 0.005, (0.0, 0.005, 0.0),
                                           (1.0, 0.0, 0.0), mu=3.0)]
        sim = Simulator(build(scene_dict('thrown', bodies, 'time_stepping', h)),
                        check_energy=math.inf)
        sim.advance(0.3)
        rise[h] = sim.energy_check.largest_rise
    assert 0.0 < rise[1e-4] <= rise[1e-3] / 5
    assert rise[1e-3] <= 3e-4                    # the stability report's bound at 1 ms
