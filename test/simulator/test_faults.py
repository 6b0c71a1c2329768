"""Fault campaign: malformed and extreme input, floods and signals.

Scene files are made by mutating the shipped scenes (a value replaced by an extreme or
malformed one, a key removed or misspelt, a structure wrapped); every one must be answered
within seconds by a run whose outputs are finite, or by one line naming the key. Command
floods of random content must leave the node running with a valid drive; signals at random
moments must end it within a second with a readable log.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import random
import subprocess
import sys
import time

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
from paths import CONFIG
import pytest
import yaml

from feeder_sim.model.scene import (
    MAX_ANGLE_RAD,
    MAX_LENGTH_M,
    MAX_SPEED_MPS,
    MAX_SPIN_RAD_S,
    parse_scene,
    read_scene_data,
    SceneError,
    shipped_scenes,
)
from feeder_sim.simulator import Simulator
from feeder_sim.stepping import EventSettings, ImpulseSettings, TimeStepSettings

SCENES = {name: yaml.safe_load((CONFIG / f'{name}.yaml').read_text())
          for name in shipped_scenes()}

NASTY = [None, True, 'text', '', [], {}, [1.0], [[1.0, 2.0]], 0, -1, 0.0, -0.0, 1e-320,
         5e-324, -1e-320, 1e-12, 1e12, 1e300, -1e300, math.nan, math.inf, -math.inf,
         2 ** 63, 10 ** 400, '1e3', [math.nan, 0.0], [0.0, 0.0, 1e16]]


def _leaves(data, path=()):
    """Key paths of every value in ``data`` (mappings and lists, depth first)."""
    yield path
    if isinstance(data, dict):
        for key, value in data.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(data, list):
        for k, value in enumerate(data):
            yield from _leaves(value, (*path, k))


def _mutate(data: dict, path: tuple, kind: str, value) -> dict:
    out = copy.deepcopy(data)
    if not path:
        return value if kind == 'replace' else {'scene': out}
    parent = out
    for key in path[:-1]:
        parent = parent[key]
    last = path[-1]
    if kind == 'replace':
        parent[last] = value
    elif kind == 'delete':
        if isinstance(parent, dict):
            del parent[last]
        else:
            parent.pop(last)
    elif kind == 'misspell' and isinstance(parent, dict):
        parent[f'{last}x'] = parent.pop(last)
    elif kind == 'scale':
        parent[last] = _scaled(parent[last], value)
    elif kind == 'wrap':
        parent[last] = [parent[last]]
    elif kind == 'duplicate' and isinstance(parent, list):
        parent.append(copy.deepcopy(parent[last]))
    return out


SCALES = [1e-9, 1e-3, -1.0, 1e3, 1e9]


def _scaled(value, factor: float):
    """Every number in ``value`` times ``factor`` (extreme but well-formed)."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, float)):
        return value * factor
    if isinstance(value, list):
        return [_scaled(v, factor) for v in value]
    if isinstance(value, dict):
        return {k: _scaled(v, factor) for k, v in value.items()}
    return value


@st.composite
def mutated_scenes(draw):
    name = draw(st.sampled_from(sorted(SCENES)))
    data = SCENES[name]
    paths = list(_leaves(data))
    path = draw(st.sampled_from(paths))
    kind = draw(st.sampled_from(['replace', 'replace', 'replace', 'scale', 'scale', 'delete',
                                 'misspell', 'wrap', 'duplicate']))
    value = draw(st.sampled_from(SCALES if kind == 'scale' else NASTY))
    return name, path, kind, _mutate(data, path, kind, value)


def answer(data, duration_s: float = 0.01) -> tuple[str, str]:
    """('refused', line) or ('ran', summary); asserts the answer is clean."""
    try:
        scene = parse_scene(data, source='mutated.yaml')
    except SceneError as err:
        line = str(err)
        assert '\n' not in line and line.startswith('mutated.yaml'), line
        return 'refused', line
    try:
        sim = Simulator(scene)
        sim.advance_by(duration_s)
    except ValueError as err:         # a refusal that needs the world (e.g. an override)
        assert '\n' not in str(err), err
        return 'refused', str(err)
    s = sim.state
    for a in (s.position, s.angle, s.velocity, s.omega):
        assert np.all(np.isfinite(a)), f'non-finite state after {duration_s} s'
    report = sim.take_contacts()
    for a in (report.point, report.normal, report.normal_impulse, report.tangent_impulse):
        assert np.all(np.isfinite(a)), 'non-finite contact report'
    assert math.isfinite(sim.mechanical_energy())
    return 'ran', f'{scene.name} t = {sim.t}'


