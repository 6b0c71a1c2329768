"""One trial of a study: a design's scene, perturbed by the trial's seed, run and measured.

:func:`run_trial` is what a Dask worker executes; it takes and returns plain data and never
raises: a failure is a row with ``status: error`` and the error's text.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
import math
import time
import traceback
from typing import Any

import numpy as np

from feeder_sim.model.scene import Scene
from feeder_sim.output.numerical_error import companion, companion_scene
from feeder_sim.output.outcomes import classify
from feeder_sim.run import run
from feeder_sim.simulator import Simulator
from feeder_sim.studies.spec import scene_of_design, StudySpec


def perturbed(scene: Scene, perturb: Mapping[str, float], seed: int) -> Scene:
    """The scene with each part's initial position and angle moved uniformly within the
    bounds of ``perturb`` and each drive's phase drawn uniformly (``drive_phase``)."""
    if not perturb:
        return scene
    rng = np.random.default_rng(seed)
    dx, da = perturb.get('position_m', 0.0), perturb.get('angle_rad', 0.0)
    bodies = []
    for body in scene.bodies:
        if body.type == 'dynamic' and (dx or da):
            shift = np.array([*rng.uniform(-dx, dx, 2), rng.uniform(-da, da)])
            body = replace(body, pose=body.pose + shift)
        elif body.vibration is not None and perturb.get('drive_phase'):
            body = replace(body, vibration=replace(body.vibration,
                                                   phase=float(rng.uniform(0, 2 * math.pi))))
        bodies.append(body)
    return replace(scene, bodies=tuple(bodies))


def metrics_of(summary: Mapping[str, Any], names: tuple[str, ...],
               resting: list[str | None] = ()) -> dict[str, float]:
    """The study's metrics from a run summary (``feeder_sim.run.summary`` with outcomes) and
    the named orientation each part lies in at the end (``resting``)."""
    parts = summary['parts']
    outcomes = summary['outcomes']
    fed = outcomes['parts_exited']
    out = {}
    for name in names:
        if name == 'conveying_speed_mps':
            value = float(np.mean([p['mean_velocity_along_track_mps'] for p in parts]))
        elif name == 'final_position_m':
            value = float(np.mean([p['final_position_along_track_m'] for p in parts]))
        elif name == 'parts_fed':
            value = float(fed)
        elif name == 'feed_rate_per_min':
            value = float(outcomes['feed_rate_parts_per_min'])
        elif name == 'feed_rate_steady_per_min':
            steady = outcomes['feed_rate_steady_parts_per_min']
            value = math.nan if steady is None else float(steady)
        elif name == 'jams':
            value = float(outcomes['jams'])
        elif name == 'recirculated':
            value = float(outcomes.get('recirculated', 0))
        elif name == 'jammed':
            value = float(outcomes['jams'] > 0)
        elif name.startswith('rest:'):
            wanted = name.split(':', 1)[1]
            if not any(resting) and wanted:
                raise ValueError(f'metric {name}: the scene names no orientations '
                                 '(outcomes.orientations)')
            value = sum(r == wanted for r in resting) / len(resting)
        else:                                   # fraction:<orientation>
            wanted = name.split(':', 1)[1]
            counts = outcomes['exit_orientations']
            if wanted not in counts:
                raise ValueError(f'metric {name}: the scene names no orientation {wanted!r} '
                                 f'(it names: {", ".join(counts) or "none"})')
            value = counts[wanted] / fed if fed else math.nan
        out[name] = value
    return out


def run_trial(spec: StudySpec, design: Mapping[str, float], repeat: int,
              record_path: str | None = None, *, companion_run: bool = False
              ) -> dict[str, Any]:
    """Run one trial; a row of the results table (parameters, seed, metrics, status).

    ``companion_run``: the trial's companion for its numerical error instead (the same start
    at the refined setting of :mod:`feeder_sim.output.numerical_error`, as ``feeder-sim run
    --error-estimate`` takes it); its row holds the rule that turns the difference into an
    error (``numerical_error``)."""
    seed = spec.trial_seed(design, repeat)
    row: dict[str, Any] = {**design, 'repeat': repeat, 'seed': seed}
    start = time.perf_counter()
    try:
        scene = perturbed(scene_of_design(spec, design), spec.perturb, seed)
        if companion_run:
            # from the setting the trial itself runs at: a method override's step or an auto
            # step as the trial's Simulator resolves it
            if spec.method not in (None, scene.solver.method) or scene.solver.time_step_auto:
                scene = Simulator(scene, method=spec.method).scene
            comp = companion(scene.solver)
            row['numerical_error'] = comp.rule()
            sim = Simulator(companion_scene(scene, comp))
        else:
            sim = Simulator(scene, method=spec.method)
        result = run(sim, spec.duration_s, publish_rate_hz=spec.publish_rate_hz,
                     record=record_path, progress_every_s=math.inf)
        resting = [classify(float(a) - sim.world.track_angle, sim.scene.outcomes)
                   for a in sim.state.angle[sim.part_indices]]
        row.update(metrics_of(result.summary, spec.metrics, resting))
        row['parts_fed_count'] = result.summary['outcomes']['parts_exited']
        row['parts_count'] = len(resting)
        row['status'] = 'ok'
        row['error'] = ''
        row['jams_at'] = [[p['jam_time_s'], *(p['jam_position_m'] or [])]
                          for p in result.summary['outcomes']['parts'] if p['jam_time_s']]
    except Exception as err:     # a failed trial is a result too: recorded, the study goes on
        row.update(dict.fromkeys(spec.metrics, math.nan))
        row['status'] = 'error'
        row['error'] = f'{type(err).__name__}: {err}'
        row['traceback'] = traceback.format_exc(limit=6)
    row['wall_s'] = time.perf_counter() - start
    return row
