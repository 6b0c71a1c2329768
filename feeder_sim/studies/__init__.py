"""Design studies: a scene's designs run as many seeded trials on Dask, with statistics.

>>> summary = run_study('config/studies/track_speed_map.yaml', 'out/speed_map')

:mod:`.spec` reads and checks a study file and makes its designs, :mod:`.trial` runs one
trial (on a worker), :mod:`.runner` schedules the missing trials and stores each as it
finishes, :mod:`.summary` writes the table, the per-design statistics and the plots.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
import time

from feeder_sim.studies.runner import COMPANIONS, ordered, run_trials, stored
from feeder_sim.studies.spec import load_study, parse_study, StudyError, StudySpec
from feeder_sim.studies.summary import attach_numerical_errors, plot, write_summary, write_table

log = logging.getLogger('feeder_sim')

__all__ = ['StudyError', 'StudySpec', 'load_study', 'parse_study', 'run_study']


def run_study(study: str | os.PathLike | StudySpec, out: str | os.PathLike, *,
              scheduler: str | None = None, workers: int | None = None,
              plots: bool = True, recompute: bool = False) -> dict:
    """Run (or complete) a study into ``out``; returns what ``study.json`` holds.
    ``recompute``: ``out`` holding trials of another spec has them computed again (else
    SpecChanged names what changed)."""
    if not isinstance(study, StudySpec):
        log.info('study: reading %s and checking its scene at each parameter\'s values', study)
    spec = study if isinstance(study, StudySpec) else load_study(study)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows = run_trials(spec, out, scheduler=scheduler, workers=workers, recompute=recompute)
    wall = time.perf_counter() - start
    table = list(ordered(spec, rows))
    try:
        convergence = None
        if spec.convergence:
            convergence = attach_numerical_errors(spec, table,
                                                  stored(out, COMPANIONS, spec))
        write_table(spec, table, out)
        summary = write_summary(spec, table, out, wall, workers or 0, convergence)
        if plots:
            summary['plots'] = [str(p) for p in plot(spec, summary, table, out)]
    except OSError as err:
        if err.filename is not None:
            raise
        # a write's error names no file ([Errno 28] alone): say where, and what is kept
        raise OSError(err.errno, f'cannot write the results into {out}: {err.strerror or err}; '
                      'the trials are stored: free space and run the same command again'
                      ) from None
    failed = summary['failed']
    log.info('study: %d trials (%d failed) in %s: results.csv, results.parquet, study.json%s',
             len(table), failed, out, ', plots' if plots else '')
    return summary