@pytest.mark.timeout(900)
@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(mutated_scenes())
def test_a_mutated_shipped_scene_is_run_or_refused_in_one_line(case):
    name, path, kind, data = case
    start = time.perf_counter()
    answer(data)
    assert time.perf_counter() - start < 30.0, (name, path, kind)


# Whole files through the command line, as a user would give them: exit 0 with a run, or
# exit 2 with one line; never a traceback.
CLI_CASES = [
    ('track_one_box', ('bodies', 1, 'mass'), 'replace', 1e-300),
    ('track_one_box', ('bodies', 1, 'mass'), 'replace', 1e300),
    ('track_one_box', ('bodies', 0, 'vibration', 'frequency'), 'replace', 5e-324),
    ('track_one_box', ('gravity',), 'replace', [0.0, -1e300]),
    ('track_ten_boxes', ('bodies', 3, 'pose'), 'replace', [0.0, 0.0, 1e16]),
    ('orienter_hook', ('solver', 'time_step'), 'replace', 0.0),
    ('incline_stick', ('bodies',), 'replace', {}),
    ('incline_slide', ('bodies', 1, 'polygon'), 'replace', [[0, 0], [1, 1], [0, 0]]),
]


@pytest.mark.timeout(600)
def test_malformed_files_through_the_cli_are_one_line_or_a_run(tmp_path):
    for k, (name, path, kind, value) in enumerate(CLI_CASES):
        scene = tmp_path / f'case_{k}.yaml'
        scene.write_text(yaml.safe_dump(_mutate(SCENES[name], path, kind, value)))
        proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', '-q', 'run', str(scene),
                               '--duration', '0.02'], capture_output=True, text=True,
                              timeout=120)
        assert 'Traceback' not in proc.stderr, (path, proc.stderr)
        if proc.returncode == 2:
            lines = [x for x in proc.stderr.splitlines() if x.strip()]
            assert len(lines) == 1 and lines[0].startswith('feeder-sim: error:'), proc.stderr
        else:
            assert proc.returncode == 0, (path, proc.stderr)
            assert 'nan' not in proc.stdout.lower(), proc.stdout


def test_the_campaign_reaches_both_answers():
    # the mutations are not all refused (nor all accepted): both paths are exercised
    rng = random.Random(7)
    answers = set()
    for _ in range(40):
        name = rng.choice(sorted(SCENES))
        path = rng.choice(list(_leaves(SCENES[name])))
        answers.add(answer(_mutate(SCENES[name], path, 'replace', rng.choice(NASTY)))[0])
    assert answers == {'ran', 'refused'}


# --- the node under a flood of random commands (real DDS) ---------------------------------

def test_a_flood_of_random_commands_leaves_a_valid_drive(tmp_path):
    from std_msgs.msg import Float64MultiArray
    from test_sim_node import Graph

    from feeder_sim.model.vibration import parse_command

    rng = random.Random(11)
    numbers = [v for v in NASTY if isinstance(v, float)] + [0.0, 3e-4, 50.0, 1e-3, 120.0]
    graph = Graph()
    try:
        node = graph.start(real_time_factor=0.0, record_path=str(tmp_path / 'flood.mcap'))
        drive = node.sim.world.drives[node.sim.world.driven[0]]
        valid = {(drive.amplitude_m, drive.frequency_hz)}
        pub = graph.publisher(Float64MultiArray, 'vibration_cmd')
        for _ in range(400):
            data = [rng.choice(numbers) for _ in range(rng.choice([0, 1, 2, 2, 2, 3]))]
            try:
                valid.add(parse_command(data))
            except ValueError:
                pass
            pub.publish(Float64MultiArray(data=data))
            graph.executor.spin_once(timeout_sec=0.0)
        frames = node.frames
        graph.spin_for(1.0)
        assert not node.done and node.frames > frames            # still simulating
        assert (drive.amplitude_m, drive.frequency_hz) in valid
        s = node.sim.state
        assert all(np.all(np.isfinite(a)) for a in (s.position, s.velocity, s.angle, s.omega))
        assert node.commands_accepted + node.commands_rejected > 0
    finally:
        graph.close()


