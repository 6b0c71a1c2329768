"""Run a scene for a duration: record MCAP, write a summary and a plot, show progress.

This is what ``feeder-sim run`` does; the ROS node publishes the same frames live.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
import json
import logging
import math
import os
from pathlib import Path
import time

import numpy as np

from feeder_sim.output import frames
from feeder_sim.output.frames import Frame, open_recorder, record_frame
from feeder_sim.output.numerical_error import companion, companion_scene, summary_errors
from feeder_sim.output.outcomes import OutcomeTracker
from feeder_sim.simulator import MAX_PUBLISH_RATE_HZ, Simulator

log = logging.getLogger('feeder_sim')


@dataclass
class Trajectory:
    """Per-frame samples of the parts, kept for the summary and the plot. Parts that come
    and go (sources, sinks) are followed by name: ``names`` lists every part seen, in order
    of appearance, and a part's columns are NaN in the frames it was not there."""

    names: tuple[str, ...]
    t: list = field(default_factory=list)
    s: list = field(default_factory=list)        # along-track position per part, m
    speed: list = field(default_factory=list)    # along-track speed per part, m/s
    frame_names: list = field(default_factory=list)

    def add(self, t: float, names: tuple[str, ...], s: np.ndarray, speed: np.ndarray) -> None:
        if not self.frame_names or names != self.frame_names[-1]:
            seen = set(self.names)
            self.names += tuple(n for n in names if n not in seen)
        self.t.append(t), self.s.append(s), self.speed.append(speed)
        self.frame_names.append(names)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        column = {name: k for k, name in enumerate(self.names)}
        s = np.full((len(self.t), len(self.names)), np.nan)
        v = np.full_like(s, np.nan)
        for i, (names, si, vi) in enumerate(zip(self.frame_names, self.s, self.speed)):
            cols = [column[n] for n in names]
            s[i, cols], v[i, cols] = si, vi
        return np.asarray(self.t), s, v


@dataclass
class RunResult:
    summary: dict
    trajectory: Trajectory


def run(sim: Simulator, duration_s: float, *, publish_rate_hz: float = 100.0,
        record: str | os.PathLike | None = None,
        on_frame: Callable[[Simulator], None] | None = None,
        progress_every_s: float = 5.0, log_time: str = 'wall',
        stop_reason: Callable[[], str | None] | None = None) -> RunResult:
    """Advance ``sim`` by ``duration_s`` of simulated time; returns the summary and samples.

    Frames are taken every 1/``publish_rate_hz`` s of simulated time; each frame is recorded
    when ``record`` names an MCAP file. A log line reports progress every
    ``progress_every_s`` of wall time. ``log_time``: see ``frames.open_recorder``. After
    each frame ``stop_reason`` (if given) may end the run early: the log is finalized as at
    the end, and the summary covers the time simulated and says why it stopped
    (``stopped``).
    """
    sim.check_duration(duration_s)
    if not (0 < publish_rate_hz <= MAX_PUBLISH_RATE_HZ):
        raise ValueError(f'publish rate must be a number of Hz in (0, {MAX_PUBLISH_RATE_HZ:g}], '
                         f'got {publish_rate_hz!r}')
    recorder = open_recorder(sim, record, log_time) if record is not None else None
    names = sim.part_poses()[0]
    traj = Trajectory(names)
    outcomes = OutcomeTracker(names, sim.scene.outcomes)
    sensors = frames.sensor_bank(sim)
    frames.read_sensors(sim, sensors)   # where the parts start: a pass in frame 1 counts
    t0 = sim.t
    period = 1.0 / publish_rate_hz
    # the last frame may be shorter: the run ends at exactly duration_s
    n_frames = max(1, math.ceil(duration_s / period - 1e-9))
    wall0 = time.perf_counter()
    last_report = wall0
    s, v = sim.track_coordinates()
    traj.add(sim.t, names, s, v)
    stopped = None
    try:
        for k in range(1, n_frames + 1):
            sim.advance_to(t0 + min(k * period, duration_s))
            frame = Frame.take(sim, sensors)
            traj.add(sim.t, frame.names, frame.s, frame.speed)
            outcomes.update(sim.t, *sim.exit_progress(), frame.angle - sim.world.track_angle,
                            frame.names)
            if recorder is not None:
                record_frame(recorder, frame)
            if on_frame is not None:
                on_frame(sim)
            now = time.perf_counter()
            if now - last_report >= progress_every_s:
                last_report = now
                log.info('t = %.3f / %.3f s simulated (%.0f%%), %.1f s wall',
                         sim.t - t0, duration_s, 100 * k / n_frames, now - wall0)
            stopped = stop_reason() if stop_reason is not None else None
            if stopped is not None and k < n_frames:
                break
            stopped = None
        if recorder is not None:
            recorder.write_metadata('outcomes', {'json': json.dumps(outcomes.summary())})
    finally:
        if recorder is not None:
            recorder.close()
    wall = time.perf_counter() - wall0
    result = summary(sim, traj, wall, duration_s if stopped is None else sim.t - t0)
    if stopped is not None:
        result['stopped'] = {'reason': stopped, 'planned_s': float(duration_s)}
    result['outcomes'] = outcomes.summary()
    if sensors.specs:
        result['sensors'] = {spec.name: count
                             for spec, count in zip(sensors.specs, sensors.counts, strict=True)}
    if sim.feed is not None:
        result['feed'] = sim.feed.counts()
        result['outcomes']['recirculated'] = result['feed']['fell_back']
    return RunResult(result, traj)


