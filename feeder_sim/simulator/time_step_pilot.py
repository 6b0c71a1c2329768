"""``time_step: auto``: the time_stepping step a pilot run of the scene picks."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
import logging
import math
import time
from typing import TYPE_CHECKING

import numpy as np

from feeder_sim.model.scene import MIN_TIME_STEP_S, Scene, SceneError, STEP_RULES

if TYPE_CHECKING:
    from feeder_sim.simulator.simulator import Simulator

log = logging.getLogger('feeder_sim')

# time_step: auto (model/scene/parse.py): each candidate step and its half run a pilot of the
# scene; the conveying speed is measured over AUTO_MEASURE_PERIODS drive periods after
# AUTO_WARMUP_PERIODS (the parts' start-up is not what the step must resolve, and a part that
# slides back and forth without sticking builds its step's error up over some ten periods:
# after 5, three steps agreed to 0.3 % on a speed 6.8 % off in its steady state), and at most
# AUTO_MAX_HALVINGS halvings are tried (from 50 to 12 800 steps per period)
AUTO_WARMUP_PERIODS = 20
AUTO_MEASURE_PERIODS = 10
AUTO_MAX_HALVINGS = 8
# below this share of the drive's peak speed a conveying speed counts as standing still: the
# error is then relative to it (a part that sticks has no speed to be 1 % of)
AUTO_SPEED_FLOOR = 0.01


def auto_time_step(scene: Scene, simulator: Callable[[Scene], Simulator]
                   ) -> tuple[Scene, dict]:
    """``solver.time_step: auto``: the scene with the largest step of the halving ladder from
    its first candidate whose conveying speed (the mean along-track speed of the parts present
    at the start, over a short pilot) has a Richardson estimate of its relative error within
    ``solver.tolerance`` over two halvings (time_stepping is first order: error(h) ~
    2 |v(h/2) - v(h)| ~ 4 |v(h/4) - v(h/2)|, the larger taken); and what the pilot found and
    cost."""
    solver = scene.solver
    drives = [b.vibration for b in scene.bodies
              if b.vibration is not None and b.vibration.frequency > 0.0]
    period = 1.0 / max(d.frequency for d in drives)
    floor = AUTO_SPEED_FLOOR * max(d.amplitude * 2.0 * math.pi * d.frequency for d in drives)
    warm, end = AUTO_WARMUP_PERIODS * period, (AUTO_WARMUP_PERIODS + AUTO_MEASURE_PERIODS) * period
    wall0 = time.perf_counter()
    candidates: list[dict] = []

    def speed(h: float) -> float:
        sim = simulator(replace(scene, solver=replace(solver, time_step=h, time_step_auto=False)))
        sim.advance_to(warm)
        before = dict(zip(sim.part_poses()[0], sim.track_coordinates()[0]))
        sim.advance_to(end)
        after = dict(zip(sim.part_poses()[0], sim.track_coordinates()[0]))
        # by name: parts that a source adds or a sink takes on the way are not measured
        moved = [after[n] - before[n] for n in before if n in after]
        if not moved:
            raise SceneError('auto measures the conveying speed of the parts on the track, '
                             f'and no part is there from t = {warm:g} to {end:g} s: give a step '
                             'in s', 'solver.time_step', scene.source)
        v = float(np.mean(moved)) / (end - warm)
        candidates.append({'time_step_s': h, 'conveying_speed_mps': v})
        return v

    # A step is taken when two halvings agree that it is within the tolerance: its own
    # difference to its half, 2 |v(h) - v(h/2)|, and the next one's scaled to it,
    # 4 |v(h/2) - v(h/4)|. One halving alone can agree by chance while the error still
    # changes sign with the step (near lift-off at Gamma 0.95: an estimate of 0.02 % at 100
    # steps per period that was 1.2 % off).
    h, chosen, error = solver.time_step, None, math.nan
    diff, scale = math.nan, 1.0
    speeds = [speed(h)]
    for _ in range(AUTO_MAX_HALVINGS):
        if h / 4 < MIN_TIME_STEP_S:
            break
        while len(speeds) < 3:
            speeds.append(speed(h / 2 ** len(speeds)))
        v_h, v_half, v_quarter = speeds
        diff, scale = abs(v_half - v_h), max(abs(v_quarter), floor)
        estimate = max(2.0 * diff, 4.0 * abs(v_quarter - v_half))
        if estimate <= solver.tolerance * scale:
            chosen, error = h, estimate / scale
            break
        h = h / 2
        speeds = speeds[1:]
    met = chosen is not None
    if not met:
        chosen = candidates[-1]['time_step_s']
        log.warning('%s: time_step auto: no step down to %g s keeps the conveying speed within '
                    '%g (the last halving changed it by %.3g %%); using %g s', scene.name,
                    chosen, solver.tolerance, 100.0 * diff / scale, chosen)
    wall = time.perf_counter() - wall0
    steps = sum((end / c['time_step_s']) for c in candidates)
    report = {'time_step_s': chosen, 'steps_per_period': period / chosen,
              'tolerance': solver.tolerance, 'met': met,
              'estimated_relative_error': error,
              'fixed_steps_per_period': STEP_RULES['time_stepping'].steps_per_period,
              'pilot': {'simulated_s_each': end, 'candidates': candidates,
                        'steps': int(round(steps)), 'wall_s': wall}}
    log.info('%s: time_step auto: %g s (%.0f steps per drive period, fixed: %g), conveying '
             'speed within %.2g %% by the pilot: %d runs of %g s, %d steps, %.2f s wall',
             scene.name, chosen, period / chosen, report['fixed_steps_per_period'], 100.0 * error,
             len(candidates), end, steps, wall)
    return replace(scene, solver=replace(solver, time_step=chosen, time_step_auto=False)), report
