"""``feeder-sim paper``: the paper's figures regenerated from the shipped scenes.

- Fig. 7: position along the 16 Hz track against time, with and without the friction impulse,
  on the flat track and on the 3 degree ramp (``bowl_track_*`` scenes).
- Where the result flips: steady speed on the 3 degree ramp against the drive's normal
  acceleration (Gamma), with and without the friction impulse, from the analytic point mass and
  from the event-driven simulation of the part.
- Fig. 8: the event-driven method against the impulse-based method on the same scenes.
- Fig. 9: a filmstrip of the centre-partition orienter (``orienter_partition``): cups fed
  from a magazine either way round fall onto a partition and all leave open end up, down the
  lane on their closed end's side.
- Fig. 10: filmstrips of the hook orienter for cup parts (``orienter_hook``: every cup leaves
  open end up; ``orienter_hook_short``: the hook is too short and the queue jams), with the
  outcome measures of each run.

Each figure is a PNG in the output folder; ``paper.json`` holds the numbers behind them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
import json
import logging
import math
import os
from pathlib import Path
import time

import numpy as np

from feeder_sim.model.scene import load_scene, Scene
from feeder_sim.reports.pointmass import conveyor_of, mean_speed
from feeder_sim.simulator import Simulator

log = logging.getLogger('feeder_sim')

TRACK_SCENES = {
    (0, True): 'bowl_track_0deg',
    (0, False): 'bowl_track_0deg_no_friction_impulse',
    (3, True): 'bowl_track_3deg',
    (3, False): 'bowl_track_3deg_no_friction_impulse',
}
HOOK_SCENES = ('orienter_hook', 'orienter_hook_short')
FILMSTRIP_TIMES_S = (0.0, 0.6, 0.72, 0.78, 2.8, 4.5)
# the first cup (open end right) falls in the first stroke, the second (open end left) in
# the next
PARTITION_TIMES_S = (0.0, 0.46, 0.52, 0.58, 1.46, 1.52, 1.58, 6.0)
FIGURES = ('fig7', 'flip', 'fig8', 'fig9', 'fig10')
_PARTITION_X_M = -0.00075    # the partition's tip in orienter_partition


def trace(scene: Scene | str, duration_s: float, rate_hz: float = 200.0,
          method: str | None = None) -> dict:
    """Position along the track (m, from the start) of the first part every 1/rate_hz s."""
    sim = Simulator(scene, method=method)
    s0 = float(sim.track_coordinates()[0][0])
    t, s = [0.0], [0.0]
    wall = time.perf_counter()
    for k in range(1, round(duration_s * rate_hz) + 1):
        sim.advance_to(k / rate_hz)
        t.append(sim.t)
        s.append(float(sim.track_coordinates()[0][0]) - s0)
    wall = time.perf_counter() - wall
    return {'t_s': t, 'position_m': s, 'wall_s': wall, 'method': sim.method,
            'wall_per_simulated_s': wall / duration_s}


def steady_speed(scene: Scene | str, *, warmup_s: float = 1.0, measure_s: float = 2.0,
                 method: str | None = None) -> float:
    """Mean speed along the track (m/s) of the first part after a warm-up."""
    sim = Simulator(scene, method=method)
    sim.advance_to(warmup_s)
    s0 = float(sim.track_coordinates()[0][0])
    sim.advance_to(warmup_s + measure_s)
    return (float(sim.track_coordinates()[0][0]) - s0) / measure_s


def _with_gamma(scene: Scene, gamma: float) -> Scene:
    track = scene.bodies[0]
    vib, theta = track.vibration, track.pose[2]
    omega = 2 * math.pi * vib.frequency
    amplitude = gamma * 9.81 * math.cos(theta) / (omega ** 2 * math.sin(vib.angle))
    track = replace(track, vibration=replace(vib, amplitude=amplitude))
    return replace(scene, bodies=(track, *scene.bodies[1:]))


def _plt():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path: Path, title: str, **title_kw) -> None:
    """Title, lay out, write and release a figure."""
    fig.suptitle(title, **title_kw)
    fig.tight_layout()
    fig.savefig(path)
    _plt().close(fig)


def _label_track_axes(ax, ramp_deg: int) -> None:
    """Titles and labels of a position-along-the-track panel, as in the paper's figures."""
    ax.set_title(f'Comparison of parts feeding speed ({ramp_deg}° ramp)')
    ax.set_xlabel('time [s]')
    ax.set_ylabel('position along the track [mm]')
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def _track_figure(path: Path, title: str,
                  curves: Callable[[int], Iterable[tuple[str, dict, str, str]]]) -> dict:
    """Position along the track against time on the 0 and 3 degree ramps side by side.

    ``curves(ramp_deg)`` yields ``(key, run, style, label)`` per curve of that panel, ``run`` a
    :func:`trace`; the runs are returned by key.
    """
    plt = _plt()
    data = {}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=120)
    for ax, ramp in zip(axes, (0, 3)):
        for key, run, style, label in curves(ramp):
            data[key] = run
            ax.plot(run['t_s'], 1e3 * np.asarray(run['position_m']), style, label=label)
        _label_track_axes(ax, ramp)
    _save(fig, path, title)
    return data


