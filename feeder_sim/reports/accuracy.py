"""``feeder-sim accuracy``: error against run time, for every method and, where installed, pymunk.

Each case has an exact or converged reference and one physically meaningful quantity (distance
slid, creep, rocking ratio, landing point, mean conveying speed). Each method is swept over its
accuracy setting:

* ``time_stepping``: the step ``time_step`` (s);
* ``event_driven``: the integrator's relative ``tolerance`` (its largest step stays the
  scene's: 1/16 of the vibration period, or 10 ms where nothing vibrates);
* ``impulse_based``: the collision envelope ``ImpulseSettings.envelope_m`` (its step does not
  enter the accuracy, see :mod:`feeder_sim.stepping.impulse_based`);
* ``pymunk`` (when importable): the step, with 20 solver iterations, a collision slop of
  1 um and the default overlap bias; friction of a pair is the product of the two shapes'
  frictions there, so the track gets 1 and the part mu; restitution 0; a kinematic track moved
  by setting its velocity to the drive's mean velocity over each step (its position is then
  exact at step ends); the incline is a level track under a tilted gravity.

For each (case, method, setting) the report keeps the relative error of the quantity and the
wall time per simulated second (``Simulator.advance`` only), and writes
``accuracy.json``, ``accuracy.png`` (work-precision: log error against log wall time, one panel
per case) and a table to stdout. Errors are floored at 1e-16 (exact answers plot on the floor).

Every case states ``tolerance``: the error each method must reach at its finest setting
(:func:`check` lists the misses; the tests run it on a small subset).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path
import statistics
import time

import numpy as np

from feeder_sim.model.builders import box_part, build, conveyor, G, ground, on_slope, scene_dict
from feeder_sim.reports.pointmass import Conveyor, mean_speed
from feeder_sim.simulator import Simulator
from feeder_sim.stepping.event_driven.stepper import EventSettings
from feeder_sim.stepping.impulse_based import ImpulseSettings

ERROR_FLOOR = 1e-16
PART = (0.02, 0.01)            # box width x height, m (the conveying tables' part)
MASS = 0.01                    # kg
METHODS = ('time_stepping', 'event_driven', 'impulse_based', 'pymunk')
SETTINGS = {                   # per method: finest last
    'event_driven': (1e-4, 1e-6, 1e-8, 1e-10),
    'impulse_based': (1e-6, 1e-7, 1e-8, 1e-9),
}
STEPS_PER_PERIOD = (50, 100, 200, 400, 800, 1600)      # time_stepping and pymunk, conveying
STEPS = (1e-3, 3e-4, 1e-4, 3e-5, 1e-5)                  # time_stepping and pymunk, otherwise


@dataclass(frozen=True)
class Case:
    """One accuracy case: a scene, the quantity measured on it, and its exact value."""

    key: str
    description: str
    quantity: str
    scene: Callable[[str], dict]           # method -> scene dict
    measure: Callable[[Simulator, float], float]   # (sim, track coordinate at warmup_s)
    reference: Callable[[], float]
    duration_s: float
    error_scale: Callable[[], float] | None = None   # |value - ref| / scale (default |ref|)
    frequency_hz: float | None = None      # a vibrating track: steps per period
    warmup_s: float = 0.0                  # measure() also gets the track coordinate here
    tolerance: dict = field(default_factory=dict)     # method -> error at its finest setting
    pymunk: Callable[[float], tuple[float, float]] | None = None   # dt -> (value, wall s)


# --------------------------------------------------------------------------- scene helpers
# the scenes' step where nothing vibrates: event_driven's largest step (the sweep sets the others)
STEP_S = 1e-2


def _part_on(theta: float, mu: float) -> dict:
    """The part resting on a slope of ``theta`` (rad) through the origin."""
    w, h = PART
    return box_part('box', w / 2, h / 2, (*on_slope(0.0, h / 2, theta), theta), mu=mu,
                    mass=MASS)


def _track_coordinate(sim: Simulator) -> float:
    return float(sim.track_coordinates()[0][0])


def _along(sim: Simulator, theta: float) -> float:
    """Displacement of the part along the slope (m, downhill positive)."""
    start = np.array(on_slope(0.0, PART[1] / 2, theta))
    d = sim.state.position[sim.part_indices[0]] - start
    return float(-(d[0] * math.cos(theta) + d[1] * math.sin(theta)))


# --------------------------------------------------------------------------- the cases
SLIDE_THETA, SLIDE_MU, SLIDE_T = math.radians(30.0), 0.3, 0.5
STICK_THETA, STICK_MU, STICK_T = math.radians(20.0), 0.5, 0.5


def _slide_reference() -> float:
    return 0.5 * G * (math.sin(SLIDE_THETA) - SLIDE_MU * math.cos(SLIDE_THETA)) * SLIDE_T ** 2


def _pymunk_incline(dt: float) -> tuple[float, float]:
    space, _ = _pymunk_space(gravity=(G * math.sin(SLIDE_THETA), -G * math.cos(SLIDE_THETA)),
                             kinematic=False)
    part = _pymunk_box(space, SLIDE_MU)
    x0 = part.position.x
    n = round(SLIDE_T / dt)
    t0 = time.perf_counter()
    for _ in range(n):
        space.step(dt)
    wall = time.perf_counter() - t0
    return part.position.x - x0, wall / SLIDE_T


FLIGHT_V, FLIGHT_OMEGA, FLIGHT_T = (1.0, 2.0), 10.0, 0.3


def _flight_measure(sim: Simulator, _mark: float) -> float:
    """Distance between the simulated and the exact centre of mass after FLIGHT_T (m)."""
    vx, vy = FLIGHT_V
    exact = np.array([vx * FLIGHT_T, vy * FLIGHT_T - 0.5 * G * FLIGHT_T ** 2])
    return float(np.linalg.norm(sim.state.position[sim.part_indices[0]] - exact))


HOUSNER_B_OVER_H, HOUSNER_OMEGA = 0.5, 2.0


def _housner_scene(method: str) -> dict:
    h = 0.01
    b = HOUSNER_B_OVER_H * h
    om = HOUSNER_OMEGA
    body = box_part('block', b, h, (0.0, h, 0.0), (-h * om, -b * om, om), mu=5.0, mass=MASS)
    return scene_dict('housner', [ground(mu=5.0, thickness=0.02), body], method, 1e-3,
                      gravity=(0.0, 0.0))


def _housner_reference() -> float:
    sin2 = HOUSNER_B_OVER_H ** 2 / (1.0 + HOUSNER_B_OVER_H ** 2)
    return 1.0 - 1.5 * sin2


@dataclass(frozen=True)
class _Track:
    frequency_hz: float
    theta_deg: float
    gamma: float
    psi_deg: float = 20.0
    mu: float = 0.5

    def point(self) -> Conveyor:
        return Conveyor(psi=math.radians(self.psi_deg), theta=math.radians(self.theta_deg),
                        mu_s=self.mu, mu_k=self.mu, gamma=self.gamma,
                        frequency_hz=self.frequency_hz, g=G)

    @property
    def cycles(self) -> tuple[int, int]:
        return (20, 10)


def _conveying_case(key: str, track: _Track, regime: str) -> Case:
    warm, meas = track.cycles
    period = 1.0 / track.frequency_hz

    def scene(method: str) -> dict:
        return conveyor(psi=math.radians(track.psi_deg), mu=track.mu,
                        theta=math.radians(track.theta_deg), gamma=track.gamma,
                        frequency_hz=track.frequency_hz, method=method, part_size=PART,
                        mass=MASS, name=key)

    def measure(sim: Simulator, mark: float) -> float:
        return (_track_coordinate(sim) - mark) / (meas * period)

    def reference() -> float:
        return mean_speed(track.point(), warmup_cycles=warm, cycles=meas)

    return Case(key, f'{track.frequency_hz:g} Hz, {track.theta_deg:g} deg uphill, Gamma '
                     f'{track.gamma:g} ({regime}), psi {track.psi_deg:g} deg, mu {track.mu}',
                'mean conveying speed (m/s) vs the point mass', scene, measure, reference,
                (warm + meas) * period, frequency_hz=track.frequency_hz,
                warmup_s=warm * period,
                tolerance={'time_stepping': 5e-3, 'event_driven': 1e-5,
                           'impulse_based': 2e-2},
                pymunk=lambda dt: _pymunk_conveying(track, dt))


CASES: dict[str, Case] = {c.key: c for c in (
    Case('incline_slide', 'box released on a 30 deg incline, mu 0.3',
         'distance slid in 0.5 s vs g (sin - mu cos) t^2 / 2',
         lambda m: scene_dict('incline_slide', [ground(SLIDE_MU, thickness=0.02,
                                                       angle=SLIDE_THETA),
                                                _part_on(SLIDE_THETA, SLIDE_MU)], m, STEP_S),
         lambda sim, _: _along(sim, SLIDE_THETA), _slide_reference, SLIDE_T,
         tolerance={'time_stepping': 1e-3, 'event_driven': 1e-9, 'impulse_based': 1e-3},
         pymunk=_pymunk_incline),
    Case('incline_stick', 'box at rest on a 20 deg incline, mu 0.5 (must stick)',
         'creep in 0.5 s over the frictionless distance g sin t^2 / 2',
         lambda m: scene_dict('incline_stick', [ground(STICK_MU, thickness=0.02,
                                                       angle=STICK_THETA),
                                                _part_on(STICK_THETA, STICK_MU)], m, STEP_S),
         lambda sim, _: _along(sim, STICK_THETA), lambda: 0.0, STICK_T,
         error_scale=lambda: 0.5 * G * math.sin(STICK_THETA) * STICK_T ** 2,
         tolerance={'time_stepping': 1e-6, 'event_driven': 1e-9, 'impulse_based': 1e-2}),
    Case('housner', 'block (b/h = 0.5) rocking onto its corner at 2 rad/s, no gravity',
         'angular velocity ratio across the impact vs 1 - 1.5 sin^2(alpha)',
         _housner_scene,
         lambda sim, _: float(sim.state.omega[sim.part_indices[0]]) / HOUSNER_OMEGA,
         _housner_reference, 0.01,
         tolerance={'time_stepping': 1e-3, 'event_driven': 1e-9, 'impulse_based': 1e-2}),
    Case('free_flight', 'box thrown at (1, 2) m/s spinning at 10 rad/s',
         'centre of mass after 0.3 s vs the parabola (m over the distance flown)',
         lambda m: scene_dict('free_flight', [box_part(
             'box', PART[0] / 2, PART[1] / 2, (0.0, 0.0, 0.0),
             (*FLIGHT_V, FLIGHT_OMEGA), mass=MASS)], m, STEP_S),
         _flight_measure, lambda: 0.0, FLIGHT_T,
         error_scale=lambda: math.hypot(FLIGHT_V[0] * FLIGHT_T,
                                        FLIGHT_V[1] * FLIGHT_T - 0.5 * G * FLIGHT_T ** 2),
         tolerance={'time_stepping': 1e-3, 'event_driven': 1e-12, 'impulse_based': 1e-12}),
    _conveying_case('conveying_50hz_flat_sliding', _Track(50.0, 0.0, 0.8), 'sliding'),
    _conveying_case('conveying_50hz_flat_hopping', _Track(50.0, 0.0, 1.5), 'hopping'),
    _conveying_case('conveying_50hz_3deg_hopping', _Track(50.0, 3.0, 1.5), 'hopping'),
    _conveying_case('conveying_16hz_flat_sliding', _Track(16.0, 0.0, 0.8), 'sliding'),
    _conveying_case('conveying_16hz_3deg_hopping', _Track(16.0, 3.0, 2.0), 'hopping'),
)}


# --------------------------------------------------------------------------- slide regime
@dataclass(frozen=True)
class SlideRegime:
    """A part conveyed without lift-off (``gamma`` < 1) with ``mu_s = ratio * mu_d``: angles
    in degrees, the track at ``frequency_hz``. The part starts at rest relative to the track."""

    psi_deg: float
    theta_deg: float
    ratio: float
    gamma: float
    frequency_hz: float
    mu_d: float = 0.4

    def __str__(self) -> str:
        return (f'psi{self.psi_deg:g}_theta{self.theta_deg:g}_ratio{self.ratio:g}'
                f'_gamma{self.gamma:g}_{self.frequency_hz:g}Hz')

    def point(self) -> Conveyor:
        return Conveyor(psi=math.radians(self.psi_deg), theta=math.radians(self.theta_deg),
                        mu_s=self.ratio * self.mu_d, mu_k=self.mu_d, gamma=self.gamma,
                        frequency_hz=self.frequency_hz, g=G)

    def reference(self) -> float:
        """The exact point mass's mean speed (m/s) over the cycles ``slide_speed`` measures."""
        return mean_speed(self.point(), warmup_cycles=SLIDE_CYCLES[0],
                          cycles=SLIDE_CYCLES[1])


