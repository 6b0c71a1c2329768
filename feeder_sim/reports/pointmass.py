"""High-accuracy reference for vibratory conveying: a point mass on a vibrating inclined track.

Model (physics reference section 4.1-4.2). The track is inclined at ``theta`` (uphill toward +x)
and moves by ``a0 sin(omega t)`` along a line at ``psi`` above the track surface, "forward and
up". The particle has static and kinetic friction ``mu_s``, ``mu_k``; landings are plastic
(normal restitution 0) with the tangential landing impulse limited by ``mu_k`` times the normal
impulse (Coulomb, no slip reversal), or frictionless if asked.

Everything is computed in the track frame and in dimensionless form: phase ``tau = omega t``,
lengths in ``g_n / omega^2`` and velocities in ``g_n / omega`` with ``g_n = g cos(theta)``. In
each phase (stick, slide with direction sigma = +-1, flight) the relative acceleration is
``alpha + beta sin(tau)``, so velocity and position are closed-form (polynomial in tau plus
sin/cos). Events are located on these closed forms:

* stick -> slide / lift-off: the friction margins ``mu_s N -+ F`` and the normal force ``N``
  are of the form ``A + B sin(tau)``, whose roots are found analytically;
* slide -> stop: ``sigma u`` is monotone between the (analytic) roots of its derivative, so its
  first zero is bracketed exactly and refined with ``brentq``;
* flight -> landing: the gap velocity is monotone between the analytic roots of the gap
  acceleration; its roots (``brentq``) split the gap into monotone pieces, whose first zero is
  refined with ``brentq``.

No sampling is involved, so no event can be missed (tangential touches aside). The integration
is re-based at every cycle start, which keeps the phase in ``[0, 2 pi]`` and gives each cycle's
displacement directly.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.optimize import brentq

TWO_PI = 2.0 * math.pi
STICK, SLIDE, FLIGHT = 'stick', 'slide', 'flight'
XTOL = 1e-15
RTOL = 4.0 * np.finfo(float).eps
MAX_EVENTS_PER_CYCLE = 10_000
MAX_PERIOD = 8          # longest periodic orbit (in cycles) recognised for early stopping
STATE_TOL = 1e-12       # relative agreement that counts as "the same state / cycle mean"


@dataclass(frozen=True)
class Conveyor:
    """A straight vibrating track and the friction of the point mass on it (angles in rad).

    ``gamma`` is the normal track acceleration amplitude over ``g cos(theta)``.
    """

    psi: float
    theta: float
    mu_s: float
    mu_k: float
    gamma: float
    frequency_hz: float = 50.0
    g: float = 9.81
    frictionless_landing: bool = False

    @property
    def omega(self) -> float:
        return TWO_PI * self.frequency_hz

    @property
    def g_n(self) -> float:
        return self.g * math.cos(self.theta)

    @property
    def amplitude(self) -> float:
        """Drive amplitude a0 (m, 0-peak along the drive line)."""
        return self.gamma * self.g_n / (self.omega ** 2 * math.sin(self.psi))

    @property
    def velocity_scale(self) -> float:
        """g_n / omega (m/s): the unit of the dimensionless speed."""
        return self.g_n / self.omega


def thresholds(c: Conveyor) -> dict[str, float]:
    """Gamma at which forward sliding, backward sliding and hopping first occur (section 4.1)."""
    cot = 1.0 / math.tan(c.psi)
    tan = math.tan(c.theta)
    backward = (c.mu_s - tan) / (cot - c.mu_s) if cot > c.mu_s else math.inf
    return {'forward': (c.mu_s + tan) / (cot + c.mu_s), 'backward': backward, 'hop': 1.0}


# ---------------------------------------------------------------------------------------------
# Closed forms for p'' = alpha + beta sin(tau), written so that they stay accurate for small
# s = tau - tau0 (the series avoid the cancellation in s - sin s and cos s - 1 + s^2/2).

def _series_tail(term: float, s2: float, power: int) -> float:
    """Sum of an alternating Taylor tail from ``term`` (the s^power term) on: each next term
    is the last times -s^2 / ((power + 1)(power + 2)), until it no longer counts."""
    total = 0.0
    while True:
        total += term
        term *= -s2 / ((power + 1) * (power + 2))
        power += 2
        if abs(term) <= 1e-17 * abs(total):
            return total


def _s_minus_sin(s: float) -> float:
    """s - sin(s)."""
    if abs(s) >= 1.0:
        return s - math.sin(s)
    s2 = s * s
    return _series_tail(s * s2 / 6.0, s2, 3)


def _cos_taylor_rest(s: float) -> float:
    """cos(s) - 1 + s^2 / 2."""
    if abs(s) >= 1.0:
        return math.cos(s) - 1.0 + 0.5 * s * s
    s2 = s * s
    return _series_tail(s2 * s2 / 24.0, s2, 4)


@dataclass(frozen=True)
class _Motion:
    """p(tau) with p(tau0) = p0, p'(tau0) = v0 and p'' = alpha + beta sin(tau)."""

    tau0: float
    p0: float
    v0: float
    alpha: float
    beta: float

    def pos(self, tau: float) -> float:
        s = tau - self.tau0
        s0, c0 = math.sin(self.tau0), math.cos(self.tau0)
        return (self.p0 + self.v0 * s + 0.5 * (self.alpha + self.beta * s0) * s * s
                + self.beta * c0 * _s_minus_sin(s) - self.beta * s0 * _cos_taylor_rest(s))

    def vel(self, tau: float) -> float:
        s = tau - self.tau0
        s0, c0 = math.sin(self.tau0), math.cos(self.tau0)
        one_minus_cos = 2.0 * math.sin(0.5 * s) ** 2
        return (self.v0 + (self.alpha + self.beta * s0) * s - self.beta * s0 * _s_minus_sin(s)
                + self.beta * c0 * one_minus_cos)

    def acc(self, tau: float) -> float:
        return self.alpha + self.beta * math.sin(tau)


