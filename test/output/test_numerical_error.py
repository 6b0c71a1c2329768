"""The numerical error bar: the companion's rule, ``feeder-sim run --error-estimate``, a study's
``convergence: true`` against a 4x refined run of the shipped studies, and ``time_step: auto``
against the exact point-mass conveying speed."""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import math

from paths import CONFIG
import pytest

from feeder_sim.cli import main
from feeder_sim.model.builders import build, conveyor
from feeder_sim.model.scene import parse_scene, scene_to_dict, SceneError, SolverSpec
from feeder_sim.output.numerical_error import Companion, companion
from feeder_sim.reports.accuracy import SlideRegime
from feeder_sim.reports.pointmass import Conveyor, mean_speed
from feeder_sim.run import run, run_with_error_estimate
from feeder_sim.simulator import Simulator
from feeder_sim.studies import load_study, run_study

pytestmark = pytest.mark.timeout(300)

STUDIES = CONFIG / 'studies'


# --- the rule ------------------------------------------------------------------------------

def test_the_rule_of_each_method():
    # first order, exactly: f(h) = f* + C h. The refined companion's estimate of the base run's
    # error is then exact, and so is the extrapolation.
    ts = companion(SolverSpec(method='time_stepping', time_step=2e-4))
    assert ts.solver.time_step == 1e-4 and ts.refined and ts.order == 1
    exact, slope = 0.04, 3.0
    base, fine = exact + slope * 2e-4, exact + slope * 1e-4
    assert ts.error(base, fine) == pytest.approx(slope * 2e-4, rel=1e-12)
    assert ts.extrapolated(base, fine) == pytest.approx(exact, rel=1e-12)
    assert 'Richardson p=1' in ts.method and 'half the step' in ts.method
    coarse = companion(SolverSpec(method='time_stepping', time_step=2e-4), refine=False)
    assert coarse.solver.time_step == 4e-4 and not coarse.refined
    assert coarse.error(base, exact + slope * 4e-4) == pytest.approx(slope * 2e-4, rel=1e-12)
    # order unknown: the plain difference, no extrapolation
    ed = companion(SolverSpec(method='event_driven', tolerance=1e-9))
    assert ed.solver.tolerance == pytest.approx(1e-11) and ed.order is None
    assert ed.error(1.0, 1.25) == 0.25 and ed.extrapolated(1.0, 1.25) is None
    ib = companion(SolverSpec(method='impulse_based', time_step=1e-3))
    assert ib.solver.time_step == 5e-4 and ib.error(2.0, 1.5) == 0.5
    # a coarsened setting past the allowed range is refined instead
    assert companion(SolverSpec(method='event_driven', tolerance=1e-3), refine=False).refined
    # a rule stored with a study's row gives the same errors
    assert Companion.from_rule(ts.rule()).error(base, fine) == ts.error(base, fine)
    assert ts.error(None, 1.0) is None and ts.error(math.nan, 1.0) is None


# --- feeder-sim run --error-estimate -------------------------------------------------------

def _conveyor(steps_per_period: float | str, **kw) -> dict:
    # mu_s = mu_d and a sliding, hopping box: time_stepping is first order here
    data = conveyor(psi=math.radians(20), mu=0.8, theta=math.radians(3), gamma=1.5,
                    method='time_stepping', **kw)
    if steps_per_period == 'auto':
        data['solver']['time_step'] = 'auto'
        del data['solver']['tolerance']          # the builder's is event_driven's, 1e-9
    else:
        data['solver']['time_step'] = 1 / 50 / steps_per_period
    return data


def test_a_runs_error_estimate_brackets_a_four_times_finer_run(tmp_path):
    # 0.4 s of the conveyor at 200 steps per period: the reported error of the box's speed and
    # position covers their distance to the same run at 800 steps per period, and the
    # extrapolated value is the base value moved by that error (Richardson, p = 1). It is not
    # asserted nearer the finer run: with Coulomb's law followed within the step the error at
    # these steps is small and changes sign (here the half-step run is farther from the
    # 800-step one than the base run: 1.3e-5 against 6.1e-6 m/s)
    base = run_with_error_estimate(Simulator(build(_conveyor(200))), 0.4)
    fine = run(Simulator(build(_conveyor(800))), 0.4).summary
    errors = base.summary['numerical_error']
    assert errors['method'].startswith('time_stepping at half the step (5e-05 s against '
                                       '0.0001 s), Richardson p=1')
    assert errors['companion']['time_step_s'] == pytest.approx(5e-5)
    assert errors['companion']['cost_ratio'] > 1.0
    for key in ('mean_velocity_along_track_mps', 'final_position_along_track_m'):
        got, want = base.summary['parts'][0][key], fine['parts'][0][key]
        assert errors['parts'][0]['name'] == 'box'
        assert 0 < abs(got - want) <= errors['parts'][0][key], key
        assert abs(errors['extrapolated']['parts'][0][key] - got) == pytest.approx(
            errors['parts'][0][key], rel=1e-9)
    assert errors['unresolved'] == []


