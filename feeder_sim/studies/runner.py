"""Running a study's trials on Dask, storing each as it finishes, resuming what is missing.

Each trial's row is written to ``DIR/trials/<key>.json`` (atomically) the moment it comes
back, so a study stopped by Ctrl-C, a kill or a crash loses only the trials running then;
the same command computes only the trials without a file. The key is the design's values
and the repeat; a trial's seed derives from them, so 1 or N workers give the same rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
import json
import logging
import os
from pathlib import Path
import tempfile
import time
from typing import Any

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


def _write_json(path: Path, data: Any) -> None:
    # written whole, then renamed: a kill leaves the old file or the new one, never half
    # (no fsync: what the study must survive is its own end, not the machine's)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix='.', suffix='.tmp')
    with os.fdopen(fd, 'w') as f:
        json.dump(data, f, default=float)
    os.replace(tmp, path)


def stored(out: Path, folder: str = 'trials') -> dict[str, dict]:
    """The trials (or companions: ``folder``) already in ``out``, by key (unreadable files are
    computed again)."""
    rows = {}
    for path in sorted((out / folder).glob('*.json')):
        try:
            rows[path.stem] = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
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


def make_client(scheduler: str | None, workers: int | None):
    """A Dask client: on the scheduler at ``scheduler``, or on a LocalCluster of ``workers``
    single-threaded processes (default: one per core). The physics holds the GIL, so a trial
    needs a process of its own."""
    from dask.distributed import Client, LocalCluster
    # the cluster's own chatter (workers starting, connections) is not the study's progress
    logging.getLogger('distributed').setLevel(logging.WARNING)
    if scheduler:
        try:
            return Client(scheduler, timeout=f'{SCHEDULER_WAIT_S}s'), None
        except (OSError, TimeoutError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise OSError(f'--scheduler {scheduler}: no Dask scheduler answered within '
                          f'{SCHEDULER_WAIT_S} s ({reason}); start one there (dask '
                          'scheduler) or leave --scheduler out for a local cluster') from None
    n = workers or os.cpu_count() or 1
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=':0', silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run_trials(spec: StudySpec, out: Path, *, scheduler: str | None = None,
               workers: int | None = None,
               on_row: Callable[[dict], None] | None = None,
               timing: dict | None = None) -> dict[str, dict]:
    """Compute the trials missing from ``out`` on Dask; returns every row by key.
    ``timing`` receives ``ready_s``: wall time until the workers were up and warm."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    (out / 'trials').mkdir(parents=True, exist_ok=True)
    rows = stored(out)
    companions = {}
    if spec.convergence:
        (out / COMPANIONS).mkdir(exist_ok=True)
        companions = stored(out, COMPANIONS)
    # in the order of their keys (hashes): designs next to each other in the grid, which
    # often cost alike (the fast-hopping corner of a speed map), are spread over the study
    # instead of all coming last and leaving the other workers idle; a companion follows its
    # trial
    todo = sorted([(k, False, d, r) for k, d, r in all_trials(spec) if k not in rows]
                  + [(k, True, d, r) for k, d, r in all_trials(spec)
                     if spec.convergence and r == 0 and k not in companions])
    total = len(rows) + len(companions) + len(todo)
    if not todo:
        log.info('study: all %d trials already in %s', total, out)
        return rows
    record_dir = None
    if spec.record != 'none':
        record_dir = str((out / 'logs').resolve())
        os.makedirs(record_dir, exist_ok=True)
    start = time.perf_counter()
    client, cluster = make_client(scheduler, workers)
    try:
        client.run(_warm_worker, spec)
        if timing is not None:
            timing['ready_s'] = time.perf_counter() - start
        log.info('study: %d runs to do (%d stored) on %d Dask workers (%s)', len(todo),
                 len(rows) + len(companions), len(client.scheduler_info()['workers']),
                 client.scheduler.address)
        # A few trials in flight beyond one per worker, one handed out when one comes back.
        # Submitted all at once, they were split evenly up front and a worker whose trials
        # ran short sat idle at the end (2.5 s of 7 on 16 one-second trials). Exactly one
        # per worker left each worker idle for the round trip of a result to the client and
        # of the next trial back (5-7 % of a one-second trial on 2 workers). One spare trial,
        # and one more per 8 workers, waits where the next free worker takes it (1-2 % on 2
        # workers); two spares on 2 workers stranded work at the end again (7 %).
        pending = iter(todo)
        futures: dict = {}

        def submit_next() -> None:
            for k, extra, d, r in pending:
                futures[client.submit(_trial_task, spec, d, r, record_dir, extra,
                                      key=f"{COMPANIONS if extra else 'trial'}-{k}",
                                      pure=False)] = (k, extra)
                return

        in_flight = as_completed()
        n_workers = max(1, len(client.scheduler_info()['workers']))
        for _ in range(n_workers + 1 + n_workers // 8):
            submit_next()
        for future in list(futures):
            in_flight.add(future)
        with tqdm(total=total, initial=total - len(todo), unit='run', desc='study',
                  dynamic_ncols=True, mininterval=0.5) as bar:
            for future in in_flight:
                key, extra = futures.pop(future)
                before = set(futures)
                submit_next()
                for new in set(futures) - before:
                    in_flight.add(new)
                try:
                    row = future.result()
                except Exception as err:    # the worker died: recorded like a failed trial
                    row = {'status': 'error', 'error': f'{type(err).__name__}: {err}'}
                row['key'] = key
                _write_json(out / (COMPANIONS if extra else 'trials') / f'{key}.json', row)
                if not extra:
                    rows[key] = row
                bar.update(1)
                if on_row is not None:
                    on_row(row)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return rows


def ordered(spec: StudySpec, rows: dict[str, dict]) -> Iterator[dict]:
    """The rows in the study's order (designs, then repeats), with their design index."""
    for index, (key, design, repeat) in enumerate(all_trials(spec)):
        if key in rows:
            yield {'design': index // spec.repeats, **design, 'repeat': repeat,
                   **{k: v for k, v in rows[key].items() if k not in design}}