@pytest.mark.parametrize('settings_type', [TimeStepSettings, EventSettings, ImpulseSettings])
def test_settings_refuse_what_they_cannot_run_in_one_line(settings_type):
    """Every field of every method's settings, set to each nasty value: either it is taken as
    the field's type (finite, within its range) or refused by one line naming the field."""
    taken = 0
    for f in dataclasses.fields(settings_type):
        kinds = [k.strip() for k in str(f.type).split('|')]
        refused = 0
        for value in NASTY:
            s = settings_type()
            try:
                setattr(s, f.name, value)
            except ValueError as e:
                message = str(e)
                assert '\n' not in message
                assert message.startswith(f'{settings_type.__name__}.{f.name} must be ')
                refused += 1
                continue
            got = getattr(s, f.name)
            taken += 1
            if got is None:
                assert 'None' in kinds
            elif kinds[0] == 'bool':
                assert isinstance(got, bool) and isinstance(value, bool)
            else:
                assert type(got).__name__ == kinds[0] and not isinstance(value, bool)
                assert math.isfinite(got)
                rule = settings_type.LIMITS.get(f.name, '')
                assert not rule.startswith('>') or got >= float(rule.split()[1])
        assert refused >= 15                        # text, NaN, inf, lists, mappings ...
    assert taken


def test_a_settings_value_that_would_never_end_a_solve_is_refused_before_the_run():
    sim = Simulator(parse_scene(SCENES['track_ten_boxes']), method='time_stepping')
    with pytest.raises(ValueError, match=r'^TimeStepSettings\.pgs_check must be an integer '
                                         r'\(64 bits\) >= 1, got 0$'):
        sim._stepper.settings.pgs_check = 0         # it would have swept forever
    with pytest.raises(TypeError, match='^time_stepping takes TimeStepSettings settings, got '
                                        'EventSettings$'):
        Simulator(parse_scene(SCENES['track_ten_boxes']), method='time_stepping',
                  settings=EventSettings())


BAD_ARRAYS = {
    'float32': lambda x: x.astype(np.float32),
    'a strided view': lambda x: np.repeat(x[..., None], 2, -1)[..., 0],
    'one body short': lambda x: x[:-1].copy(),
    'read-only': lambda x: np.frombuffer(x.tobytes()).reshape(x.shape),
    'a list': lambda x: x.tolist(),
}


@pytest.mark.parametrize('method', ['time_stepping', 'event_driven', 'impulse_based'])
@pytest.mark.parametrize('bad', sorted(BAD_ARRAYS))
@pytest.mark.parametrize('field', ['position', 'angle', 'velocity', 'omega'])
def test_a_state_array_replaced_by_one_no_stepper_can_take_is_refused(field, bad, method):
    # A caller that replaces a state array by one of another dtype, shape or memory layout
    # gets one line naming the field, at once (the compiled steppers would compile anew for
    # a minute, or read it as float64 of the world's size); a good array put back runs on,
    # and the run agrees with one whose state was never touched.
    sims = [Simulator(parse_scene(SCENES['track_one_box']), method=method) for _ in range(2)]
    for sim in sims:
        sim.advance(0.01)
    sim, ref = sims
    good = getattr(sim.state, field)
    setattr(sim.state, field, BAD_ARRAYS[bad](good))
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=rf'^state\.{field} must be a writable, C-contiguous '
                                         rf'float64 array of shape \((2, 2|2,)\), got '):
        sim.advance(0.02)
    assert time.perf_counter() - t0 < 0.5
    assert sim.t == ref.t < 0.02
    setattr(sim.state, field, good.copy())
    for s in sims:
        s.advance(0.02)
    assert np.array_equal(sim.state.position, ref.state.position)
    assert np.array_equal(sim.state.velocity, ref.state.velocity)


def test_a_state_time_that_is_not_a_finite_number_is_refused():
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    for bad in (math.nan, math.inf, '0.1', None):
        sim.state.t = bad
        with pytest.raises(ValueError, match=r'^state\.t must be a finite number of seconds'):
            sim.advance(0.02)
        with pytest.raises(ValueError, match=r'^state\.t must be a finite number of seconds'):
            sim.advance_by(0.02)