def test_the_cli_adds_the_error_to_the_summary_and_says_so(tmp_path, capsys):
    scene = tmp_path / 'conveyor.yaml'
    scene.write_text(json.dumps(_conveyor(100)))
    summary = tmp_path / 'run.json'
    assert main(['-q', 'run', str(scene), '--duration', '0.2', '--summary', str(summary),
                 '--error-estimate']) == 0
    out = capsys.readouterr().out
    data = json.loads(summary.read_text())
    error = data['numerical_error']['parts'][0]['mean_velocity_along_track_mps']
    assert error > 0
    assert f'± {1e3 * error:.2g} mm/s' in out
    assert 'numerical error (±, of the numbers above): time_stepping at half the step' in out


def test_outcome_errors_from_counts_and_times():
    # the hook orienter for 2.5 s: every outcome of the summary gets an error under its own
    # key, by the same rule (2 |fine - base|): a count's is an even whole number, an exit
    # time's twice a whole number of frames (exits are seen at the 10 ms frames)
    result = run_with_error_estimate(Simulator('orienter_hook'), 2.5)
    s, e = result.summary, result.summary['numerical_error']
    assert [p['name'] for p in e['parts']] == [p['name'] for p in s['parts']]
    assert set(e['outcomes']['exit_orientations']) == set(s['outcomes']['exit_orientations'])
    assert set(e['outcomes']['exit_orientation_shares']) == {'open_end_up', 'open_end_down',
                                                             'other'}
    assert s['outcomes']['parts_exited'] >= 2
    for key in ('parts_exited', 'jams'):
        assert e['outcomes'][key] / 2 == round(e['outcomes'][key] / 2), key
    times = [p['exit_time_s'] for p in e['outcomes']['parts'] if p.get('exit_time_s') is not None]
    assert times
    for t in times:
        assert t / 0.02 == pytest.approx(round(t / 0.02), abs=1e-6)
    for share in e['outcomes']['exit_orientation_shares'].values():
        assert share is None or 0 <= share <= 2


# --- studies: convergence: true against a 4x refined run ----------------------------------

def _four_times_refined(spec):
    data = copy.deepcopy(spec.scene_data)
    solver = data.setdefault('solver', {})
    if (spec.method or solver.get('method')) == 'event_driven':
        solver['tolerance'] = solver.get('tolerance', 1e-9) / 100 ** 2
    else:
        solver['time_step'] = solver['time_step'] / 4
    return dataclasses.replace(spec, scene_data=data, convergence=False)


@pytest.fixture(scope='module')
def cluster():
    """One local Dask cluster of two worker processes for the studies below (as a study makes
    its own; started once)."""
    import logging

    from dask.distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=':0', silence_logs=logging.ERROR) as c:
        yield c.scheduler_address


# A design at the jam threshold (the hook orienter's low hooks with the cups touching) jams or
# not, and which cup, by the step itself (the 6 mm hook fed 4, 5, 6, 3, 4 cups in 5 s at 2x,
# 1x, 1/2, 1/4 and 1/8 of the step): no estimate from one companion run can promise to bracket
# it. Such a design is recognised by its jam, not named: `jammed` differs between the step,
# its half (a numerical error above 0) or its quarter. Every other design must be bracketed in
# every metric, and at most MAX_AT_THRESHOLD designs may be at the threshold.
MAX_AT_THRESHOLD = 3


@pytest.mark.slow
@pytest.mark.parametrize('name, duration_s', [('track_speed_map', 0.5),
                                              ('hook_orienter', 5.0)])
