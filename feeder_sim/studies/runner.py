"""Running a study's trials on Dask, storing each as it finishes, resuming what is missing.

Each trial's row is written to ``DIR/trials/<key>.json`` (atomically) the moment it comes
back, so a study stopped by Ctrl-C, a kill or a crash loses only the trials running then;
the same command computes only the trials without a file. The key is the design's values
and the repeat; a trial's seed derives from them, so 1 or N workers give the same rows.

A directory belongs to one spec: ``DIR/spec.json`` holds what a trial's numbers depend on
beyond its key (the scene's data, duration, seed, perturbation, publish rate, method and
feeder_sim's version) and each row carries its hash. A run whose spec differs names what
changed and refuses (:class:`SpecChanged`) unless told to recompute; a stored trial that
lacks a metric the study now asks for is run again. Parameters and repeats are not part of
it: they only decide which keys exist, so a grid extended by a value reuses every trial
that was already computed for it.

Cancelled or lost trials are not results: nothing is stored for them and the next run
computes them. A scheduler that stops answering ends the study within seconds
(:class:`SchedulerLost`), everything finished kept.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import errno
import hashlib
import json
import logging
import os
from pathlib import Path
import socket
import struct
import tempfile
import threading
import time
from typing import Any
from urllib.parse import urlsplit

from feeder_sim import __version__
from feeder_sim.studies.spec import StudySpec
from feeder_sim.studies.trial import run_trial

log = logging.getLogger('feeder_sim')


def trial_key(spec: StudySpec, design: dict[str, float], repeat: int) -> str:
    return f'{spec.trial_seed(design, repeat):016x}'


# the companions of ``convergence: true`` (a design's first trial at the refined setting),
# stored beside the trials under the key of the trial they go with
COMPANIONS = 'convergence'


def all_trials(spec: StudySpec) -> list[tuple[str, dict[str, float], int]]:
    """(key, design, repeat) of every trial, designs in order, repeats within each."""
    return [(trial_key(spec, d, r), d, r) for d in spec.designs() for r in range(spec.repeats)]


class SpecChanged(ValueError):
    """The study directory holds trials of another spec; the message names what changed."""


class SchedulerLost(OSError):
    """The scheduler stopped answering mid-study (what had finished is stored)."""


SPEC_FILE = 'spec.json'


def trial_spec(spec: StudySpec) -> dict[str, Any]:
    """What a trial's numbers depend on beyond its key (design, repeat): two runs with equal
    trial specs give equal rows."""
    scene = json.dumps(spec.scene_data, sort_keys=True, default=str)
    return {'scene': hashlib.sha256(scene.encode()).hexdigest()[:16],
            'duration_s': spec.duration_s, 'seed': spec.seed,
            'perturb': {k: float(v) for k, v in sorted(spec.perturb.items())},
            'publish_rate_hz': spec.publish_rate_hz, 'method': spec.method,
            'feeder_sim': __version__}


def fingerprint(spec: StudySpec) -> str:
    return hashlib.sha256(json.dumps(trial_spec(spec), sort_keys=True).encode()
                          ).hexdigest()[:16]


_UNITS = {'duration_s': ('duration', ' s'), 'publish_rate_hz': ('publish_rate', ' Hz')}


def describe_changes(old: dict[str, Any], new: dict[str, Any]) -> str:
    """``duration 0.2 -> 2 s, feeder_sim 0.1.0 -> 0.2.0``: what differs, in the study file's
    words."""
    changes = []
    for key in new:
        if old.get(key) == new[key]:
            continue
        if key == 'scene':
            changes.append("the scene's data")
        elif key == 'perturb':
            before, after = old.get(key) or {}, new[key]
            for name in sorted(set(before) | set(after)):
                if before.get(name) != after.get(name):
                    changes.append(f'perturb.{name} {before.get(name, "none")} -> '
                                   f'{after.get(name, "none")}')
        else:
            name, unit = _UNITS.get(key, (key, ''))
            changes.append(f'{name} {old.get(key, "none")} -> {new[key]}{unit}')
    return ', '.join(changes)


def check_directory(spec: StudySpec, out: Path, recompute: bool = False) -> None:
    """Make ``out`` the directory of ``spec``: a new one gets its spec file; one of another
    spec is refused in a line naming what changed (SpecChanged), or with ``recompute`` its
    trials are deleted so that every one is computed again."""
    path = out / SPEC_FILE
    current = trial_spec(spec)
    old_files = [p for folder in ('trials', COMPANIONS) for p in (out / folder).glob('*.json')]
    try:
        before = json.loads(path.read_text())['trial_spec']
        if not isinstance(before, dict):
            raise ValueError
    except FileNotFoundError:
        before = None if old_files else current
    except (OSError, ValueError, KeyError, TypeError):
        before = None
    if before != current:
        what = ('no record of the spec they were computed for' if before is None
                else describe_changes(before, current))
        if not recompute:
            raise SpecChanged(f'{out} holds {len(old_files)} trials of another spec ({what}): '
                              'run with --recompute to compute them again, or give another '
                              '--out')
        log.info('study: %s: %s; computing all %d stored trials again', out, what,
                 len(old_files))
        for p in [*old_files, *(out / 'logs').glob('*.mcap')]:
            p.unlink(missing_ok=True)
    if before != current or not path.exists():
        _write_json(path, {'trial_spec': current, 'fingerprint': fingerprint(spec)})


def _write_json(path: Path, data: Any) -> None:
    # written whole, then renamed: a kill leaves the old file or the new one, never half
    # (no fsync: what the study must survive is its own end, not the machine's)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix='.', suffix='.tmp')
        with os.fdopen(fd, 'w') as f:
            json.dump(data, f, default=float)
        os.replace(tmp, path)
    except OSError as err:
        # a write's error names no file ([Errno 28] alone): say which and what is kept
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        raise OSError(err.errno, f'cannot write {path}: {err.strerror or err}'
                      + ('; free space there and run the same command again (what is '
                         'stored is kept)' if err.errno in (errno.ENOSPC, errno.EDQUOT)
                         else '')) from None


# the error of a trial the cluster lost or cancelled (an older study stored them as rows):
# not a result, computed again
_NOT_RESULTS = ('FutureCancelledError', 'CancelledError', 'CommClosedError',
                'StreamClosedError')


def stored(out: Path, folder: str = 'trials', spec: StudySpec | None = None
           ) -> dict[str, dict]:
    """The trials (or companions: ``folder``) already in ``out``, by key. Unreadable files,
    rows of a cluster's failure and, given ``spec``, rows of another spec are left out: they
    are computed again."""
    rows = {}
    mark = None if spec is None else fingerprint(spec)
    for path in sorted((out / folder).glob('*.json')):
        try:
            row = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(row, dict):
            continue
        if row.get('status') == 'error' and str(row.get('error', '')).startswith(_NOT_RESULTS):
            continue
        if mark is not None and row.get('spec') != mark:
            continue
        rows[path.stem] = row
    return rows


def _trial_task(spec: StudySpec, design: dict, repeat: int, record_dir: str | None,
                companion_run: bool = False) -> dict:
    """What a worker runs: the trial, with its MCAP log when the study keeps logs (or the
    companion of a design's first trial, without)."""
    if companion_run:
        return run_trial(spec, design, repeat, companion_run=True)
    record = None
    if record_dir is not None:
        record = str(Path(record_dir) / f'{trial_key(spec, design, repeat)}.mcap')
    row = run_trial(spec, design, repeat, record)
    if record is not None:
        keep = spec.record == 'all' or (spec.record == 'jammed' and row.get('jams_at'))
        if not keep and os.path.exists(record):
            os.remove(record)
        row['log'] = record if keep else ''
    return row


def _warm_worker(spec: StudySpec) -> None:
    """Import the physics and load the compiled kernels the study's scene needs, once per
    worker, before the first trial is timed (a second or two; from the kernel cache)."""
    from feeder_sim.simulator import Simulator
    from feeder_sim.studies.spec import scene_of_design
    sim = Simulator(scene_of_design(spec, spec.designs()[0]), method=spec.method)
    sim.advance_by(min(spec.duration_s, 0.01))


# How long a study waits for the scheduler it is given to answer (s).
SCHEDULER_WAIT_S = 10
# How long a scheduler may take to greet a new connection (a Dask scheduler does at once): the
# probe that tells a scheduler from anything else listening there (an HTTP server, a silent
# socket) before Dask reads what it sends.
PROBE_S = 4.0
# A Dask greeting is tens of bytes; a first frame announcing more is not from a scheduler
# (Dask would allocate whatever is announced: 'HTTP/1.0' read as a length is 3.5 EB).
MAX_GREETING_BYTES = 1 << 16
# How long the client may be without its scheduler before the study ends (s): long enough
# for a blip of the network, short enough not to sit for minutes.
LOST_AFTER_S = 5.0
SCHEMES = ('tcp', 'tls')


def _scheduler_error(address: str, reason: str) -> OSError:
    return OSError(f'--scheduler {address}: {reason}; start a Dask scheduler there (dask '
                   'scheduler) or leave --scheduler out for a local cluster')


def check_address(address: str) -> tuple[str, str, int]:
    """(scheme, host, port) of a scheduler address (tcp://HOST:PORT, tls://HOST:PORT or
    HOST:PORT); OSError in one line for anything else."""
    text = address if '://' in address else f'tcp://{address}'
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        port, parts = None, None
    if parts is None or parts.scheme not in SCHEMES or not parts.hostname or port is None \
            or parts.path not in ('', '/'):
        if text.startswith('inproc://'):
            raise OSError(f'--scheduler {address}: an in-process address is reachable only '
                          'inside the process that made it; give tcp://HOST:PORT of a running '
                          'scheduler, or leave --scheduler out for a local cluster')
        raise OSError(f'--scheduler {address}: expected tcp://HOST:PORT or tls://HOST:PORT '
                      '(e.g. tcp://127.0.0.1:8786)')
    return parts.scheme, parts.hostname, port


def probe_scheduler(address: str, wait_s: float = PROBE_S) -> None:
    """Connect to ``address`` and read its greeting within ``wait_s``: OSError in one line
    when nothing answers there, or something that is not a Dask scheduler (silent, HTTP,
    a frame of absurd size, bytes that do not decode to Dask's handshake)."""
    scheme, host, port = check_address(address)
    if scheme != 'tcp':
        return                           # TLS: the client's own timeout bounds it
    deadline = time.monotonic() + wait_s
    try:
        sock = socket.create_connection((host, port), timeout=wait_s)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        if isinstance(err, TimeoutError) or isinstance(err, socket.timeout):
            reason = f'no connection within {wait_s:g} s'
        raise _scheduler_error(address, f'no Dask scheduler answered ({reason})') from None
    data = b''
    try:
        with sock:
            need = 8
            while len(data) < need:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                sock.settimeout(left)
                chunk = sock.recv(min(65536, need - len(data)))
                if not chunk:
                    raise ConnectionResetError
                data += chunk
                if need == 8 and len(data) >= 8:
                    (size,) = struct.unpack('<Q', data[:8])
                    if not 0 < size <= MAX_GREETING_BYTES:
                        raise ValueError(size)
                    need = 8 + size
    except TimeoutError:
        raise _scheduler_error(address, 'something accepted the connection but sent nothing '
                               f'within {wait_s:g} s (a Dask scheduler greets at once: an '
                               'HTTP server or another service is listening there)') from None
    except ValueError:
        what = 'an HTTP server' if data.startswith(b'HTTP') else 'not a Dask scheduler'
        raise _scheduler_error(address, f'what answers is {what} (its first bytes '
                               f'{data[:8]!r})') from None
    except OSError as err:
        raise _scheduler_error(address, 'the connection was closed before a greeting '
                               f'({err.strerror or type(err).__name__})') from None
    try:
        from distributed.protocol import loads
        from distributed.protocol.utils import unpack_frames
        frames, rest = unpack_frames(memoryview(data[8:]), partial=True)
        greeting = loads(frames) if not rest else None
    except Exception:          # anything the bytes make the decoder raise: not a greeting
        greeting = None
    if not (isinstance(greeting, dict) and 'pickle-protocol' in greeting):
        raise _scheduler_error(address, 'what answers is not a Dask scheduler (its greeting '
                               'does not decode as one)')


def make_client(scheduler: str | None, workers: int | None):
    """A Dask client: on the scheduler at ``scheduler``, or on a LocalCluster of ``workers``
    single-threaded processes (default: one per core). The physics holds the GIL, so a trial
    needs a process of its own."""
    from dask.distributed import Client, LocalCluster
    # the cluster's own chatter (workers starting, connections) is not the study's progress;
    # a lost scheduler is reported by the study in one line, not by the client's reconnects
    logging.getLogger('distributed').setLevel(logging.WARNING)
    for name in ('distributed.client', 'distributed.comm', 'distributed.core',
                 'distributed.batched'):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if scheduler:
        probe_scheduler(scheduler)
        try:
            return Client(scheduler, timeout=f'{SCHEDULER_WAIT_S}s'), None
        except Exception as err:     # whatever a failed connection raises, one line
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise _scheduler_error(scheduler, f'no Dask scheduler answered within '
                                   f'{SCHEDULER_WAIT_S} s ({reason})') from None
    n = workers or os.cpu_count() or 1
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=':0', silence_logs=logging.ERROR)
    return Client(cluster), cluster


