"""Studies where something is wrong: a directory of another spec, a scheduler that dies or is
not a scheduler, sizes counted before they are built, extremes checked before the first
trial, failed trials, a full disk. The trials run on a real Dask LocalCluster (one, shared:
its start is most of a small study's time) and on a scheduler started as its own process."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import errno
import http.server
import json
import os
from pathlib import Path
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest
from test_studies import start_dask_processes
import yaml

from feeder_sim import cli
from feeder_sim.studies import parse_study, run_study, runner, StudyError
from feeder_sim.studies.runner import run_trials, SpecChanged, stored

pytestmark = pytest.mark.timeout(120)

TINY = {
    'scene': 'track_one_box', 'duration': 0.1, 'repeats': 1, 'seed': 4,
    'parameters': {'bodies[track].vibration.amplitude': [2.0e-4, 4.0e-4]},
    'perturb': {'drive_phase': True},
    'metrics': ['conveying_speed_mps'],
}


def error_lines(stderr: str) -> list[str]:
    """What a study printed on stderr besides its progress (its bar, its 'study:' lines)."""
    return [line for line in stderr.replace('\r', '\n').splitlines()
            if line.strip() and not line.startswith(('study:', '[feeder_sim] study:'))]


@pytest.fixture(scope='module')
def cluster():
    """A LocalCluster of one worker process; studies reach it by its address."""
    from dask.distributed import LocalCluster
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=':0') as local:
        yield local.scheduler_address


def rows_of(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / 'trials').glob('*.json'))]


# --- a directory belongs to one spec -------------------------------------------------------

def test_a_changed_spec_is_named_and_refused_or_recomputed(tmp_path, cluster, monkeypatch,
                                                           capsys):
    out = tmp_path / 'out'
    first = run_study(parse_study(TINY), out, scheduler=cluster, plots=False)
    assert first['trials'] == 2 and first['failed'] == 0
    speeds = {r['key']: r['conveying_speed_mps'] for r in rows_of(out)}

    longer = parse_study({**TINY, 'duration': 0.3})
    with pytest.raises(SpecChanged) as err:
        run_trials(longer, out, scheduler=cluster)
    assert 'duration 0.1 -> 0.3 s' in str(err.value) and '--recompute' in str(err.value)
    # the command line: one line, exit 2, nothing computed or deleted
    study = tmp_path / 'longer.yaml'
    study.write_text(yaml.safe_dump({**TINY, 'duration': 0.3}))
    capsys.readouterr()                            # the first run's progress bar
    assert cli.main(['study', str(study), '--out', str(out), '--scheduler', cluster]) == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and 'duration 0.1 -> 0.3 s' in lines[0], lines
    assert {r['key']: r['conveying_speed_mps'] for r in rows_of(out)} == speeds

    # the scene's data and the package version are part of the spec too
    data = json.loads(json.dumps(longer.scene_data))
    data['bodies'][1]['mass'] = 0.02 if data['bodies'][1].get('mass') != 0.02 else 0.03
    with pytest.raises(SpecChanged, match="the scene's data"):
        run_trials(dataclasses.replace(parse_study(TINY), scene_data=data), out)
    monkeypatch.setattr(runner, '__version__', '99.0')
    with pytest.raises(SpecChanged, match='feeder_sim 0.1.0 -> 99.0'):
        run_trials(parse_study(TINY), out)
    monkeypatch.undo()

    # --recompute: every trial again, at the new duration, and the directory is the new spec's
    summary = run_study(longer, out, scheduler=cluster, plots=False, recompute=True)
    assert summary['duration_s'] == 0.3 and summary['trials'] == 2
    again = {r['key']: r['conveying_speed_mps'] for r in rows_of(out)}
    assert set(again) == set(speeds) and all(again[k] != speeds[k] for k in speeds)
    computed = []
    run_trials(longer, out, scheduler=cluster, on_row=computed.append)
    assert computed == []


def test_an_added_metric_reruns_the_trials_without_it(tmp_path, cluster, caplog):
    out = tmp_path / 'out'
    run_study(parse_study(TINY), out, scheduler=cluster, plots=False)
    wider = parse_study({**TINY, 'metrics': ['conveying_speed_mps', 'final_position_m']})
    computed = []
    with caplog.at_level('INFO', logger='feeder_sim'):
        run_trials(wider, out, scheduler=cluster, on_row=computed.append)
    assert len(computed) == 2 and all('final_position_m' in r for r in computed)
    assert '2 stored trials lack final_position_m: computing them again' in caplog.text
    summary = run_study(wider, out, scheduler=cluster, plots=False)
    assert summary['failed'] == 0
    assert summary['designs'][1]['metrics']['final_position_m']['n'] == 1


def test_rows_of_a_lost_trial_are_not_results(tmp_path, cluster):
    # what an older study stored for trials the cluster cancelled: computed again
    spec = parse_study(TINY)
    out = tmp_path / 'out'
    run_study(spec, out, scheduler=cluster, plots=False)
    path = sorted((out / 'trials').glob('*.json'))[0]
    row = json.loads(path.read_text())
    path.write_text(json.dumps({**row, 'status': 'error',
                                'error': 'FutureCancelledError: lost'}))
    assert path.stem not in stored(out, spec=spec)
    computed = []
    run_trials(spec, out, scheduler=cluster, on_row=computed.append)
    assert [r['key'] for r in computed] == [path.stem] and computed[0]['status'] == 'ok'


# --- a scheduler that dies mid-study -------------------------------------------------------

def test_a_lost_scheduler_ends_the_study_and_a_rerun_completes_it(tmp_path, cluster):
    procs: list[subprocess.Popen] = []
    try:
        address = start_dask_processes(tmp_path, procs)
        data = {**TINY, 'duration': 0.5, 'repeats': 6,
                'parameters': {'bodies[track].vibration.amplitude': [2.0e-4]}}
        study = tmp_path / 'study.yaml'
        study.write_text(yaml.safe_dump(data))
        out = tmp_path / 'out'
        proc = subprocess.Popen([sys.executable, '-m', 'feeder_sim.cli', '-q', 'study',
                                 str(study), '--out', str(out), '--scheduler', address],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        procs.append(proc)
        end = time.monotonic() + 90
        while not list((out / 'trials').glob('*.json')):
            if proc.poll() is not None or time.monotonic() > end:
                proc.kill()
                pytest.fail(f'no trial stored: {proc.communicate()}')
            time.sleep(0.05)
        os.killpg(procs[0].pid, signal.SIGKILL)
        killed = time.monotonic()
        _, err = proc.communicate(timeout=30)
        took = time.monotonic() - killed
        assert proc.returncode != 0 and took < 15, (proc.returncode, took, err)
        lines = error_lines(err)
        assert len(lines) == 1 and 'stopped answering' in lines[0], err
        done = rows_of(out)
        assert 1 <= len(done) < 6 and all(r['status'] == 'ok' for r in done)
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    # a fresh cluster: only the missing trials
    computed = []
    run_trials(parse_study(data), out, scheduler=cluster, on_row=computed.append)
    assert len(computed) == 6 - len(done)
    assert not {r['key'] for r in computed} & {r['key'] for r in done}
    assert all(r['status'] == 'ok' for r in rows_of(out)) and len(rows_of(out)) == 6


# --- scheduler addresses that are no scheduler ---------------------------------------------

class _Quiet(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def _serve(handle) -> tuple[str, socket.socket]:
    """A loopback listener whose every connection goes to ``handle`` (in a thread)."""
    listener = socket.create_server(('127.0.0.1', 0))

    def accept() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            threading.Thread(target=handle, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    return f'tcp://127.0.0.1:{listener.getsockname()[1]}', listener


def _silent(conn: socket.socket) -> None:
    time.sleep(30)
    conn.close()


def _huge_frame(conn: socket.socket) -> None:
    try:
        conn.sendall(struct.pack('<Q', 1 << 60) + b'\xff' * 64)
        time.sleep(30)
    except OSError:
        pass
    conn.close()


def _garbage(conn: socket.socket) -> None:
    # a plausible length, then bytes that are no Dask message
    try:
        conn.sendall(struct.pack('<Q', 40) + os.urandom(40))
        time.sleep(30)
    except OSError:
        pass
    conn.close()


def test_what_is_not_a_dask_scheduler_is_one_line_within_15_s(tmp_path, capsys):
    httpd = http.server.ThreadingHTTPServer(('127.0.0.1', 0), _Quiet)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    servers = [_serve(h) for h in (_silent, _huge_frame, _garbage)]
    free = socket.create_server(('127.0.0.1', 0))
    closed = f'tcp://127.0.0.1:{free.getsockname()[1]}'
    free.close()
    addresses = {'http': f'tcp://127.0.0.1:{httpd.server_address[1]}',
                 'silent': servers[0][0], 'huge frame': servers[1][0],
                 'garbage': servers[2][0], 'closed port': closed}
    expected = {'http': 'sent nothing', 'silent': 'sent nothing',
                'huge frame': 'not a Dask scheduler', 'garbage': 'not a Dask scheduler',
                'closed port': 'no Dask scheduler answered (Connection refused)'}

    def attempt(address: str) -> tuple[str, float]:
        start = time.monotonic()
        try:
            runner.make_client(address, None)
        except OSError as err:
            return str(err), time.monotonic() - start
        return 'connected', time.monotonic() - start

    try:
        with concurrent.futures.ThreadPoolExecutor(len(addresses)) as pool:
            results = dict(zip(addresses, pool.map(attempt, addresses.values()), strict=True))
        for name, (message, took) in results.items():
            assert took < 15 and '\n' not in message, (name, took, message)
            assert message.startswith(f'--scheduler {addresses[name]}: ') \
                and expected[name] in message, (name, message)
        # and on the command line: one line, exit 2
        assert cli.main(['study', 'config/studies/track_speed_map.yaml', '--out', str(tmp_path),
                         '--scheduler', addresses['huge frame']]) == 2
        err = error_lines(capsys.readouterr().err)
        assert len(err) == 1 and 'not a Dask scheduler' in err[0], err
    finally:
        httpd.shutdown()
        for _, listener in servers:
            listener.close()


@pytest.mark.parametrize('address, fragment', [
    ('inproc://x', 'an in-process address is reachable only inside the process'),
    ('tcp://127.0.0.1:port', 'expected tcp://HOST:PORT or tls://HOST:PORT'),
    ('http://127.0.0.1:8787', 'expected tcp://HOST:PORT or tls://HOST:PORT'),
], ids=['inproc', 'port', 'http scheme'])
def test_an_address_that_is_no_scheduler_address_is_one_line(address, fragment, tmp_path):
    with pytest.raises(OSError) as err:
        runner.make_client(address, None)
    assert str(err.value).startswith(f'--scheduler {address}: ') and fragment in str(err.value)


# --- sizes and extremes before the first trial ---------------------------------------------

@pytest.mark.parametrize('count, sizes', [(100_000, '100000 x 100000'), (3163, '3163 x 3163')])
def test_a_study_too_large_is_refused_before_its_designs_are_built(count, sizes):
    grid = {'bodies[track].vibration.amplitude': {'range': [1e-4, 5e-4], 'count': count},
            'bodies[track].vibration.frequency': {'range': [30.0, 60.0], 'count': count}}
    start = time.perf_counter()
    with pytest.raises(StudyError) as err:
        parse_study({**TINY, 'parameters': grid})
    assert time.perf_counter() - start < 1.0
    assert err.value.path == 'parameters'
    assert err.value.message.startswith(f'{sizes} designs x 1 repeats = {count * count} trials')


def test_a_long_range_is_checked_at_its_ends_in_well_under_a_second():
    grid = {'bodies[track].vibration.amplitude': {'range': [1e-4, 5e-4], 'count': 300},
            'bodies[track].vibration.frequency': {'range': [30.0, 60.0], 'count': 300}}
    start = time.perf_counter()
    spec = parse_study({**TINY, 'parameters': grid})
    assert time.perf_counter() - start < 1.0 and spec.design_count() == 90_000


@pytest.mark.parametrize('change, path, fragment', [
    ({'duration': 1e12}, 'duration', 'steps of'),
    ({'perturb': {'position_m': 1e300}}, 'perturb.position_m', 'a spread of at most 0.1 m'),
    ({'perturb': {'angle_rad': 7.0}}, 'perturb.angle_rad', 'a spread of at most 3.14159'),
    ({'perturb': {'position_m': 0.01}}, 'perturb.position_m',
     "'box' and 'track' overlap by"),
], ids=['duration over the step limit', 'huge shift', 'angle', 'shift into the track'])
def test_what_a_study_varies_is_checked_at_its_extremes(change, path, fragment):
    start = time.perf_counter()
    with pytest.raises(StudyError) as err:
        parse_study({**TINY, **change})
    assert time.perf_counter() - start < 1.0
    assert err.value.path == path and fragment in err.value.message, str(err.value)
    assert '\n' not in str(err.value)


# --- failed trials, a full disk ------------------------------------------------------------

def test_a_study_with_failed_trials_exits_non_zero_with_the_first_reason(
        tmp_path, cluster, monkeypatch, capsys):
    # a spec edited past the checks: the metric fails every trial
    spec = dataclasses.replace(parse_study(TINY), metrics=('conveying_speed_mps',
                                                           'fraction:open_end_up'))
    monkeypatch.setattr('feeder_sim.studies.load_study', lambda path: spec)
    code = cli.main(['-q', 'study', 'study.yaml', '--out', str(tmp_path / 'out'),
                     '--scheduler', cluster])
    assert code == 1
    err = error_lines(capsys.readouterr().err)
    assert len(err) == 1 and err[0].startswith('feeder-sim: error: 2 of 2 trials failed; the '
                                               'first: design 0 repeat 0: ValueError: metric '
                                               'fraction:open_end_up'), err


def test_a_full_disk_names_the_file(tmp_path, monkeypatch):
    def full(*args, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(runner.os, 'replace', full)
    target = tmp_path / 'trials' / 'abc.json'
    target.parent.mkdir()
    with pytest.raises(OSError) as err:
        runner._write_json(target, {'x': 1})
    assert str(target) in str(err.value) and 'No space left on device' in str(err.value)
    assert 'free space there' in str(err.value)
    assert not list(target.parent.iterdir())             # no temporary file left behind