API_MISUSE = [
    (lambda s: s.advance_to('1'), r"^t_end must be a finite number of seconds, got '1'$"),
    (lambda s: s.advance_to(None), r'^t_end must be a finite number of seconds, got None$'),
    (lambda s: s.advance_by('x'), r"^duration must be a positive number of seconds, got 'x'$"),
    (lambda s: s.set_part_pose('box', [0.0]), r'^pose must be \[x, y, angle\] in m and rad'),
    (lambda s: s.set_part_pose('box', 'abc'), r'^pose must be \[x, y, angle\] in m and rad'),
    (lambda s: s.add_part('box', 'b', [0.0, 0.1, 0.0], velocity=[[1.0], 2.0, 3.0]),
     r'^velocity must be \[vx, vy, omega\] in m/s and rad/s'),
    (lambda s: s.command_vibration('a', 50.0),
     r'^amplitude_m and frequency_hz must be finite numbers >= 0'),
    (lambda s: s.command_vibration(np.array([1e-3, 2e-3]), 50.0),
     r'^amplitude_m and frequency_hz must be finite numbers >= 0, got array'),
    # a time so far ahead that the run would never end, as advance_by refuses its duration
    (lambda s: s.advance_to(1e300), r'^t_end 1e\+300 s is more than 1e\+12 steps of 0.001 s '
                                    r'ahead of t = 0.01 s; go on by at most 1e\+09 s per call$'),
]


@pytest.mark.parametrize('args, kw, error, message', [
    (('',), {}, SceneError, r'^<scene>: no scene given: name a scene file or a shipped scene '),
    ((3,), {}, TypeError, r'^scene must be a Scene, the data of a scene file \(a mapping\), '
                          r'a scene file path or a shipped scene name, got int$'),
    (('track_one_box',), {'check_energy': 'x'}, ValueError,
     r"^check_energy must be a tolerance >= 0 \(relative to the energy scale, e.g. 1e-6\), "
     r"got 'x'$"),
], ids=['empty name', 'not a scene', 'energy tolerance'])
def test_a_simulator_that_cannot_be_made_is_one_line(args, kw, error, message):
    with pytest.raises(error, match=message):
        Simulator(*args, **kw)


def test_a_simulator_takes_the_data_of_a_scene_file():
    sims = Simulator(read_scene_data('track_one_box')[0]), Simulator('track_one_box')
    for sim in sims:
        sim.advance_to(0.05)
    assert np.array_equal(sims[0].state.position, sims[1].state.position)


@pytest.mark.parametrize('case', range(len(API_MISUSE)))
def test_python_api_misuse_is_one_line_naming_the_argument(case):
    call, message = API_MISUSE[case]
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    sim.advance(0.01)
    before = sim.state.copy()
    with pytest.raises(ValueError, match=message):
        call(sim)
    assert sim.t == before.t and np.array_equal(sim.state.position, before.position)
    sim.advance(0.02)
    assert sim.t > before.t


# -- state and settings changed from Python ------------------------------------------------

STATE_BOUNDS = {'position': MAX_LENGTH_M, 'angle': MAX_ANGLE_RAD, 'velocity': MAX_SPEED_MPS,
                'omega': MAX_SPIN_RAD_S}


def _out_of(limit: float):
    past = st.floats(min_value=math.nextafter(limit, math.inf), max_value=1.7e308)
    return st.one_of(st.sampled_from([math.nan, math.inf, -math.inf]), past,
                     past.map(lambda x: -x))


@st.composite
def state_changes(draw):
    """(field, component, value, bad): a part's value set in place beyond a scene's bounds, or
    within them (``value`` is then a function of the value before: a place and a turn the run
    can go on from)."""
    field = draw(st.sampled_from(sorted(STATE_BOUNDS)))
    component = draw(st.integers(0, 1)) if field in ('position', 'velocity') else None
    if draw(st.booleans()):
        return field, component, draw(_out_of(STATE_BOUNDS[field])), True
    if field == 'position':
        d = draw(st.floats(0.0, 1e-2) if component == 1 else st.floats(-1e-2, 1e-2))
        return field, component, lambda x: x + d, False           # lifted or moved along
    if field == 'angle':
        k = draw(st.integers(-150, 150))                            # whole turns, < 1000 rad
        return field, component, lambda x: x + 2 * math.pi * k, False
    v = draw(st.floats(-1.0, 1.0) if field == 'velocity' else st.floats(-10.0, 10.0))
    return field, component, lambda x: v, False


