"""Design studies on a real Dask cluster: the study file, designs and seeds, the numbers a
trial gives, the statistics, resuming, 1 and 2 workers, a scheduler and a worker started as
their own processes."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
from paths import CONFIG
import pytest
from scipy import stats
import yaml

from feeder_sim.run import run
from feeder_sim.simulator import Simulator
from feeder_sim.studies import parse_study, run_study, StudyError
from feeder_sim.studies.runner import all_trials, run_trials, stored
from feeder_sim.studies.spec import scene_of_design, set_path
from feeder_sim.studies.summary import t_interval, wilson

pytestmark = pytest.mark.timeout(300)

SMALL = {
    'scene': 'track_one_box', 'duration': 0.2, 'repeats': 2, 'seed': 3,
    'parameters': {'bodies[track].vibration.amplitude': [2.0e-4, 4.0e-4],
                   'bodies[track].vibration.frequency': {'range': [40.0, 50.0], 'count': 2}},
    'perturb': {'drive_phase': True, 'position_m': 1e-4},
    'metrics': ['conveying_speed_mps', 'final_position_m'],
}


def study_file(tmp_path: Path, data: dict, name: str = 'study.yaml') -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def table(out: Path) -> list[list[str]]:
    """results.csv without the columns that depend on the machine (wall time)."""
    lines = [row.split(',') for row in (out / 'results.csv').read_text().splitlines()]
    keep = [i for i, c in enumerate(lines[0]) if c != 'wall_s']
    return [[r[i] for i in keep] for r in lines]


# --- the study file ------------------------------------------------------------------------

@pytest.mark.parametrize('change, path, fragment', [
    ({'sceen': 'x'}, 'sceen', "unknown key 'sceen'"),
    ({'duration': -1}, 'duration', 'positive finite number'),
    ({'metrics': ['speed']}, 'metrics[0]', "unknown metric 'speed'"),
    ({'parameters': {'bodies[trak].vibration.amplitude': [1e-4]}},
     'parameters.bodies[trak].vibration.amplitude', "no body named 'trak'"),
    ({'parameters': {'bodies[track].vibration.amplitude': [0.5]}},
     'parameters.bodies[track].vibration.amplitude', 'invalid scene'),
    ({'parameters': {'hook_height': [0.01]}}, 'parameters.hook_height',
     'a parameter is one the scene declares (none) or a key path'),
    ({'parameters': {'solver.time_step': {'range': [1e-3], 'count': 2}}},
     'parameters.solver.time_step', 'a range is {range: [lo, hi], count: n}'),
    ({'repeats': 0}, 'repeats', 'whole number from 1'),
    ({'objective': {'metric': 'jams'}}, 'objective', 'one of the metrics'),
    ({'metrics': ['conveying_speed_mps', 'fraction:sideways']}, 'metrics[1]',
     "the scene names no orientation 'sideways'; its outcomes.orientations: none"),
    ({'perturb': {'position_m': -1e-4}}, 'perturb.position_m', 'a spread >= 0, got -0.0001'),
    ({'perturb': {'drive_phase': 'yes please'}}, 'perturb.drive_phase', 'true or false'),
    ({'parameters': {'bodies[track].vibration.amplitude': {
        'sample': 'random', 'low': 5e-4, 'high': 1e-4, 'count': 2}}},
     'parameters.bodies[track].vibration.amplitude', 'low (0.0005) must be below high'),
], ids=['unknown key', 'duration', 'metric', 'body name', 'value', 'not a parameter',
        'range', 'repeats', 'objective', 'orientation', 'negative spread', 'phase flag',
        'empty sample'])
def test_a_bad_study_file_is_one_line_naming_the_key(change, path, fragment):
    with pytest.raises(StudyError) as err:
        parse_study({**SMALL, **change}, 'study.yaml')
    assert err.value.path == path and fragment in err.value.message, str(err.value)
    assert '\n' not in str(err.value)


@pytest.mark.parametrize('text, fragment', [
    ('duration: 0.2\nduration: 0.3\n', "duplicate key 'duration' at line 2"),
    ('a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]\n' + ''.join(
        f'a{i}: &a{i} [{", ".join([f"*a{i - 1}"] * 9)}]\n' for i in range(1, 11)),
     'its YAML aliases expand to more than'),
    ('x: ' + '[' * 40 + ']' * 40 + '\n', 'nested deeper than 32 levels; a study file'),
    (b'\x80\x81', 'not UTF-8 text'),
], ids=['duplicate key', 'alias bomb', 'nesting', 'not utf-8'])
def test_a_study_file_is_read_as_scene_files_are(tmp_path, text, fragment):
    from feeder_sim.studies import load_study
    path = tmp_path / 'study.yaml'
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(StudyError) as err:
        load_study(path)
    assert str(err.value).startswith(f'{path}: ') and fragment in str(err.value)
    assert '\n' not in str(err.value)


def test_a_study_file_takes_yaml_12_numbers(tmp_path):
    from feeder_sim.studies import load_study
    path = tmp_path / 'study.yaml'
    path.write_text('scene: track_one_box\nduration: 2e-1\nrepeats: 1\nparameters:\n'
                    '  bodies[track].vibration.amplitude: [2e-4]\nmetrics: [final_position_m]\n')
    spec = load_study(path)
    assert spec.duration_s == 0.2 and spec.parameters[0].values == (2e-4,)


def test_a_sampled_parameter_is_checked_at_the_ends_of_its_interval(monkeypatch):
    from feeder_sim.studies import spec as spec_module
    calls = []
    parse = spec_module.parse_scene

    def counted(*args, **kw):
        calls.append(args)
        return parse(*args, **kw)

    monkeypatch.setattr(spec_module, 'parse_scene', counted)
    sampled = {'bodies[track].vibration.amplitude': {'sample': 'random', 'low': 1e-4,
                                                     'high': 5e-4, 'count': 20_000}}
    spec = parse_study({**SMALL, 'repeats': 1, 'parameters': sampled})
    assert len(spec.designs()) == 20_000
    assert len(calls) <= 4             # its two ends (and the metrics' check), not 20 000 draws
    sampled['bodies[track].vibration.amplitude']['high'] = 0.5
    with pytest.raises(StudyError) as err:
        parse_study({**SMALL, 'repeats': 1, 'parameters': sampled})
    assert err.value.path == 'parameters.bodies[track].vibration.amplitude'
    assert err.value.message.startswith('0.5 gives an invalid scene')


def test_designs_grid_and_latin_hypercube():
    spec = parse_study(SMALL)
    designs = spec.designs()
    assert len(designs) == 4 and len(all_trials(spec)) == 8
    assert {d['bodies[track].vibration.frequency'] for d in designs} == {40.0, 50.0}
    lhs = parse_study({**SMALL, 'parameters': {
        'bodies[track].vibration.amplitude': {'sample': 'lhs', 'low': 1e-4, 'high': 5e-4,
                                              'count': 8},
        'bodies[track].vibration.frequency': {'sample': 'lhs', 'low': 30.0, 'high': 70.0,
                                              'count': 8}}})
    points = lhs.designs()
    assert len(points) == 8 and points == lhs.designs()             # seeded
    for name, lo, hi in (('bodies[track].vibration.amplitude', 1e-4, 5e-4),
                         ('bodies[track].vibration.frequency', 30.0, 70.0)):
        strata = sorted(int((d[name] - lo) / (hi - lo) * 8) for d in points)
        assert strata == list(range(8))                           # one point per stratum
    # a trial's seed depends on its design and repeat only
    assert spec.trial_seed(designs[1], 1) == parse_study(SMALL).trial_seed(designs[1], 1)
    assert spec.trial_seed(designs[1], 0) != spec.trial_seed(designs[1], 1)


def test_key_paths_address_bodies_by_name_or_index():
    data = {'solver': {'time_step': 1e-3}, 'bodies': [{'name': 'track', 'pose': [0, 0, 0]},
                                                      {'name': 'box', 'pose': [0, 0, 0]}]}
    set_path(data, 'bodies[box].pose[1]', 0.5)
    set_path(data, 'bodies[0].pose[2]', 0.1)
    set_path(data, 'solver.time_step', 2e-4)
    assert data['bodies'][1]['pose'] == [0, 0.5, 0] and data['bodies'][0]['pose'][2] == 0.1
    assert data['solver']['time_step'] == 2e-4
    with pytest.raises(KeyError, match='past the end'):
        set_path(data, 'bodies[5].pose', 1.0)


# --- statistics ----------------------------------------------------------------------------

def test_intervals_against_their_definitions():
    # Wilson: 5 of 10 -> (0.2366, 0.7634); 0 of 20 -> (0, 0.1611)
    assert wilson(5, 10) == pytest.approx((0.23659, 0.76341), abs=1e-5)
    assert wilson(0, 20) == pytest.approx((0.0, 0.16113), abs=1e-5)
    values = np.array([1.0, 2.0, 4.0, 7.0])
    lo, hi = t_interval(values)
    half = stats.t.ppf(0.975, 3) * np.std(values, ddof=1) / 2.0
    assert (lo, hi) == pytest.approx((3.5 - half, 3.5 + half))
    assert all(math.isnan(x) for x in t_interval(np.array([1.0])))


# --- trials on a cluster -------------------------------------------------------------------

def test_a_trial_is_the_run_of_its_scene(tmp_path):
    # without perturbation, a trial's metric is what a plain run of the design's scene gives
    spec = parse_study({**SMALL, 'perturb': {}, 'repeats': 1})
    summary = run_study(spec, tmp_path / 'out', workers=1, plots=False)
    design = spec.designs()[3]
    sim = Simulator(scene_of_design(spec, design))
    result = run(sim, 0.2, publish_rate_hz=100.0)
    expected = result.summary['parts'][0]['mean_velocity_along_track_mps']
    got = summary['designs'][3]['metrics']['conveying_speed_mps']['mean']
    assert got == expected                                        # bit for bit
    assert summary['designs'][3]['parameters'] == design


def test_one_and_two_workers_give_the_same_table_and_a_rerun_computes_nothing(tmp_path):
    spec = parse_study(SMALL, 'small.yaml')
    one = run_study(spec, tmp_path / 'one', workers=1)
    two = run_study(spec, tmp_path / 'two', workers=2)
    assert table(tmp_path / 'one') == table(tmp_path / 'two')
    assert one['trials'] == two['trials'] == 8 and one['failed'] == 0
    for name in ('results.csv', 'results.parquet', 'study.json',
                 'conveying_speed_mps.png', 'final_position_m.png'):
        assert (tmp_path / 'two' / name).stat().st_size > 0, name
    import pyarrow.parquet as pq
    frame = pq.read_table(tmp_path / 'two' / 'results.parquet').to_pylist()
    assert [r['conveying_speed_mps'] for r in frame] == \
        [float(r[5]) for r in table(tmp_path / 'two')[1:]]
    # the repeats differ (their seeds perturb the start), the statistics cover them
    d0 = two['designs'][0]['metrics']['conveying_speed_mps']
    lo, hi = d0['ci95']
    assert d0['n'] == 2 and lo < d0['mean'] < hi
    computed = []
    run_trials(spec, tmp_path / 'two', workers=1, on_row=computed.append)
    assert computed == []


def test_a_study_resumes_what_is_missing(tmp_path):
    spec = parse_study(SMALL, 'small.yaml')
    out = tmp_path / 'resumed'
    run_study(spec, out, workers=2, plots=False)
    full = table(out)
    files = sorted((out / 'trials').glob('*.json'))
    for path in files[::2]:
        path.unlink()                                    # as if stopped midway
    (files[1]).write_text('{"truncated')                 # and one written half
    computed = []
    run_trials(spec, out, workers=2, on_row=computed.append)
    assert len(computed) == len(files[::2]) + 1
    run_study(spec, out, workers=2, plots=False)
    assert table(out) == full


def test_a_failing_trial_is_recorded_and_the_study_goes_on(tmp_path):
    # the track scene names no orientations: that metric fails every trial, with its reason
    # (parse_study refuses it; a spec edited past the check must not stop the study)
    spec = dataclasses.replace(parse_study({**SMALL, 'repeats': 1}), metrics=(
        'conveying_speed_mps', 'fraction:open_end_up'))
    summary = run_study(spec, tmp_path / 'out', workers=2, plots=False)
    assert summary['failed'] == summary['trials'] == 4
    rows = [json.loads(p.read_text()) for p in (tmp_path / 'out' / 'trials').glob('*.json')]
    assert all(r['status'] == 'error' and 'names no orientation' in r['error'] for r in rows)


def test_a_study_killed_midway_resumes_without_recomputing(tmp_path):
    study = study_file(tmp_path, {**SMALL, 'duration': 1.0, 'repeats': 3})
    out = tmp_path / 'killed'
    cmd = [sys.executable, '-m', 'feeder_sim.cli', 'study', str(study), '--out', str(out),
           '--workers', '1']
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    end = time.monotonic() + 120
    while len(list((out / 'trials').glob('*.json'))) < 3:
        assert proc.poll() is None and time.monotonic() < end, proc.communicate()
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    done = stored(out)
    assert 3 <= len(done) < 12
    spec = parse_study({**SMALL, 'duration': 1.0, 'repeats': 3})
    computed = []
    run_trials(spec, out, workers=2, on_row=computed.append)
    assert len(computed) == 12 - len(done)
    assert not {r['key'] for r in computed} & set(done)


def test_a_scheduler_that_does_not_answer_is_one_line(tmp_path):
    study = study_file(tmp_path, SMALL)
    proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'study', str(study), '--out',
                           str(tmp_path / 'out'), '--scheduler', 'tcp://127.0.0.1:1'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    # the progress lines the study says as it starts, then the error in one line
    lines = [line for line in proc.stderr.strip().splitlines()
             if not line.startswith('[feeder_sim] study: ')]
    assert len(lines) == 1 and 'Traceback' not in proc.stderr, proc.stderr
    assert lines[0].startswith('feeder-sim: error: --scheduler tcp://127.0.0.1:1: no Dask '
                               'scheduler answered (Connection refused)')


def start_dask_processes(folder: Path, procs: list[subprocess.Popen]) -> str:
    """A Dask scheduler and one single-threaded worker as processes of their own sessions
    (appended to ``procs``, for the caller to end); the scheduler's address."""
    scheduler_file = folder / 'scheduler.json'

    def start(args: list[str]) -> subprocess.Popen:
        procs.append(subprocess.Popen([sys.executable, '-m', *args],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True))
        return procs[-1]

    start(['distributed.cli.dask_scheduler', '--host', '127.0.0.1', '--port', '0',
           '--dashboard-address', ':0', '--scheduler-file', str(scheduler_file)])
    end = time.monotonic() + 60
    while not scheduler_file.exists():
        assert time.monotonic() < end
        time.sleep(0.05)
    address = json.loads(scheduler_file.read_text())['address']
    start(['distributed.cli.dask_worker', address, '--nworkers', '1', '--nthreads', '1',
           '--no-dashboard'])
    return address