def figure7(out: Path, duration_s: float = 1.0) -> dict:
    """Fig. 7: with and without the friction impulse, 0 and 3 degree ramps."""
    def curves(ramp: int):
        for friction_impulse, style in ((True, '-'), (False, '--')):
            name = TRACK_SCENES[ramp, friction_impulse]
            run = trace(name, duration_s)
            run['position_at_end_m'] = run['position_m'][-1]
            label = 'with' if friction_impulse else 'without'
            yield name, run, style, f'{label} tangent impulse'
    return _track_figure(out / 'fig7_friction_impulse.png',
                         'Fig. 7: feeding with and without the friction impulse (16 Hz)', curves)


def flip(out: Path, gammas: Iterable[float] = np.round(np.arange(1.6, 3.01, 0.1), 2)) -> dict:
    """Steady speed on the 3 degree ramp against Gamma: where the friction impulse matters."""
    plt = _plt()
    base = load_scene(TRACK_SCENES[3, True])
    rows = []
    for gamma in gammas:
        row = {'gamma': float(gamma)}
        for friction_impulse in (True, False):
            key = 'with' if friction_impulse else 'without'
            row[f'point_mass_{key}_mps'] = mean_speed(conveyor_of(base, gamma, friction_impulse))
            scene = _with_gamma(base, gamma)
            scene = replace(scene, solver=replace(scene.solver,
                                                  friction_impulse=friction_impulse))
            row[f'position_1s_{key}_m'] = trace(scene, 1.0, rate_hz=16.0)['position_m'][-1]
        rows.append(row)
        log.info('flip sweep: Gamma %.2f done', gamma)
    g = np.array([r['gamma'] for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=120)
    for key, style in (('with', '-o'), ('without', '--s')):
        axes[0].plot(g, [1e3 * r[f'point_mass_{key}_mps'] for r in rows], style,
                     label=f'{key} friction impulse')
        axes[1].plot(g, [1e3 * r[f'position_1s_{key}_m'] for r in rows], style,
                     label=f'{key} friction impulse')
    shipped = conveyor_of(base).gamma
    for ax in axes:
        ax.axhline(0.0, color='k', lw=0.8)
        ax.axvline(shipped, color='grey', ls=':', label=f'shipped scenes (Γ = {shipped:.2f})')
        ax.set_xlabel('normal track acceleration Γ [g]')
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel('steady speed up the ramp [mm/s]')
    axes[0].set_title('point mass (analytic)')
    axes[1].set_ylabel('position after 1 s [mm]')
    axes[1].set_title('the part (event-driven)')
    _save(fig, out / 'flip_friction_impulse.png',
          '3° ramp, 16 Hz, drive 60°, μ = 0.3: where the friction impulse decides')
    return {'rows': rows, 'shipped_gamma': shipped,
            'flips_between': _flip_interval(rows)}


def _flip_interval(rows: list[dict]) -> list[float] | None:
    """Gamma interval in which the part (event-driven, 1 s) starts sliding back without the
    friction impulse while it still climbs with it."""
    for a, b in zip(rows, rows[1:]):
        if a['position_1s_without_m'] > 0 >= b['position_1s_without_m']:
            return [a['gamma'], b['gamma']]
    return None


def figure8(out: Path, duration_s: float = 1.0) -> dict:
    """Fig. 8: the simultaneous-LCP event-driven method against the impulse-based method."""
    def curves(ramp: int):
        name = TRACK_SCENES[ramp, True]
        for method, style in (('event_driven', '-'), ('impulse_based', '--')):
            run = trace(name, duration_s, method=method)
            run['steady_speed_mps'] = steady_speed(name, method=method)
            yield (f'{name}/{method}', run, style,
                   f"{method} ({1e3 * run['steady_speed_mps']:.1f} mm/s steady)")
    return _track_figure(
        out / 'fig8_methods.png',
        'Fig. 8: simultaneous frictional LCP (this method) vs impulse-based method', curves)


def _outlines_at(sim: Simulator) -> list[tuple[str, str, list[np.ndarray]]]:
    """(name, type, world outlines in mm) of every body of ``sim`` now, moving bodies where
    they are (a vibrating track a fraction of a millimetre off, a slide its whole stroke)."""
    origin, angle = sim.world.body_frame_pose(sim.state)
    shapes = []
    for body, o, a in zip(sim.scene.bodies, origin, angle):
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, -s], [s, c]])
        shapes.append((body.name, body.type, [1e3 * (poly @ rot.T + o) for poly in body.outlines]))
    return shapes