def _close(client, cluster, lost: bool) -> None:
    if not lost:
        client.close()
        if cluster is not None:
            cluster.close()
        return
    # a client without its scheduler can wait out its reconnect timeout while closing: done
    # in the background, the study's end not held up by it
    closer = threading.Thread(target=client.close, kwargs={'timeout': 2}, daemon=True)
    closer.start()
    closer.join(3)


def _while_saying(work: Callable[[], Any], line: Callable[[float], str],
                  every_s: float = 5.0) -> Any:
    """``work()``, with ``line(seconds so far)`` logged every ``every_s`` while it runs."""
    done = threading.Event()
    start = time.perf_counter()

    def say() -> None:
        while not done.wait(every_s):
            log.info(line(time.perf_counter() - start))

    threading.Thread(target=say, daemon=True).start()
    try:
        return work()
    finally:
        done.set()


def run_trials(spec: StudySpec, out: Path, *, scheduler: str | None = None,
               workers: int | None = None,
               on_row: Callable[[dict], None] | None = None,
               timing: dict | None = None, recompute: bool = False) -> dict[str, dict]:
    """Compute the trials missing from ``out`` on Dask; returns every row by key.
    ``timing`` receives ``ready_s``: wall time until the workers were up and warm.
    ``recompute``: a directory of another spec has its trials computed again instead of
    being refused (SpecChanged)."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    (out / 'trials').mkdir(parents=True, exist_ok=True)
    if spec.convergence:
        (out / COMPANIONS).mkdir(exist_ok=True)
    check_directory(spec, out, recompute)
    mark = fingerprint(spec)
    rows = stored(out, spec=spec)
    companions = stored(out, COMPANIONS, spec) if spec.convergence else {}
    # a metric added to the study: the trials stored without it are run again
    lacking = sorted({m for r in [*rows.values(), *companions.values()] for m in spec.metrics
                      if m not in r})
    if lacking:
        stale = [k for k, r in rows.items() if any(m not in r for m in spec.metrics)]
        log.info('study: %d stored trials lack %s: computing them again', len(stale),
                 ', '.join(lacking))
        rows = {k: r for k, r in rows.items() if all(m in r for m in spec.metrics)}
        companions = {k: r for k, r in companions.items()
                      if all(m in r for m in spec.metrics)}
    # in the order of their keys (hashes): designs next to each other in the grid, which
    # often cost alike (the fast-hopping corner of a speed map), are spread over the study
    # instead of all coming last and leaving the other workers idle; a companion follows its
    # trial
    trials = all_trials(spec)
    todo = sorted([(k, False, d, r) for k, d, r in trials if k not in rows]
                  + [(k, True, d, r) for k, d, r in trials
                     if spec.convergence and r == 0 and k not in companions])
    wanted = {k for k, _, _ in trials}
    total = len(wanted & set(rows)) + len(wanted & set(companions)) + len(todo)
    if not todo:
        log.info('study: all %d trials already in %s', total, out)
        return rows
    record_dir = None
    if spec.record != 'none':
        record_dir = str((out / 'logs').resolve())
        os.makedirs(record_dir, exist_ok=True)
    start = time.perf_counter()
    log.info('study: %d runs to do (%d stored); %s', len(todo), total - len(todo),
             f'connecting to {scheduler}' if scheduler else 'starting a local Dask cluster')
    client, cluster = make_client(scheduler, workers)
    lost = False
    try:
        log.info('study: %d Dask workers up after %.1f s; loading the kernels on them (a cold '
                 'cache compiles them: a minute or more)',
                 len(client.scheduler_info()['workers']), time.perf_counter() - start)
        _while_saying(lambda: client.run(_warm_worker, spec),
                      lambda s: f'study: still loading the kernels on the workers, {s:.0f} s')
        if timing is not None:
            timing['ready_s'] = time.perf_counter() - start
        log.info('study: running on %d Dask workers (%s), ready after %.1f s',
                 len(client.scheduler_info()['workers']), client.scheduler.address,
                 time.perf_counter() - start)
        # A few trials in flight beyond one per worker, one handed out when one comes back.
        # Submitted all at once, they would be split evenly up front, and a worker whose
        # trials ran short would sit idle at the end. With exactly one per worker, each
        # worker would sit idle for the round trip of a result to the client and of the next
        # trial back. One spare trial, and one more per 8 workers, waits where the next free
        # worker takes it; more spares strand work at the end again (two on 2 workers do).
        # benchmarks/study.py measures the overhead per trial that is left.
        pending = iter(todo)
        futures: dict = {}
        in_flight = as_completed()

        def submit(k: str, extra: bool, d: dict, r: int) -> None:
            future = client.submit(_trial_task, spec, d, r, record_dir, extra,
                                   key=f"{COMPANIONS if extra else 'trial'}-{k}", pure=False)
            futures[future] = (k, extra, d, r)
            in_flight.add(future)

        def submit_next() -> None:
            for item in pending:
                submit(*item)
                return

        n_workers = max(1, len(client.scheduler_info()['workers']))
        for _ in range(n_workers + 1 + n_workers // 8):
            submit_next()
        done = total - len(todo)
        retries: dict[str, int] = {}
        dropped = 0
        away_since = None
        with tqdm(total=total, initial=done, unit='run', desc='study',
                  dynamic_ncols=True, mininterval=0.5) as bar:
            while futures:
                if not in_flight.has_ready():
                    # the client reconnects on its own for a while; a study waits LOST_AFTER_S
                    if client.status != 'running':
                        away_since = away_since or time.monotonic()
                        if time.monotonic() - away_since > LOST_AFTER_S:
                            lost = True
                            raise SchedulerLost(
                                f'the Dask scheduler at {client.scheduler.address} stopped '
                                f'answering; {done} of {total} runs are stored in {out}: run '
                                'the same command again to compute the rest')
                    else:
                        away_since = None
                    time.sleep(0.05)
                    continue
                future = next(in_flight)
                key, extra, d, r = futures.pop(future)
                try:
                    row = future.result()
                except Exception as err:
                    if future.status == 'cancelled' or client.status != 'running' \
                            or type(err).__name__ in _NOT_RESULTS:
                        # lost with its worker or the scheduler: not a result; tried again
                        # while the cluster is there, else left for the next run
                        if client.status == 'running' and retries.get(key, 0) < 2:
                            retries[key] = retries.get(key, 0) + 1
                            submit(key, extra, d, r)
                        else:
                            dropped += 1
                            submit_next()
                        continue
                    # the trial killed its workers (Dask gave up on it): its result
                    row = {**d, 'repeat': r, 'status': 'error',
                           'error': f'{type(err).__name__}: {err}'}
                submit_next()
                row['key'] = key
                row['spec'] = mark
                _write_json(out / (COMPANIONS if extra else 'trials') / f'{key}.json', row)
                if not extra:
                    rows[key] = row
                done += 1
                bar.update(1)
                if on_row is not None:
                    on_row(row)
        if dropped:
            raise OSError(f'{dropped} runs were cancelled or lost by the cluster and are not '
                          f'stored ({done} of {total} are, in {out}): run the same command '
                          'again to compute them')
    finally:
        _close(client, cluster, lost)
    return rows


def ordered(spec: StudySpec, rows: dict[str, dict]) -> Iterator[dict]:
    """The rows in the study's order (designs, then repeats), with their design index."""
    for index, (key, design, repeat) in enumerate(all_trials(spec)):
        if key in rows:
            yield {'design': index // spec.repeats, **design, 'repeat': repeat,
                   **{k: v for k, v in rows[key].items() if k not in design}}