# ---------------------------------------------------------------------------------------------
# Root location

def _sin_roots(a_: float, b_: float, lo: float, hi: float) -> list[tuple[float, float]]:
    """Roots of ``a_ + b_ sin(tau)`` in (lo, hi), sorted, each with the sign of the slope there.

    Tangential roots (|a_| = |b_|) are not crossings and are left out.
    """
    if b_ == 0.0 or hi <= lo:
        return []
    r = -a_ / b_
    if not -1.0 < r < 1.0:
        return []
    t1 = math.asin(r)
    base = ((t1, math.copysign(1.0, b_)), (math.pi - t1, -math.copysign(1.0, b_)))
    out = []
    for k in range(math.floor(lo / TWO_PI) - 1, math.floor(hi / TWO_PI) + 2):
        for t, slope in base:
            t = t + k * TWO_PI
            if lo < t < hi:
                out.append((t, slope))
    out.sort()
    return out


def _first_drop(a_: float, b_: float, lo: float, hi: float) -> float | None:
    """First tau in [lo, hi] at which ``a_ + b_ sin(tau)`` (>= 0 at lo) becomes negative."""
    tol = 1e-13 * (abs(a_) + abs(b_))
    if a_ + b_ * math.sin(lo) < -tol:
        return lo
    for t, slope in _sin_roots(a_, b_, lo - 1e-9, hi):
        if slope < 0:
            return max(t, lo)
    return None


def _scaled(f, k: float):
    return lambda t: k * f(t)


def _first_zero_from_above(f, breaks: list[float], lo: float, hi: float) -> float | None:
    """First tau in (lo, hi] where ``f`` passes from > 0 to <= 0.

    ``f`` must be monotone between consecutive points of ``lo, *breaks, hi`` (breaks sorted,
    inside (lo, hi)).
    """
    points = [lo, *breaks, hi]
    fp = f(lo)
    for p, q in zip(points[:-1], points[1:]):
        fq = f(q)
        if fp > 0.0 and fq <= 0.0:
            if fq == 0.0:
                return q
            return brentq(f, p, q, xtol=XTOL, rtol=RTOL)
        fp = fq
    return None


