"""Single-point frictional collision in 2D: the closed-form Routh/Mirtich walk.

Routh/Mirtich integration of one collision in the contact frame (tangent, normal), closed form
in 2D: the contact velocity is ``u(p) = u0 + K p`` with the constant collision matrix ``K``;
parameterised by the normal impulse ``p_N``, the velocity moves on straight rays:

* sliding with ``sigma = sign(u_T)``: ``du/dp_N = K (-mu_dynamic sigma, 1)``;
* when ``u_T`` reaches 0 the contact sticks for the rest of the collision iff
  ``|K_TN| <= mu_static K_TT`` (then ``dp_T/dp_N = -K_TN/K_TT``), else the slip reverses and
  follows the other ray;
* compression ends at ``u_N = 0``; the collision ends by the restitution law ``law``:
  Stronge (work of the normal impulse in restitution = ``-e^2`` times that in compression;
  never creates energy), Poisson (``p_N = (1 + e) p_N,c``) or Newton (``u_N = -e u_N0``).

A sliding ray on which ``u_N`` falls (``mu sigma K_TN >= K_NN``, the impulsive Painlevé
situation of a long part with much friction) always stops the slip first in 2D, since
``K_TN^2 < K_TT K_NN``; so every collision ends. The same ray makes a contact that slides at
``u_N = 0`` take an impulse although it does not approach: Génot & Brogliato's tangential
impact, where sliding with no consistent contact force (Painlevé) ends. ``routh_collision``
walks it from ``u_N = 0`` when the ray falls there; with ``e = 0`` it ends where the normal
velocity is back to 0, the slip stopped (or reversed where sticking cannot hold).

A ray that would neither stop the slip nor end the compression ("jam") is therefore only a
round-off guard: it is finished frictionless, which dissipates, and reported by the phase bit
``jam`` and a counter.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from feeder_sim.compiled.jit import inner, jit

__all__ = ['collide', 'CollisionResult', 'LAWS', 'routh_collision']

LAWS = {'stronge': 0, 'poisson': 1, 'newton': 2}
STRONGE, POISSON, NEWTON = 0, 1, 2

# phase bits of one collision
SLIDE, STICK, REVERSE, JAM = 1, 2, 4, 8
PHASE_NAMES = ((SLIDE, 'slide'), (STICK, 'stick'), (REVERSE, 'reverse'), (JAM, 'jam'))


@dataclass
class CollisionResult:
    """One single-point collision in contact coordinates (tangent, normal)."""

    impulse: np.ndarray       # (p_T, p_N), N s
    velocity: np.ndarray      # (u_T, u_N) after the collision, m/s
    phases: tuple[str, ...]   # those that happened, in the order slide, stick, reverse, jam
    compression_impulse: float  # p_N at the end of compression, N s

    @property
    def normal_impulse(self) -> float:
        return float(self.impulse[1])

    @property
    def tangent_impulse(self) -> float:
        return float(self.impulse[0])


@inner
def _rise(un, dun, target):
    """Normal impulse along a ray until u_N reaches ``target`` (0 if already there)."""
    if un >= target:
        return 0.0
    if dun > 0.0:
        return (target - un) / dun
    return math.inf


@inner
def _termination(law, e, un0, pn, un, w, pc, wc, dun, v_sep):
    """Normal impulse from the current point of a ray to the end of the collision."""
    if law == NEWTON:
        d_law = _rise(un, dun, -e * un0)
    elif law == POISSON:
        d_law = max(0.0, (1.0 + e) * pc - pn)
    else:
        # Stronge: work of the normal impulse reaches (1 - e^2) of the compression work
        deficit = (1.0 - e * e) * wc - w
        if deficit <= 0.0:
            d_law = 0.0
        else:
            disc = un * un + 2.0 * dun * deficit
            denom = un + math.sqrt(disc) if disc >= 0.0 else -1.0
            d_law = 2.0 * deficit / denom if denom > 0.0 else math.inf
    return max(d_law, _rise(un, dun, v_sep))


@jit
def routh_collision(ktt, ktn, knn, ut0, un0, mu_d, mu_s, e, law, v_sep):
    """Closed-form 2D Routh/Mirtich collision; returns (p_T, p_N, u_T, u_N, phase bits, p_N,c).

    The walk goes ray by ray in ``p_N``: at most a sliding ray that stops the slip, then
    sticking or the reversed ray (or a frictionless finish after a jam).
    """
    pt = pn = w = 0.0
    ut, un = ut0, un0
    phases = 0
    if not un0 < 0.0:
        sigma = 1.0 if ut0 > 0.0 else -1.0
        if not (un0 == 0.0 and ut0 != 0.0 and knn - mu_d * sigma * ktn <= 0.0):
            return 0.0, 0.0, ut0, un0, 0, 0.0
    frictionless = mu_d <= 0.0 and mu_s <= 0.0
    mu_stick = max(mu_s, mu_d)
    slip_tol = 1e-12 * abs(un0)
    compressed = finished = False
    pc = wc = 0.0
    for _segment in range(6):
        length = math.inf
        if frictionless:
            dpt, dut, dun = 0.0, ktn, knn
        elif abs(ut) <= slip_tol and abs(ktn) <= mu_stick * ktt:
            ut = 0.0
            dpt, dut, dun = -ktn / ktt, 0.0, knn - ktn * ktn / ktt
            phases |= STICK
        else:
            if abs(ut) <= slip_tol:
                # sticking cannot hold: slip starts the way the coupling pushes it
                sigma = 1.0 if ktn > 0.0 else -1.0
                if phases & SLIDE:
                    phases |= REVERSE
                ut = 0.0
            else:
                sigma = 1.0 if ut > 0.0 else -1.0
            dpt = -mu_d * sigma
            dut = ktn - mu_d * sigma * ktt
            dun = knn - mu_d * sigma * ktn
            phases |= SLIDE
            if sigma * dut < 0.0:
                length = -ut / dut
            elif dun <= 0.0:
                # jam: u_N would never stop falling; finish without friction
                dpt, dut, dun = 0.0, ktn, knn
                frictionless = True
                phases |= JAM
        if not compressed:
            d_c = -un / dun if dun > 0.0 else math.inf
            if d_c > length:
                pn += length
                pt += dpt * length
                w += length * (un + 0.5 * dun * length)
                un += dun * length
                ut = 0.0
                continue
            pn += d_c
            pt += dpt * d_c
            w += d_c * (un + 0.5 * dun * d_c)
            ut += dut * d_c
            un = 0.0
            compressed = True
            pc, wc = pn, w
            length -= d_c
        d_end = _termination(law, e, un0, pn, un, w, pc, wc, dun, v_sep)
        step = min(d_end, length)
        if step < math.inf:
            pn += step
            pt += dpt * step
            w += step * (un + 0.5 * dun * step)
            ut += dut * step
            un += dun * step
        if d_end <= length and d_end < math.inf:
            finished = True
            break
        ut = 0.0       # the slip stopped at the end of this ray
    if not finished:
        # not reached for positive definite K; finish without friction to stay finite
        phases |= JAM
        d_end = _termination(law, e, un0, pn, un, w, pc, wc, knn, v_sep)
        if d_end < math.inf:
            pn += d_end
    # velocities from the impulse itself, not the walk's increments (round-off)
    ut = ut0 + ktt * pt + ktn * pn
    un = un0 + ktn * pt + knn * pn
    return pt, pn, ut, un, phases, pc


def collide(K: np.ndarray, u0: np.ndarray, mu: float, e: float, law: str = 'stronge', *,
            mu_static: float | None = None, bounce_speed: float = 0.0) -> CollisionResult:
    """Single-point collision, closed form in 2D (Routh/Mirtich integration).

    ``K``: 2x2 collision matrix in (tangent, normal) coordinates (symmetric positive definite,
    1/kg); ``u0``: pre-impact contact velocity ``(u_T, u_N)`` in m/s, ``u_N < 0`` approaching
    (otherwise nothing happens); ``mu``: sliding (dynamic) friction; ``mu_static``: the stable
    sticking test ``|K_TN| <= mu_static K_TT`` (default ``mu``); ``e``: restitution in [0, 1];
    ``law``: 'stronge', 'poisson' or 'newton'; ``bounce_speed``: least separation speed (m/s,
    the micro-collision rule; 0 for a plain collision).
    """
    K = np.asarray(K, dtype=float)
    u0 = np.asarray(u0, dtype=float)
    if K.shape != (2, 2) or u0.shape != (2,):
        raise ValueError('K must be 2x2 and u0 a 2-vector')
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(u0))):
        raise ValueError('K and u0 must be finite')
    if abs(K[0, 1] - K[1, 0]) > 1e-9 * np.abs(K).max() or K[0, 0] <= 0 or \
            np.linalg.det(K) <= 0:
        raise ValueError('K must be symmetric positive definite')
    if law not in LAWS:
        raise ValueError(f'law must be one of {", ".join(LAWS)}, got {law!r}')
    mu_s = mu if mu_static is None else mu_static
    if not (mu >= 0 and mu_s >= 0 and 0 <= e <= 1 and bounce_speed >= 0):
        raise ValueError('need mu, mu_static, bounce_speed >= 0 and 0 <= e <= 1')
    pt, pn, ut, un, phases, pc = routh_collision(K[0, 0], 0.5 * (K[0, 1] + K[1, 0]), K[1, 1],
                                          u0[0], u0[1], float(mu), float(mu_s), float(e),
                                          LAWS[law], float(bounce_speed))
    return CollisionResult(np.array([pt, pn]), np.array([ut, un]),
                           tuple(name for bit, name in PHASE_NAMES if phases & bit), pc)