def run_with_error_estimate(sim: Simulator, duration_s: float, *, refine: bool = True,
                            stop_reason: Callable[[], str | None] | None = None,
                            **kw) -> RunResult:
    """``run``, then the same scene again at the companion setting
    (:mod:`feeder_sim.output.numerical_error`; ``refine``: finer, else coarser), without a
    log; the summary gains ``numerical_error``: each outcome's estimated error under the key
    the summary gives it, the method and the companion's cost. ``sim`` must be at its scene's
    start (the companion starts there)."""
    if sim.t != 0.0:
        raise ValueError(f'an error estimate runs the scene again from its start: give a '
                         f'simulator at t = 0, not t = {sim.t:g} s')
    scene = sim.scene
    check = None if sim.energy_check is None else sim.energy_check.tolerance
    result = run(sim, duration_s, stop_reason=stop_reason, **kw)
    if 'stopped' in result.summary:
        return result
    comp = companion(scene.solver, refine=refine)
    log.info('numerical error: running %s again, %s', scene.name, comp.method)
    other_sim = Simulator(companion_scene(scene, comp), check_energy=check)
    other = run(other_sim, duration_s, stop_reason=stop_reason,
                **{k: v for k, v in kw.items() if k in ('publish_rate_hz', 'progress_every_s')})
    if 'stopped' in other.summary:
        result.summary['stopped'] = other.summary['stopped'] | {'in': 'error estimate'}
        return result
    errors = summary_errors(result.summary, other.summary, comp)
    base_wall = result.summary['wall_s']
    errors['companion'] |= {'wall_s': other.summary['wall_s'],
                            'cost_ratio': (base_wall + other.summary['wall_s']) / base_wall
                            if base_wall > 0 else math.nan}
    result.summary['numerical_error'] = errors
    return result


def summary(sim: Simulator, traj: Trajectory, wall_s: float, duration_s: float) -> dict:
    t, s, _ = traj.arrays()
    # each part over the frames it was there (all of them, without sources and sinks)
    mean_v, final = [], []
    for k in range(len(traj.names)):
        there = np.flatnonzero(np.isfinite(s[:, k]))
        first, last = there[0], there[-1]
        span = t[last] - t[first]
        mean_v.append((s[last, k] - s[first, k]) / span if span > 0 else 0.0)
        final.append(s[last, k])
    energy = sim.mechanical_energy()
    pilot = {} if sim.time_step_pilot is None else {'time_step_auto': sim.time_step_pilot}
    return {
        'scene': sim.scene.name,
        'method': sim.method,
        'time_step_s': float(sim.scene.solver.time_step),
        **pilot,
        'simulated_s': float(duration_s),
        'wall_s': float(wall_s),
        'wall_per_simulated_s': float(wall_s / duration_s),
        'parts': [{'name': n, 'mean_velocity_along_track_mps': float(mv),
                   'final_position_along_track_m': float(sf)}
                  for n, mv, sf in zip(traj.names, mean_v, final, strict=True)],
        'solver': sim.stats.as_dict(),
        'energy': {'initial_mechanical_j': float(sim.initial_energy_j),
                   'final_mechanical_j': float(energy),
                   'final_kinetic_j': float(sim.world.kinetic_energy(sim.state))},
    }


def write_summary(data: dict, path: str | os.PathLike) -> None:
    Path(path).write_text(json.dumps(data, indent=2) + '\n')


def plot_trajectory(traj: Trajectory, path: str | os.PathLike, title: str) -> None:
    """Position along the track against time, one line per part (PNG)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    t, s, _ = traj.arrays()
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    for i, name in enumerate(traj.names):
        ax.plot(t, 1e3 * s[:, i], label=name, lw=1.2)
    ax.set_xlabel('simulated time [s]')
    ax.set_ylabel('position along the track [mm]')
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if 0 < len(traj.names) <= 10:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