SLIDE_CYCLES = (20, 20)         # warm-up and measured vibration periods
# Corners and middles of the slide regime (Gamma 0.2-0.95, psi 5-45 deg, theta 0-5 deg,
# mu_s / mu_d 1-1.5, 25-100 Hz): one line each in slide_regime.png
SLIDE_REGIMES = (
    SlideRegime(5.0, 0.0, 1.5, 0.95, 25.0),
    SlideRegime(10.0, 0.0, 1.25, 0.8, 50.0),
    SlideRegime(5.0, 0.0, 1.5, 0.3, 50.0),
    SlideRegime(20.0, 3.0, 1.5, 0.5, 50.0),
    SlideRegime(45.0, 5.0, 1.5, 0.5, 25.0),
    SlideRegime(30.0, 2.5, 1.0, 0.8, 100.0),
    SlideRegime(15.0, 5.0, 1.25, 0.95, 100.0),
    SlideRegime(45.0, 0.0, 1.0, 0.5, 25.0),
    SlideRegime(15.0, 2.5, 1.5, 0.8, 50.0),
)
SLIDE_STEPS_PER_PERIOD = (100, 200, 400, 800, 1600)


def slide_speed(regime: SlideRegime, method: str, time_step: float | None = None) -> float:
    """Mean conveying speed (m/s) of the regime's box over ``SLIDE_CYCLES``' measured periods."""
    f = regime.frequency_hz
    sim = Simulator(build(conveyor(
        psi=math.radians(regime.psi_deg), mu=regime.ratio * regime.mu_d,
        mu_dynamic=regime.mu_d, theta=math.radians(regime.theta_deg), gamma=regime.gamma,
        frequency_hz=f, method=method, time_step=time_step, part_size=PART, mass=MASS,
        start_with_track=True)))
    warm, cycles = SLIDE_CYCLES
    sim.advance_to(warm / f)
    mark = _track_coordinate(sim)
    sim.advance_to((warm + cycles) / f)
    return (_track_coordinate(sim) - mark) * f / cycles