def test_a_scheduler_and_a_worker_started_as_processes(tmp_path):
    procs: list[subprocess.Popen] = []
    try:
        address = start_dask_processes(tmp_path, procs)
        study = study_file(tmp_path, {**SMALL, 'repeats': 1})
        proc = subprocess.run([sys.executable, '-m', 'feeder_sim.cli', 'study', str(study),
                               '--out', str(tmp_path / 'remote'), '--scheduler', address],
                              capture_output=True, text=True, timeout=240)
        assert proc.returncode == 0, proc.stderr
        assert '4 trials (0 failed)' in proc.stdout
        local = run_study(parse_study({**SMALL, 'repeats': 1}), tmp_path / 'local', workers=1,
                          plots=False)
        assert local['trials'] == 4
        assert table(tmp_path / 'remote') == table(tmp_path / 'local')
    finally:
        for p in procs:
            os.killpg(p.pid, signal.SIGTERM)
            p.wait(timeout=30)


def test_per_trial_logs_all_or_only_the_jammed(tmp_path):
    # a drive of 1 nm leaves the box where it is: jammed after jam_time (1 s); 0.4 mm feeds it
    from mcap.reader import make_reader
    base = {**SMALL, 'duration': 1.5, 'repeats': 1, 'perturb': {},
            'parameters': {'bodies[track].vibration.amplitude': [1e-9, 4e-4]},
            'metrics': ['jammed', 'conveying_speed_mps']}
    for record, kept in (('all', 2), ('jammed', 1)):
        out = tmp_path / record
        summary = run_study(parse_study({**base, 'record': record}), out, workers=1,
                            plots=False)
        assert [d['metrics']['jammed']['mean'] for d in summary['designs']] == [1.0, 0.0]
        logs = sorted((out / 'logs').glob('*.mcap'))
        assert len(logs) == kept
        with open(logs[0], 'rb') as f:
            assert make_reader(f).get_summary().statistics.message_count > 100
        rows = {r['design']: r for r in json.loads((out / 'study.json').read_text())['designs']}
        assert set(rows) == {0, 1}