def test_a_studys_numerical_error_brackets_a_four_times_refined_run(tmp_path, cluster, name,
                                                                     duration_s):
    """The shipped studies' designs with ``convergence: true``, one trial each (the estimate
    is made on one trial per design; the speed map over 0.5 s instead of its 1 s, to keep the
    test short; the hook orienter over its own 5 s: cut short, a cup that would leave at the
    end counts or not by a step's difference): per design and metric,
    |base - run at 4x refined setting| <= the reported numerical error (time_stepping: a
    quarter of the step; event_driven: the tolerance / 100^2), to 1e-9 of the value (the
    round-off of a feed rate's time span); except the designs at the jam threshold (see
    ``MAX_AT_THRESHOLD``)."""
    spec = dataclasses.replace(load_study(STUDIES / f'{name}.yaml'), duration_s=duration_s,
                               repeats=1, convergence=True)
    summary = run_study(spec, tmp_path / 'study', scheduler=cluster, plots=False)
    fine = run_study(_four_times_refined(spec), tmp_path / 'fine', scheduler=cluster,
                     plots=False)
    assert summary['failed'] == fine['failed'] == 0
    assert summary['convergence']['designs_measured'] == len(spec.designs())
    rows = list(csv.DictReader(open(tmp_path / 'study' / 'results.csv')))
    changed, missed, at_threshold = 0, [], 0
    for d, f, row in zip(summary['designs'], fine['designs'], rows, strict=True):
        jam = d['metrics'].get('jammed')
        threshold = jam is not None and (jam['numerical_error'] > 0
                                          or jam['mean'] != f['metrics']['jammed']['mean'])
        at_threshold += threshold
        for metric in spec.metrics:
            base, ref = d['metrics'][metric]['mean'], f['metrics'][metric]['mean']
            error = d['metrics'][metric]['numerical_error']
            assert float(row[metric + '_numerical_error']) == pytest.approx(error, abs=0)
            if math.isnan(base) and math.isnan(ref):
                continue
            if abs(base - ref) > error + 1e-9 * abs(ref):
                missed.append((d['design'], metric, base, ref, error))
                assert threshold, missed[-1]
            changed += abs(base - ref) > 1e-9 * abs(ref)
    assert at_threshold <= MAX_AT_THRESHOLD
    print(f'{name}: {changed} design-metrics differ from the 4x refined run; not bracketed: '
          f'{missed} ({at_threshold} designs at the jam threshold); cost ratio '
          f'{summary["convergence"]["cost_ratio"]:.2f}')


def test_study_json_csv_warnings_and_plots(tmp_path, cluster):
    # the conveyor at 50 steps per period, two drive amplitudes, two repeats each (their drive
    # phases differ): the conveying speed's numerical error beside its interval; the step is
    # coarse enough that the error exceeds the interval's half-width somewhere, and the study
    # says where
    from feeder_sim.studies import parse_study
    scene = tmp_path / 'conveyor.yaml'
    scene.write_text(json.dumps(_conveyor(50)))
    spec = parse_study({
        'scene': str(scene), 'duration': 0.3, 'repeats': 2, 'seed': 3,
        'parameters': {'bodies[track].vibration.amplitude': [5.0e-4, 6.0e-4]},
        'perturb': {'drive_phase': True},
        'metrics': ['conveying_speed_mps'], 'convergence': True})
    summary = run_study(spec, tmp_path / 'out', scheduler=cluster, plots=True)
    rows = list(csv.DictReader(open(tmp_path / 'out' / 'results.csv')))
    assert 'conveying_speed_mps_numerical_error' in rows[0]
    filled = [r for r in rows if r['conveying_speed_mps_numerical_error']]
    assert [r['repeat'] for r in filled] == ['0', '0']
    for d in summary['designs']:
        m = d['metrics']['conveying_speed_mps']
        first = next(r for r in filled if int(r['design']) == d['design'])
        assert m['numerical_error'] == float(first['conveying_speed_mps_numerical_error']) > 0
        half = (m['ci95'][1] - m['ci95'][0]) / 2
        warned = any(line.startswith(f"design {d['design']} (") for line in summary['warnings'])
        assert warned == (m['numerical_error'] > half)
    assert summary['warnings'] and 'conveying_speed_mps' in summary['warnings'][0]
    assert summary['convergence']['method'].startswith('time_stepping at half the step')
    assert summary['convergence']['cost_ratio'] > 1.0
    written = json.loads((tmp_path / 'out' / 'study.json').read_text())
    assert written['designs'][0]['metrics']['conveying_speed_mps']['numerical_error'] > 0
    assert (tmp_path / 'out' / 'conveying_speed_mps.png').stat().st_size > 10_000


# --- time_step: auto -----------------------------------------------------------------------