def run_slide_regime(out_dir: str | os.PathLike,
                     steps_per_period: Sequence[int] = SLIDE_STEPS_PER_PERIOD,
                     regimes: Sequence[SlideRegime] = SLIDE_REGIMES,
                     progress: Callable[[str], None] | None = print) -> list[dict]:
    """time_stepping's relative error in the mean conveying speed against steps per period,
    per slide regime; writes ``slide_regime.json`` and ``slide_regime.png`` (with the
    first-order bound ``2 (2 pi / N)``)."""
    say = progress or (lambda _m: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for regime in regimes:
        exact = regime.reference()
        errors = {}
        for n in steps_per_period:
            speed = slide_speed(regime, 'time_stepping', 1.0 / (regime.frequency_hz * n))
            # a part that sticks all along has no speed to be relative to: m/s then
            errors[n] = abs(speed - exact) / (abs(exact) or 1.0)
        rows.append({'regime': str(regime), 'reference_mps': exact,
                     'errors': {str(n): e for n, e in errors.items()}})
        say(f'slide regime {regime}: reference {exact:.6g} m/s, relative error '
            + ', '.join(f'N={n} {e:.2e}' for n, e in errors.items()))
    (out / 'slide_regime.json').write_text(json.dumps(rows, indent=2) + '\n')
    _plot_slide_regime(rows, steps_per_period, out / 'slide_regime.png')
    return rows


def _plot_slide_regime(rows: Sequence[dict], steps_per_period: Sequence[int],
                       path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    n = np.asarray(steps_per_period, float)
    for row in rows:
        err = [max(ERROR_FLOOR, row['errors'][str(k)]) for k in steps_per_period]
        ax.loglog(n, err, 'o-', ms=3, lw=1, label=row['regime'])
    ax.loglog(n, 4 * math.pi / n, 'k--', lw=1.5, label='2 (2 pi / N): first-order bound')
    ax.set_xlabel('time steps per vibration period N')
    ax.set_ylabel('relative error of the mean conveying speed')
    ax.set_title('time_stepping, slide regime (Gamma < 1), vs the exact point mass', fontsize=10)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- pymunk peer
def _pymunk_space(gravity, kinematic: bool):
    import pymunk
    space = pymunk.Space()
    space.gravity = gravity
    space.iterations = 20
    space.collision_slop = 1e-6
    body = (pymunk.Body(body_type=pymunk.Body.KINEMATIC) if kinematic
            else space.static_body)
    track = pymunk.Poly(body, [(-1.0, -0.01), (1.0, -0.01), (1.0, 0.0), (-1.0, 0.0)])
    track.friction, track.elasticity = 1.0, 0.0
    if kinematic:
        space.add(body, track)
    else:
        space.add(track)
    return space, body


def _pymunk_box(space, mu: float):
    import pymunk
    w, h = PART
    part = pymunk.Body(MASS, pymunk.moment_for_box(MASS, (w, h)))
    part.position = (0.0, h / 2)
    shape = pymunk.Poly.create_box(part, (w, h), radius=0.0)
    shape.friction, shape.elasticity = mu, 0.0
    space.add(part, shape)
    return part


def _pymunk_conveying(track: _Track, dt: float) -> tuple[float, float]:
    th = math.radians(track.theta_deg)
    space, body = _pymunk_space(gravity=(-G * math.sin(th), -G * math.cos(th)), kinematic=True)
    part = _pymunk_box(space, track.mu)
    point = track.point()
    amp, om, psi = point.amplitude, point.omega, math.radians(track.psi_deg)
    ux, uy = math.cos(psi), math.sin(psi)
    warm, meas = track.cycles
    period = 1.0 / track.frequency_hz
    n_per = max(1, round(period / dt))
    h = period / n_per
    x_mark, t, wall = 0.0, 0.0, 0.0
    for k in range(warm + meas):
        t0 = time.perf_counter()
        for _ in range(n_per):
            speed = amp * (math.sin(om * (t + h)) - math.sin(om * t)) / h
            body.velocity = (speed * ux, speed * uy)
            space.step(h)
            t += h
        wall += time.perf_counter() - t0
        if k + 1 == warm:
            x_mark = part.position.x - body.position.x
    v = (part.position.x - body.position.x - x_mark) / (meas * period)
    return v, wall / ((warm + meas) * period)


def pymunk_available() -> bool:
    try:
        import pymunk  # noqa: F401
    except ImportError:
        return False
    return True


# --------------------------------------------------------------------------- running
def settings_for(case: Case, method: str) -> tuple:
    if method in SETTINGS:
        return SETTINGS[method]
    if case.frequency_hz:
        return tuple(1.0 / (case.frequency_hz * n) for n in STEPS_PER_PERIOD)
    return STEPS


def _simulator(case: Case, method: str, setting: float) -> Simulator:
    scene = build(case.scene(method))
    if method == 'time_stepping':
        return Simulator(scene, time_step=setting)
    if method == 'event_driven':
        return Simulator(scene, tolerance=setting, settings=EventSettings())
    return Simulator(scene, settings=ImpulseSettings(envelope_m=setting))


def _error(case: Case, value: float, reference: float) -> float:
    scale = case.error_scale() if case.error_scale else abs(reference)
    return max(ERROR_FLOOR, abs(value - reference) / scale)


def run_one(case: Case, method: str, setting: float) -> dict:
    """One point of the work-precision plot."""
    if method == 'pymunk':
        value, wall_per_s = case.pymunk(setting)
        stats = {}
    else:
        sim = _simulator(case, method, setting)
        t0 = time.perf_counter()
        mark = 0.0
        if case.warmup_s:
            sim.advance_to(case.warmup_s)
            mark = _track_coordinate(sim)
        sim.advance_to(case.duration_s)
        wall_per_s = (time.perf_counter() - t0) / case.duration_s
        value = case.measure(sim, mark)
        st = sim.stats
        stats = {'fallbacks': st.fallbacks, 'unconverged': st.unconverged,
                 'lcp_solves': st.lcp_solves, 'events': st.events}
    return {'case': case.key, 'method': method, 'setting': setting, 'value': value,
            'wall_per_sim_s': wall_per_s, **stats}


def run_accuracy(out_dir: str | os.PathLike, cases: Sequence[str] | None = None,
                 methods: Sequence[str] | None = None, quick: bool = False,
                 repeats: int = 1, settings: dict[str, Sequence[float]] | None = None,
                 progress: Callable[[str], None] | None = print) -> dict:
    """Sweep every method over its setting on every case; write accuracy.json / .png.

    ``quick`` keeps the coarsest and the finest setting of each method; ``settings`` replaces
    a method's grid (method -> settings, coarse to fine). ``repeats`` > 1 times each point
    that often and keeps the median wall time (the values are deterministic)."""
    say = progress or (lambda _m: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keys = list(cases or CASES)
    unknown = [k for k in keys if k not in CASES]
    if unknown:
        raise ValueError(f'unknown accuracy case(s) {", ".join(unknown)}; choose from '
                         f'{", ".join(CASES)}')
    wanted = list(methods or METHODS)
    bad = [m for m in wanted if m not in METHODS]
    if bad:
        raise ValueError(f'unknown method(s) {", ".join(bad)}; choose from {", ".join(METHODS)}')
    if 'pymunk' in wanted and not pymunk_available():
        say('pymunk is not installed: it is left out (pip install pymunk)')
        wanted.remove('pymunk')
    rows = []
    for key in keys:
        case = CASES[key]
        reference = case.reference()
        say(f'{key}: {case.description}; reference {reference:.9g}')
        for method in wanted:
            if method == 'pymunk' and case.pymunk is None:
                continue
            grid = tuple((settings or {}).get(method) or settings_for(case, method))
            if quick:
                grid = tuple(dict.fromkeys((grid[0], grid[-1])))
            # untimed: loads (or compiles) the kernels this case uses before any timing
            run_one(case, method, grid[0])
            for setting in grid:
                runs = [run_one(case, method, setting) for _ in range(max(1, repeats))]
                row = runs[0]
                row['wall_per_sim_s'] = statistics.median(r['wall_per_sim_s'] for r in runs)
                row['reference'] = reference
                row['error'] = _error(case, row['value'], reference)
                rows.append(row)
                say(f'  {method:13s} {_label(method, setting):>12s}  error {row["error"]:.2e}'
                    f'  {row["wall_per_sim_s"]:.3g} s wall / simulated s')
    result = {'cases': {k: {'description': CASES[k].description,
                            'quantity': CASES[k].quantity,
                            'tolerance': CASES[k].tolerance} for k in keys},
              'methods': wanted, 'rows': rows, 'misses': check(rows),
              'comparison': compare(rows)}
    if cases is None and 'time_stepping' in wanted:
        steps = SLIDE_STEPS_PER_PERIOD
        result['slide_regime'] = run_slide_regime(
            out, (steps[0], steps[-1]) if quick else steps, progress=progress)
    (out / 'accuracy.json').write_text(json.dumps(result, indent=2) + '\n')
    plot(rows, out / 'accuracy.png')
    say(table(rows))
    if result['comparison']:
        say(comparison_table(result['comparison']))
    say(f'wrote {out / "accuracy.json"} and {out / "accuracy.png"}')
    return result


def _label(method: str, setting: float) -> str:
    return {'event_driven': 'tol', 'impulse_based': 'env'}.get(method, 'dt') + f' {setting:.0e}'


def _finest(rows: Iterable[dict]) -> dict[tuple[str, str], dict]:
    best: dict[tuple[str, str], dict] = {}
    for r in rows:
        k = (r['case'], r['method'])
        # settings are ordered coarse -> fine; the finest is the smallest number
        if k not in best or r['setting'] < best[k]['setting']:
            best[k] = r
    return best


def check(rows: Iterable[dict]) -> list[str]:
    """Cases whose finest setting of a method misses the case's stated tolerance."""
    misses = []
    for (key, method), r in sorted(_finest(rows).items()):
        tol = CASES[key].tolerance.get(method)
        if tol is not None and not r['error'] <= tol:
            misses.append(f'{key} / {method}: error {r["error"]:.2e} > {tol:.0e}')
    return misses


def compare(rows: Iterable[dict], target: float = 1e-4, peer_target: float = 1e-2) -> dict:
    """Per conveying case: the cheapest event_driven point within ``target`` and the cheapest
    peer (pymunk, time_stepping) point within ``peer_target`` (wall s per simulated s).

    A first-order method's error is not monotonic in its step (it can cross zero), so each
    entry also gives the cheapest setting from which every finer one stays within the bound
    (``steady``): what a user who cannot check against a reference would have to pay."""
    rows = list(rows)
    out = {}
    for key in dict.fromkeys(r['case'] for r in rows):
        if not key.startswith('conveying'):
            continue
        entry = {}
        for method, tol in (('event_driven', target), ('pymunk', peer_target),
                            ('time_stepping', peer_target)):
            mine = sorted((r for r in rows if r['case'] == key and r['method'] == method),
                          key=lambda r: -r['setting'])          # coarse -> fine
            ok = [r for r in mine if r['error'] <= tol]
            steady = next((r for i, r in enumerate(mine)
                           if all(q['error'] <= tol for q in mine[i:])), None)
            entry[method] = None if not ok else {
                'error_bound': tol,
                'cheapest': _point(min(ok, key=lambda r: r['wall_per_sim_s'])),
                'steady': None if steady is None else _point(steady)}
        out[key] = entry
    return out


def _point(r: dict) -> dict:
    return {'setting': r['setting'], 'error': r['error'], 'wall_per_sim_s': r['wall_per_sim_s']}


def comparison_table(comparison: dict) -> str:
    """event_driven at 1e-4 next to the peers at 1e-2, wall s per simulated s."""
    lines = [f'{"case":30s} {"event_driven <=1e-4":>20s} {"pymunk <=1e-2":>15s} '
             f'{"(steady)":>9s} {"time_stepping <=1e-2":>21s} {"(steady)":>9s}']

    def cell(e, which='cheapest'):
        return '-' if not e or not e.get(which) else f'{e[which]["wall_per_sim_s"]:.3g}'
    for key, e in comparison.items():
        lines.append(f'{key:30s} {cell(e["event_driven"]):>20s} {cell(e["pymunk"]):>15s} '
                     f'{cell(e["pymunk"], "steady"):>9s} {cell(e["time_stepping"]):>21s} '
                     f'{cell(e["time_stepping"], "steady"):>9s}')
    return '\n'.join(lines)


def table(rows: Sequence[dict]) -> str:
    lines = [f'{"case":30s} {"method":14s} {"setting":>12s} {"value":>14s} {"error":>9s} '
             f'{"wall s/sim s":>12s}']
    for r in rows:
        lines.append(f'{r["case"]:30s} {r["method"]:14s} {_label(r["method"], r["setting"]):>12s}'
                     f' {r["value"]:14.7g} {r["error"]:9.2e} {r["wall_per_sim_s"]:12.4g}')
    return '\n'.join(lines)


def plot(rows: Sequence[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    keys = list(dict.fromkeys(r['case'] for r in rows))
    n = len(keys)
    cols = min(3, n)
    lines = (n + cols - 1) // cols
    fig, axes = plt.subplots(lines, cols, figsize=(5.2 * cols, 3.8 * lines), squeeze=False)
    colors = {'time_stepping': 'C0', 'event_driven': 'C3', 'impulse_based': 'C2',
              'pymunk': 'C7'}
    for ax, key in zip(axes.flat, keys):
        for method in colors:
            pts = sorted((-r['setting'], r['wall_per_sim_s'], r['error']) for r in rows
                         if r['case'] == key and r['method'] == method)   # coarse -> fine
            if pts:
                _, x, y = zip(*pts)
                ax.loglog(x, y, 'o-', color=colors[method], label=method, ms=4)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel('wall time per simulated second (s)')
        ax.set_ylabel('relative error')
        ax.grid(True, which='both', alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=8)
    fig.suptitle('feeder_sim work-precision: error against run time')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