# ---------------------------------------------------------------------------------------------
# The piecewise integrator

@dataclass(frozen=True)
class _State:
    """State at a cycle start: phase, slide direction, relative tangential velocity u, gap z
    and gap velocity w (dimensionless)."""

    phase: str
    sigma: int = 0
    u: float = 0.0
    z: float = 0.0
    w: float = 0.0

    def close_to(self, other: _State, tol: float = STATE_TOL) -> bool:
        return (self.phase == other.phase and self.sigma == other.sigma
                and all(abs(a - b) <= tol * max(1.0, abs(a), abs(b))
                        for a, b in ((self.u, other.u), (self.z, other.z),
                                     (self.w, other.w))))


@dataclass(frozen=True)
class _Segment:
    """One phase interval inside a cycle, for trajectories."""

    cycle: int
    tau_start: float
    tau_end: float
    phase: str
    sigma: int
    x: _Motion          # relative tangential position (p0 = position at cycle start + ...)
    z: _Motion | None   # gap, in flight


class _PointMass:
    def __init__(self, c: Conveyor) -> None:
        if c.mu_k > c.mu_s:
            raise ValueError('mu_k must not exceed mu_s')
        self.c = c
        self.tan = math.tan(c.theta)
        self.gamma = c.amplitude * math.sin(c.psi) * c.omega ** 2 / c.g_n   # = c.gamma
        g_line = c.amplitude * c.omega ** 2 / c.g_n                         # G = Gamma / sin psi
        self.g_cos = g_line * math.cos(c.psi)
        self.g_sin = g_line * math.sin(c.psi)

    # tangential acceleration alpha + beta sin(tau) of each phase
    def _tangential(self, phase: str, sigma: int) -> tuple[float, float]:
        if phase == SLIDE:
            mu = self.c.mu_k * sigma
            return -self.tan - mu, self.g_cos + mu * self.g_sin
        if phase == FLIGHT:
            return -self.tan, self.g_cos
        return 0.0, 0.0

    def _from_rest(self, tau: float) -> _State:
        """Contact state of a particle at relative rest on the track at ``tau``."""
        s = math.sin(tau)
        normal = 1.0 - self.gamma * s
        if normal < 0.0:
            return _State(FLIGHT)
        demand = self.tan - self.g_cos * s          # friction needed to stay at rest
        if abs(demand) <= self.c.mu_s * normal:
            return _State(STICK)
        return _State(SLIDE, -1 if demand > 0 else 1)

    def initial_state(self) -> _State:
        return self._from_rest(0.0)

    def run_cycle(self, state: _State, cycle: int = 0,
                  segments: list[_Segment] | None = None) -> tuple[_State, float]:
        """Integrate one cycle (tau from 0 to 2 pi) from ``state``; return the state at the end
        and the relative tangential displacement over the cycle."""
        c = self.c
        tau, x = 0.0, 0.0
        for _ in range(MAX_EVENTS_PER_CYCLE):
            if tau >= TWO_PI:
                return state, x
            alpha, beta = self._tangential(state.phase, state.sigma)
            xm = _Motion(tau, 0.0, state.u, alpha, beta)
            zm = None
            if state.phase == STICK:
                # mu_s N - F and mu_s N + F with F = tan - G cos(psi) sin(tau); N = 1 - Gamma sin
                back = _first_drop(c.mu_s - self.tan, self.g_cos - c.mu_s * self.gamma,
                                   tau, TWO_PI)
                fwd = _first_drop(c.mu_s + self.tan, -self.g_cos - c.mu_s * self.gamma,
                                  tau, TWO_PI)
                lift = _first_drop(1.0, -self.gamma, tau, TWO_PI)
                options = [(t, k) for t, k in ((lift, 'lift'), (back, 'back'), (fwd, 'fwd'))
                           if t is not None]
                end, kind = min(options) if options else (TWO_PI, 'cycle')
                new = {'lift': _State(FLIGHT), 'back': _State(SLIDE, -1),
                       'fwd': _State(SLIDE, 1), 'cycle': state}[kind]
            elif state.phase == SLIDE:
                sigma = state.sigma
                lift = _first_drop(1.0, -self.gamma, tau, TWO_PI)
                limit = TWO_PI if lift is None else lift
                breaks = [t for t, _ in _sin_roots(alpha, beta, tau, limit)]
                stop = _first_zero_from_above(_scaled(xm.vel, sigma), breaks, tau, limit)
                if stop is not None:
                    end = stop
                    new = self._from_rest(end)
                elif lift is not None:
                    end = lift
                    new = _State(FLIGHT, 0, xm.vel(end))
                else:
                    end = TWO_PI
                    new = _State(SLIDE, sigma, xm.vel(end))
            else:
                zm = _Motion(tau, state.z, state.w, -1.0, self.gamma)
                acc_roots = [t for t, _ in _sin_roots(-1.0, self.gamma, tau, TWO_PI)]
                pts = [tau, *acc_roots, TWO_PI]
                vel_roots = []
                for p, q in zip(pts[:-1], pts[1:]):
                    wp, wq = zm.vel(p), zm.vel(q)
                    if wp * wq < 0.0:
                        vel_roots.append(brentq(zm.vel, p, q, xtol=XTOL, rtol=RTOL))
                land = _first_zero_from_above(zm.pos, vel_roots, tau, TWO_PI)
                if land is None:
                    end = TWO_PI
                    new = _State(FLIGHT, 0, xm.vel(end), zm.pos(end), zm.vel(end))
                else:
                    end = land
                    new = self._landing(end, xm.vel(end), zm.vel(end))
            if segments is not None and end > tau:
                segments.append(_Segment(cycle, tau, end, state.phase, state.sigma, xm, zm))
            x += xm.pos(end)
            tau, state = end, new
        raise RuntimeError(f'more than {MAX_EVENTS_PER_CYCLE} events in one cycle')

    def _landing(self, tau: float, u: float, w: float) -> _State:
        """Plastic landing with Coulomb-limited tangential impulse; the state just after."""
        impulse_n = max(-w, 0.0)
        if not self.c.frictionless_landing:
            if abs(u) <= self.c.mu_k * impulse_n:
                u = 0.0
            else:
                u -= math.copysign(self.c.mu_k * impulse_n, u)
        if 1.0 - self.gamma * math.sin(tau) < 0.0:
            return _State(FLIGHT, 0, u, 0.0, 0.0)     # the track still outruns gravity
        if u == 0.0:
            return self._from_rest(tau)
        return _State(SLIDE, 1 if u > 0 else -1, u)