def filmstrip(scene: Scene | str, duration_s: float, times_s: Iterable[float], axes,
              window_mm: tuple[tuple[float, float], tuple[float, float]] = ((-50, 40), (-95, 25))
              ) -> dict:
    """Run an orienter scene, draw it at ``times_s`` into ``axes`` (x and y limits
    ``window_mm``); returns its outcomes. Cups are blue when they start at angle 0, orange
    when turned round."""
    from feeder_sim.run import run
    sim = Simulator(scene)
    first = {b.name: b.pose[2] for b in sim.scene.bodies if b.type == 'dynamic'}
    wanted = iter(sorted(times_s))
    pending = [next(wanted)]
    snaps = []

    def snap(s: Simulator) -> None:
        while pending and s.t >= pending[0] - 1e-9:
            snaps.append((s.t, _outlines_at(s)))
            pending[:] = [t for t in (next(wanted, None),) if t is not None]

    snap(sim)
    wall = time.perf_counter()
    result = run(sim, duration_s, on_frame=snap)
    wall = time.perf_counter() - wall
    spec = sim.scene.outcomes
    for ax, (t, shapes) in zip(axes, snaps):
        for name, kind, polys in shapes:
            if kind == 'dynamic':
                leading_open = abs(math.remainder(first[name], 2 * math.pi)) < 1.0
                style = {'fc': 'tab:blue' if leading_open else 'tab:orange', 'ec': 'k',
                         'lw': 0.5}
            else:
                style = {'fc': '0.75', 'ec': '0.4', 'lw': 0.5}
            for poly in polys:
                ax.fill(poly[:, 0], poly[:, 1], **style)
        if spec.exit_position is not None and spec.exit_axis == (0.0, -1.0):
            ax.axhline(-1e3 * spec.exit_position, color='tab:green', ls=':', lw=0.8)
        ax.set_xlim(*window_mm[0])
        ax.set_ylim(*window_mm[1])
        ax.set_aspect('equal')
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f't = {t:.2f} s', fontsize=8)
    return {'outcomes': result.summary['outcomes'], 'wall_s': wall,
            'wall_per_simulated_s': wall / duration_s,
            'snapshot_times_s': [t for t, _ in snaps]}


def figure9(out: Path, duration_s: float = 6.0) -> dict:
    """Fig. 9: the centre-partition orienter as a filmstrip of two strokes and the end."""
    plt = _plt()
    times = PARTITION_TIMES_S
    fig, axes = plt.subplots(2, len(times) // 2, figsize=(9.0, 9.6), dpi=120)
    data = filmstrip('orienter_partition', duration_s, times, axes.flat,
                     window_mm=((-48, 32), (-80, 72)))
    o = data['outcomes']
    counts = ', '.join(f'{v} {k.replace("_", " ")}' for k, v in o['exit_orientations'].items()
                       if v)
    lanes = {'left': 0, 'right': 0}
    for p in o['parts']:
        if p['exit_point_m'] is not None:
            lanes['left' if p['exit_point_m'][0] < _PARTITION_X_M else 'right'] += 1
    data['lanes'] = lanes
    axes[0, 0].set_ylabel(f'{o["parts_exited"]}/{len(o["parts"])} out ({counts or "none"})\n'
                          f'left lane {lanes["left"]}, right lane {lanes["right"]}', fontsize=8)
    _save(fig, out / 'fig9_partition_orienter.png',
          'Fig. 9: cups oriented by a centre partition (blue: open end right, orange: open end '
          'left; green: exit line)', fontsize=10)
    return data


def figure10(out: Path, duration_s: float = 4.5) -> dict:
    """Fig. 10: the hook orienter, a good hook and a too-short one, as filmstrips."""
    plt = _plt()
    data = {}
    times = FILMSTRIP_TIMES_S
    fig, axes = plt.subplots(len(HOOK_SCENES), len(times), figsize=(2.1 * len(times), 6.2),
                             dpi=120)
    for row, name in zip(axes, HOOK_SCENES):
        data[name] = run = filmstrip(name, duration_s, times, row)
        o = run['outcomes']
        jams = [p for p in o['parts'] if p['jam_time_s'] is not None]
        jam = f", jam at {min(p['jam_time_s'] for p in jams):.2f} s" if jams else ', no jam'
        counts = ', '.join(f'{v} {k.replace("_", " ")}' for k, v in
                           o['exit_orientations'].items() if v)
        row[0].set_ylabel(f'{name}\n{o["parts_exited"]}/{len(o["parts"])} out '
                          f'({counts or "none"}){jam}', fontsize=8)
    _save(fig, out / 'fig10_hook_orienter.png',
          'Fig. 10: cups oriented by a hook (blue: arriving open end first, orange: '
          'closed end first; green: exit line)', fontsize=10)
    return data


_BUILDERS: dict[str, Callable[[Path], dict]] = {'fig7': figure7, 'flip': flip, 'fig8': figure8,
                                                 'fig9': figure9, 'fig10': figure10}


def paper(out_dir: str | os.PathLike, figures: Iterable[str] = FIGURES) -> dict:
    """Regenerate ``figures`` into ``out_dir``; returns (and writes) the numbers as JSON."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in figures:
        if name not in _BUILDERS:
            raise ValueError(f'unknown figure {name!r}; choose from {", ".join(_BUILDERS)}')
        log.info('paper: %s ...', name)
        t0 = time.perf_counter()
        results[name] = _BUILDERS[name](out)
        log.info('paper: %s done in %.1f s', name, time.perf_counter() - t0)
    path = out / 'paper.json'
    path.write_text(json.dumps(results, indent=1) + '\n')
    return results