@settings(max_examples=30, deadline=None, database=None)
@given(state_changes())
def test_a_state_value_changed_in_place_is_checked_at_the_next_advance(change):
    # `state.velocity[...] = 1e300` ran on to positions of 5e298 and `omega = inf` to NaN
    # poses: now one line naming the element, the state as it was given, and a value put back
    # within the bounds runs on
    field, component, value, bad = change
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    sim.advance(0.01)
    part = int(sim.part_indices[0])
    at = part if component is None else (part, component)
    array = getattr(sim.state, field)
    before = float(array[at])
    if bad:
        array[at] = value
        with pytest.raises(ValueError) as err:
            sim.advance_by(0.01)
        message = str(err.value)
        assert '\n' not in message
        shown = str(part) if component is None else f'{part}, {component}'
        assert message.startswith(f"state.{field}[{shown}] (part 'box') must be finite and "
                                  f'within +-{STATE_BOUNDS[field]:g} ')
        assert sim.t == pytest.approx(0.01)
        array[at] = before
    else:
        array[at] = value(before)
    sim.advance_by(0.01)
    assert sim.t == pytest.approx(0.02, abs=1e-12)
    s = sim.state
    assert all(np.all(np.isfinite(a)) for a in (s.position, s.angle, s.velocity, s.omega))


def test_the_simulations_own_values_beyond_the_bounds_run_on():
    # a part that fell off the track falls on past the scene's bounds: not the caller's doing
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    sim.advance(0.01)
    part = int(sim.part_indices[0])
    sim.state.position[part, 1] = -2e4
    with pytest.raises(ValueError, match=r"^state\.position\[1, 1\] \(part 'box'\)"):
        sim.advance(0.02)
    sim._trusted = sim._trusted[:0] + (sim.state.position.tobytes(),) + sim._trusted[1:]
    sim.advance(0.02)                      # as if the simulation had put it there
    assert sim.t == pytest.approx(0.02)


@pytest.mark.parametrize('t', [1e18, -1e300, 1e10])
def test_a_state_time_beyond_the_round_off_of_a_step_is_refused(t):
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    sim.state.t = t
    for call in (lambda: sim.advance_by(0.01), lambda: sim.advance_to(t + 1.0)):
        with pytest.raises(ValueError, match=r'^state\.t must be within \+-1e\+09 s \(beyond, '
                                             r'a step of 0\.001 s is lost in the round-off'):
            call()


@pytest.mark.parametrize('duration', [np.float32(0.01), np.float16(0.01), np.float64(0.01),
                                      np.longdouble(0.01)], ids=lambda x: type(x).__name__)
def test_a_numpy_scalar_is_taken_as_the_python_float_it_stands_for(duration):
    # np.float32 made t a float32: kernels compiled anew for 84 s and t drifted to 0.0199999995
    sim = Simulator(parse_scene(SCENES['track_one_box']))
    start = time.perf_counter()
    sim.advance_by(duration)
    sim.advance_by(duration)
    sim.advance_to(np.float32(0.03))
    assert type(sim.t) is float and sim.t == 0.03
    assert time.perf_counter() - start < 5.0
    sim.state.t = np.float32(0.04)
    sim.advance_by(0.01)
    assert type(sim.t) is float and sim.t == pytest.approx(0.05, abs=1e-12)


@pytest.mark.parametrize('settings_type', [TimeStepSettings, EventSettings, ImpulseSettings])
def test_every_number_of_the_settings_has_a_range(settings_type):
    numbers = [f.name for f in dataclasses.fields(settings_type)
               if str(f.type).split('|')[0].strip() in ('int', 'float')]
    assert numbers and sorted(set(numbers) - set(settings_type.LIMITS)) == []


def test_no_pgs_sweep_is_refused_at_construction():
    with pytest.raises(ValueError, match=r'^TimeStepSettings\.pgs_max_sweeps must be an '
                                         r'integer \(64 bits\) >= 1, got 0$'):
        TimeStepSettings(pgs_max_sweeps=0)