def _cycle_displacements(c: Conveyor, warmup_cycles: int, cycles: int) -> list[float]:
    """Dimensionless relative displacement of each of the warmup + measured cycles.

    Once the state at a cycle start repeats an earlier one (period p <= MAX_PERIOD) and the
    cycle displacements agree, the rest is filled in by periodic repetition.
    """
    total = warmup_cycles + cycles
    pm = _PointMass(c)
    state = pm.initial_state()
    starts = [state]
    dxs: list[float] = []
    for k in range(total):
        state, dx = pm.run_cycle(state, k)
        dxs.append(dx)
        starts.append(state)
        for p in range(1, min(MAX_PERIOD, k) + 1):
            if (state.close_to(starts[k + 1 - p]) and starts[k].close_to(starts[k - p])
                    and abs(dx - dxs[k - p]) <= STATE_TOL * max(abs(dx), abs(dxs[k - p]), 1e-3)):
                while len(dxs) < total:
                    dxs.append(dxs[len(dxs) - p])
                return dxs
    return dxs


def dimensionless_speed(c: Conveyor, *, warmup_cycles: int = 40, cycles: int = 40) -> float:
    """Mean conveying speed V_m = v_m omega / (g cos theta), averaged over ``cycles`` whole
    cycles after ``warmup_cycles`` (positive = forward / uphill)."""
    if cycles < 1 or warmup_cycles < 0:
        raise ValueError('need cycles >= 1 and warmup_cycles >= 0')
    dxs = _cycle_displacements(c, warmup_cycles, cycles)
    return math.fsum(dxs[warmup_cycles:]) / (TWO_PI * cycles)