def test_auto_is_read_checked_and_written_back():
    scene = build(_conveyor('auto'))
    assert scene.solver.time_step_auto and scene.solver.tolerance == 0.01
    assert scene.solver.time_step == pytest.approx(1 / 50 / 50)     # the first candidate
    assert scene_to_dict(scene)['solver']['time_step'] == 'auto'
    data = _conveyor('auto')
    data['solver']['tolerance'] = 0.005
    assert build(data).solver.tolerance == 0.005
    for change, fragment in (
            ({'method': 'event_driven'}, 'auto picks the fixed step of time_stepping, not of '
                                         'event_driven'),
            ({'time_step': 'automatic'}, 'or auto (time_stepping'),
            ({'tolerance': 0.5}, 'out of range'),
            ({'tolerance': 1e-9}, 'time_step: auto asks for the conveying speed to 1e-07 %')):
        bad = _conveyor('auto')
        bad['solver'].update(change)
        with pytest.raises(SceneError) as err:
            parse_scene(bad)
        assert err.value.path.startswith('solver.') and fragment in err.value.message
        assert '\n' not in str(err.value)
    still = _conveyor('auto')
    still['bodies'][0]['vibration']['frequency'] = 0.0
    with pytest.raises(SceneError, match=r'solver.time_step: auto picks the step .* no body '
                                         'vibrates'):
        parse_scene(still)
    with pytest.raises(SceneError, match='solver.time_step: auto picks the fixed step of '
                                         'time_stepping, not of impulse_based'):
        Simulator(scene, method='impulse_based')
    with pytest.raises(SceneError, match=r'solver.tolerance: 1e-09 with time_step: auto'):
        Simulator(scene, tolerance=1e-9)
    # a step given replaces the pilot
    assert Simulator(scene, time_step=1e-4).scene.solver.time_step == 1e-4


def test_auto_meets_its_tolerance_against_the_exact_point_mass(capsys):
    # psi 20 deg, mu_s = mu_d = 0.8, 3 deg uphill, Gamma 1.5: the box slides and hops. auto
    # picks the step whose conveying speed the pilot puts within 1 %; the speed over cycles
    # 20-40 is within 1 % of the exact point mass (feeder_sim.reports.pointmass), and the
    # pilot's cost is reported beside the fixed 400 steps per period
    sim = Simulator(build(_conveyor('auto')))
    pilot = sim.time_step_pilot
    assert pilot['met'] and pilot['estimated_relative_error'] <= 0.01
    assert pilot['fixed_steps_per_period'] == 400
    assert pilot['time_step_s'] == sim.scene.solver.time_step
    steps = pilot['steps_per_period']
    assert steps in (50, 100, 200, 400, 800, 1600)
    f = 50.0
    sim.advance_to(20 / f)
    s1 = sim.track_coordinates()[0][0]
    sim.advance_to(40 / f)
    v = (sim.track_coordinates()[0][0] - s1) * f / 20
    c = Conveyor(psi=math.radians(20), theta=math.radians(3), mu_s=0.8, mu_k=0.8, gamma=1.5)
    assert v == pytest.approx(mean_speed(c, warmup_cycles=20, cycles=20), rel=0.01)
    # cost: the pilot's steps and the run's against the same 40 cycles at 400 per period
    ratio = (pilot['pilot']['steps'] + 40 * steps) / (40 * 400)
    print(f'auto: {steps:.0f} steps per period, pilot {pilot["pilot"]["steps"]} steps, '
          f'{pilot["pilot"]["wall_s"]:.2f} s; steps against the fixed 400 over 40 cycles: '
          f'{ratio:.2f}')
    result = run(sim, 0.1)
    assert result.summary['time_step_auto'] == pilot
    assert result.summary['time_step_s'] == pilot['time_step_s']


@pytest.mark.parametrize('regime', [
    SlideRegime(10.0, 0.0, 1.25, 0.8, 50.0),     # forward and back, mu_s > mu_d
    SlideRegime(20.0, 3.0, 1.5, 0.5, 50.0),      # uphill stick-slip
    SlideRegime(30.0, 5.0, 1.5, 0.8, 50.0),      # never sticks for long
], ids=str)
def test_auto_meets_one_percent_in_the_slide_regime(regime):
    # The slide regime of the friction-law sweep (test_slide_conveying): the step auto picks
    # keeps the mean speed over cycles 20-40 within 1 % of the exact point mass
    scene = conveyor(psi=math.radians(regime.psi_deg), mu=regime.ratio * regime.mu_d,
                     mu_dynamic=regime.mu_d, theta=math.radians(regime.theta_deg),
                     gamma=regime.gamma, frequency_hz=regime.frequency_hz,
                     method='time_stepping', start_with_track=True)
    scene['solver']['time_step'] = 'auto'
    del scene['solver']['tolerance']
    sim = Simulator(build(scene))
    assert sim.time_step_pilot['met']
    f = regime.frequency_hz
    sim.advance_to(20 / f)
    s1 = sim.track_coordinates()[0][0]
    sim.advance_to(40 / f)
    v = (sim.track_coordinates()[0][0] - s1) * f / 20
    assert v == pytest.approx(regime.reference(), rel=0.01)