def test_the_point_mass_reference_beside_the_measured_speed(tmp_path):
    # one box sliding and hopping on the track: the measured mean speed over 2 s (start-up
    # included) is within 3 % of the point-mass theory's steady speed for the same design
    spec = parse_study({**SMALL, 'duration': 2.0, 'repeats': 1, 'perturb': {},
                        'parameters': {'bodies[track].vibration.amplitude': [2e-4, 3e-4]},
                        'metrics': ['conveying_speed_mps'], 'reference': 'pointmass'})
    summary = run_study(spec, tmp_path / 'out', workers=1, plots=True)
    for d in summary['designs']:
        theory = d['reference']['conveying_speed_mps']
        assert theory > 0.01
        assert d['metrics']['conveying_speed_mps']['mean'] == pytest.approx(theory, rel=0.03)
    with pytest.raises(StudyError, match='add the metric conveying_speed_mps'):
        parse_study({**SMALL, 'metrics': ['jams'], 'reference': 'pointmass'})


def test_workers_need_neither_the_scene_file_nor_its_path(tmp_path):
    # a cluster's workers on other machines: the scene travels with the study
    scene = tmp_path / 'scene.yaml'
    scene.write_text((CONFIG /
                      'track_one_box.yaml').read_text())
    study = study_file(tmp_path, {**SMALL, 'scene': 'scene.yaml', 'repeats': 1})
    from feeder_sim.studies import load_study
    spec = load_study(study)
    scene.unlink()
    summary = run_study(spec, tmp_path / 'out', workers=2, plots=False)
    assert summary['failed'] == 0 and summary['trials'] == 4
    with pytest.raises(StudyError, match=r'publish_rate: at most 100000'):
        parse_study({**SMALL, 'publish_rate': 1e9})


def test_every_shipped_study_is_valid():
    studies = sorted((CONFIG / 'studies').glob('*.yaml'))
    assert len(studies) >= 4
    from feeder_sim.studies import load_study
    for path in studies:
        spec = load_study(path)                       # the file and every design's scene
        assert spec.designs() and spec.metrics


def test_convergence_is_true_or_false():
    assert parse_study({**SMALL, 'convergence': True}).convergence
    assert not parse_study(SMALL).convergence
    with pytest.raises(StudyError) as err:
        parse_study({**SMALL, 'convergence': 'yes'})
    assert err.value.path == 'convergence' and 'expected true or false' in err.value.message