def mean_speed(c: Conveyor, *, warmup_cycles: int = 40, cycles: int = 40) -> float:
    """Mean conveying speed along the track, m/s (positive = forward / uphill)."""
    return dimensionless_speed(c, warmup_cycles=warmup_cycles, cycles=cycles) * c.velocity_scale


def trajectory(c: Conveyor, t_end: float, n_samples: int) -> dict:
    """Relative motion sampled at ``n_samples`` times in [0, t_end] (for plots).

    Returns arrays ``t`` (s), ``x`` (position along the track relative to the track's
    vibrating frame, m), ``v`` (relative velocity, m/s), ``z`` (gap above the track, m) and
    ``phase`` (labels 'stick', 'slide+', 'slide-', 'flight').
    """
    pm = _PointMass(c)
    n_cycles = max(1, math.ceil(t_end * c.frequency_hz - 1e-12))
    segments: list[_Segment] = []
    offsets = []                          # x at each cycle start
    state, x0 = pm.initial_state(), 0.0
    for k in range(n_cycles):
        offsets.append(x0)
        state, dx = pm.run_cycle(state, k, segments)
        x0 += dx
    t = np.linspace(0.0, t_end, n_samples)
    tau_abs = t * c.omega
    x = np.zeros(n_samples)
    v = np.zeros(n_samples)
    z = np.zeros(n_samples)
    phase = np.empty(n_samples, dtype=object)
    seg_ends = np.array([s.cycle * TWO_PI + s.tau_end for s in segments])
    # position at each segment start within its cycle
    seg_x0 = {}
    for i, s in enumerate(segments):
        prev = segments[i - 1] if i and segments[i - 1].cycle == s.cycle else None
        seg_x0[i] = (offsets[s.cycle] if prev is None
                     else seg_x0[i - 1] + prev.x.pos(prev.tau_end))
    for j, ta in enumerate(tau_abs):
        i = min(int(np.searchsorted(seg_ends, ta)), len(segments) - 1)
        s = segments[i]
        tau = min(max(ta - s.cycle * TWO_PI, s.tau_start), s.tau_end)
        x[j] = seg_x0[i] + s.x.pos(tau)
        v[j] = s.x.vel(tau)
        z[j] = s.z.pos(tau) if s.z is not None else 0.0
        phase[j] = ('slide+' if s.sigma > 0 else 'slide-') if s.phase == SLIDE else s.phase
    length = c.g_n / c.omega ** 2
    return {'t': t, 'x': x * length, 'v': v * c.velocity_scale, 'z': z * length,
            'phase': phase}


def conveyor_of(scene, gamma: float | None = None, friction_impulse: bool = True) -> Conveyor:
    """The point-mass conveyor of a track scene (a ``model.scene.Scene``): its track's drive
    angle, slope and frequency, its first part's friction on the track (the contact rule: the
    geometric mean of the two bodies'), the scene's gravity and the normal acceleration
    amplitude ``Gamma = a omega^2 sin(psi) / (g cos(theta))`` (or ``gamma`` instead)."""
    track = next(b for b in scene.bodies if b.name == scene.track)
    part = next(b for b in scene.bodies if b.type == 'dynamic')
    vib, theta = track.vibration, float(track.pose[2])
    g = float(np.linalg.norm(scene.gravity))
    if gamma is None:
        omega = 2 * math.pi * vib.frequency
        gamma = vib.amplitude * omega ** 2 * math.sin(vib.angle) / (g * math.cos(theta))
    return Conveyor(psi=vib.angle, theta=theta,
                    mu_s=math.sqrt(track.mu_static * part.mu_static),
                    mu_k=math.sqrt(track.mu_dynamic * part.mu_dynamic), gamma=gamma,
                    frequency_hz=vib.frequency, g=g, frictionless_landing=not friction_impulse)
