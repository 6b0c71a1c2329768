"""Frictional boxed LCP solver for 2D contact impulses and resting-contact forces.

Problem
-------
``w = A x + b`` with ``A`` (m, m), not necessarily symmetric. Row k is a *normal row* when
``normal_of[k] == -1``::

    x_k >= 0,  w_k >= 0,  x_k w_k = 0

otherwise a *friction row* of normal row ``j = normal_of[k]`` with bounds proportional to x_j::

    lo_k = -mu_lo[k] x_j,  hi_k = mu_hi[k] x_j
    x_k = lo_k  =>  w_k >= 0;   lo_k < x_k < hi_k  =>  w_k = 0;   x_k = hi_k  =>  w_k <= 0

(``lo = hi = 0`` forces x_k = 0 and leaves w_k free). Impulse problems use w_N = v'_N + e v_N,
w_T = v'_T; static friction is ``(mu_s, mu_s)``, Kawachi's one-sided dynamic friction ("no
reversal") is ``(mu_d, 0)`` for pre-impact slip v_T > 0 and ``(0, mu_d)`` for v_T < 0. In 2D
the Coulomb cone is exactly this interval, so no pyramid approximation is involved.

Baraff-Dantzig pivoting (method ``'dantzig'``)
----------------------------------------------
Rows are treated one at a time: the most negative untreated normal row, then the friction rows
of the normals that are clamped (a normal row, then its friction row). Every treated row lives
in one set:

* ``C``  clamped: w = 0 and x free (normal x >= 0; friction lo <= x <= hi);
* ``NC`` a normal row not clamped: x = 0, w >= 0;
* ``NC-`` / ``NC+`` a friction row at its lower / upper bound, x slaved to -mu_lo x_j / mu_hi x_j,
  w >= 0 / w <= 0. Slaving substitutes the friction column into its normal's column
  (``A[:, j] + c A[:, k]``), which is what makes the clamped system non-symmetric;
* deferred: a friction row with w = 0 that is linearly dependent on the clamped rows (the second
  contact of a box edge on a flat) stays at x = 0 instead of making the clamped system singular.

Untreated rows hold x = 0, which is always inside a friction interval, so they may be ignored
until they are driven; the friction rows of a normal that opens become untreated again. Driving
row d moves x_d (normal: up from 0; friction: towards the bound that reduces |w_d|) while the
clamped equations stay satisfied (one linear solve per pivot) and slaved rows follow their
normals. The step is the smallest of: d reaching its target (w_d = 0, or for friction the bound
matching the sign of w_d); a clamped normal reaching x = 0 (-> NC); an NC normal's w reaching 0
(-> C); a clamped friction row reaching its bound, where the bound moves with the step,
``mu (x_j + s dx_j)``, so the crossing is solved exactly (no frozen "findex" bounds); a slaved
friction row's w crossing 0 (-> C); a deferred row's w starting to move because a row it
depended on left C (-> C). Ties prefer finishing d, then the lowest row index.

Degeneracy and failure modes:

* zero-length steps are allowed; a state (sets, event, direction) that repeats without a
  positive step in between is cycling. Before giving up, untreated friction rows of active
  normals whose w is already 0 are clamped (this rescues a saturated row whose redundant twin
  is still waiting for its turn);
* a *fold*: right after a row changes set it would change straight back (with friction its
  Schur complement can be negative, so both sets are infeasible in the current direction).
  Like Lemke's method, the drive then follows the solution path with x_d moving backwards;
  returning to x_d = 0 (or a friction row reaching the bound of the wrong sign) aborts;
* a singular clamped system (tiny LU pivot) is solved in the minimum-norm least-squares sense;
* no admissible step at all (dw_d <= 0 and nothing else changes: infeasible, or a Painleve-like
  non-PSD A) aborts, as does the pivot cap (default 50 m + 50 over both passes below).

A failed pass is retried once with all normal rows treated before any friction row, since with
friction the outcome depends on the order. After a successful pass the final sets are solved
again in one piece ("polish") when enough pivots happened for round-off to matter.

Fallback ladder
---------------
``solve`` runs the methods in order and returns the first candidate whose ``residual`` is within
``tol``: ``'dantzig'`` -> ``'lemke'`` (standard LCP: friction split into x+ and x- with a slack per
side, Lemke's complementary pivoting with an artificial variable, lexicographic ratio test, ray
termination) -> ``'pgs'`` (projected Gauss-Seidel, bounds from the current normals) ->
``'frictionless'`` (friction x = 0, normal rows alone by Dantzig, else PGS). A problem whose normal
rows all have b >= 0 is answered by x = 0 (``'trivial'``) without running any of them. Every
candidate is checked with ``residual`` (within ``tol``) and with the same measure on the velocity
scale of b alone (``S = max|b|``, not grown by the candidate's own ``max|A| max|x|``; within
``sqrt(tol)``): the round-off of an exact answer to an ill-conditioned problem passes, but where A
is singular (a wedged part, redundant corners) a squeeze along its null space does not, which Lemke
has answered with 2.4e9 N s, a residual of 1e-14 and 0.035 m/s of velocity error (3 on b's scale).
A non-finite or inaccurate candidate counts as a failure (``fallbacks`` += 1, the reason goes to
``message``). If every method fails, the finite candidate with the smallest residual on b's scale
is returned with ``converged=False``; a result reports the scale-free ``residual``. ``solve`` never
raises for well-formed input (``FrictionalLCP`` validates it), never loops without bound and never
returns NaN or inf.

Guarantees and limits: frictionless PSD problems (Delassus matrices, singular or not) are what
Baraff's method is proven for; with friction the solution may not exist or not be unique and
pivoting may fail, which is what the ladder is for. Lemke certifies nothing either for these
(non-copositive) matrices; ray termination is reported as failure.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

import numpy as np
from scipy.linalg.lapack import dgetrf, dgetrs

__all__ = ['FrictionalLCP', 'LCPResult', 'METHODS', 'residual', 'solve']

METHODS = ('dantzig', 'lemke', 'pgs', 'frictionless')


@dataclass(frozen=True)
class FrictionalLCP:
    """``w = A x + b`` with normal rows (``normal_of == -1``) and friction rows bounded by
    ``[-mu_lo x_j, mu_hi x_j]``, ``j = normal_of[k]``. Arrays are converted to float / int."""

    A: np.ndarray
    b: np.ndarray
    normal_of: np.ndarray
    mu_lo: np.ndarray
    mu_hi: np.ndarray

    def __post_init__(self) -> None:
        # Built for every contact solve, so the common (valid) case is checked with few
        # reductions; the per-field checks only run to name the culprit.
        b = np.asarray(self.b, dtype=float)
        if b.ndim != 1:
            raise ValueError(f'b must be 1-D, got shape {b.shape}')
        m = b.shape[0]
        A = np.asarray(self.A, dtype=float)
        if A.shape != (m, m):
            raise ValueError(f'A must have shape ({m}, {m}), got {A.shape}')
        if m and not (math.isfinite(float(A.sum())) and math.isfinite(float(b.sum()))):
            if not np.isfinite(A).all():
                raise ValueError('A must be finite')
            if not np.isfinite(b).all():
                raise ValueError('b must be finite')
        normal_of = np.asarray(self.normal_of)
        if normal_of.shape != (m,):
            raise ValueError(f'normal_of must have shape ({m},), got {normal_of.shape}')
        if normal_of.dtype.kind not in 'iu':
            if m and not np.array_equal(normal_of, np.round(normal_of)):
                raise ValueError('normal_of must hold integers')
            normal_of = normal_of.astype(np.intp)
        mus = []
        for name in ('mu_lo', 'mu_hi'):
            mu = np.asarray(getattr(self, name), dtype=float)
            if mu.shape != (m,):
                raise ValueError(f'{name} must have shape ({m},), got {mu.shape}')
            # min catches negatives and NaN (not >= 0), max catches inf
            if m and not (float(mu.min()) >= 0.0 and float(mu.max()) < math.inf):
                raise ValueError(f'{name} must be finite and >= 0')
            mus.append(mu)
        if m:
            if int(normal_of.min()) < -1 or int(normal_of.max()) >= m:
                raise ValueError('normal_of must be -1 or a row index')
            target = normal_of[np.maximum(normal_of, 0)]
            if ((normal_of >= 0) & (target != -1)).any():
                raise ValueError('normal_of must refer to normal rows (normal_of[j] == -1)')
        for name, value in (('A', A), ('b', b), ('normal_of', normal_of), ('mu_lo', mus[0]),
                            ('mu_hi', mus[1])):
            object.__setattr__(self, name, value)


@dataclass
class LCPResult:
    x: np.ndarray
    w: np.ndarray
    method: str        # 'trivial' | 'dantzig' | 'lemke' | 'pgs' | 'frictionless'
    pivots: int        # pivots (PGS: sweeps) spent over all methods tried
    fallbacks: int     # methods that failed before the one that answered
    residual: float    # residual(problem, x)
    converged: bool    # residual <= tol
    message: str       # why methods were abandoned, '' if none


# ---------------------------------------------------------------------------------------------
# problem data shared by the solvers, and the residual


class _Data:
    """The problem arrays plus the index sets and scales that every solver and the residual
    reuse (built once per solve so that small problems stay cheap)."""

    __slots__ = ('A', 'b', 'normal_of', 'mu_lo', 'mu_hi', 'm', 'nidx', 'fidx', 'fnorm', 'flo',
                 'fhi', 'amax', 'bmax')

    def __init__(self, A: np.ndarray, b: np.ndarray, normal_of: np.ndarray, mu_lo: np.ndarray,
                 mu_hi: np.ndarray) -> None:
        self.A, self.b, self.normal_of, self.mu_lo, self.mu_hi = A, b, normal_of, mu_lo, mu_hi
        self.m = b.shape[0]
        fr = normal_of >= 0
        self.nidx = np.flatnonzero(~fr)
        self.fidx = np.flatnonzero(fr)
        self.fnorm = normal_of[self.fidx]
        self.flo = mu_lo[self.fidx]
        self.fhi = mu_hi[self.fidx]
        self.amax = float(np.abs(A).max()) if self.m else 0.0
        self.bmax = float(np.abs(b).max()) if self.m else 0.0

    @classmethod
    def of(cls, problem: FrictionalLCP) -> _Data:
        return cls(problem.A, problem.b, problem.normal_of, problem.mu_lo, problem.mu_hi)

    def residual(self, x: np.ndarray, on_b: bool = False) -> float:
        """``residual``; ``on_b``: on the velocity scale of b alone (see ``solve``)."""
        if self.m == 0:
            return 0.0
        w = self.A @ x + self.b
        xmax = float(np.abs(x).max())
        if not (math.isfinite(xmax) and math.isfinite(float(w.sum()))):
            return math.inf     # also keeps NaN out of the max() below
        s_w = max(1e-300, self.bmax, 0.0 if on_b else self.amax * xmax)
        s_x = s_w / self.amax if self.amax > 0.0 else max(1e-300, xmax)
        if self.m <= 12:
            return self._residual_small(x.tolist(), w.tolist(), s_x, s_w)
        r = 0.0
        if self.nidx.size:
            xn, wn = x[self.nidx], w[self.nidx]
            r = max(-float(xn.min()) / s_x, -float(wn.min()) / s_w,
                    float(np.abs(xn * wn).max()) / (s_x * s_w))
        if self.fidx.size:
            xj = np.maximum(x[self.fnorm], 0.0)
            xk, wk = x[self.fidx], w[self.fidx]
            dl = xk + self.flo * xj
            dh = self.fhi * xj - xk
            away = np.where(wk > 0.0, wk * np.maximum(dl, 0.0), -wk * np.maximum(dh, 0.0))
            r = max(r, -float(dl.min()) / s_x, -float(dh.min()) / s_x,
                    float(away.max()) / (s_x * s_w))
        return max(r, 0.0)

    def _residual_small(self, x: list[float], w: list[float], s_x: float, s_w: float) -> float:
        """Same formula as ``residual`` row by row: cheaper than numpy calls for tiny m."""
        r = 0.0
        nof, lo, hi = self.normal_of.tolist(), self.mu_lo.tolist(), self.mu_hi.tolist()
        for k, j in enumerate(nof):
            xk, wk = x[k], w[k]
            if j < 0:
                r = max(r, -xk / s_x, -wk / s_w, abs(xk * wk) / (s_x * s_w))
            else:
                xj = max(x[j], 0.0)
                dl = xk + lo[k] * xj
                dh = hi[k] * xj - xk
                away = wk * max(dl, 0.0) if wk > 0.0 else -wk * max(dh, 0.0)
                r = max(r, -dl / s_x, -dh / s_x, away / (s_x * s_w))
        return r


def residual(problem: FrictionalLCP, x: np.ndarray) -> float:
    """Scale-free violation of the frictional LCP conditions by ``x`` (0 = exact solution).

    With ``w = A x + b``, ``S = max(1e-300, max|b|, max|A| max|x|)`` and ``X = S / max|A|``,
    quantities are normalised as ``x^ = x / X`` and ``w^ = w / S`` (so the largest entries of
    x^ and w^ are O(1)). The residual is the largest of

    * normal rows: ``-x^``, ``-w^`` (sign violations) and ``|x^ w^|`` (complementarity);
    * friction rows, with ``d_lo = x^ - lo^`` and ``d_hi = hi^ - x^`` (bounds from the
      non-negative part of the normal, ``max(x_j, 0)``): ``-d_lo``, ``-d_hi`` (bound
      violations), ``max(w^, 0) d_lo`` (positive w away from the lower bound) and
      ``max(-w^, 0) d_hi`` (negative w away from the upper bound).

    The two friction products decide "at a bound" with a relative band instead of a fixed one:
    a row whose normalised distance to a bound times its normalised w is below the tolerance
    counts as being at that bound. An interior row therefore needs w = 0, and a row with
    lo = hi = 0 leaves w free. Non-finite x gives ``inf``; m = 0 gives 0.
    """
    return _Data.of(problem).residual(np.asarray(x, dtype=float))


# ---------------------------------------------------------------------------------------------
# Baraff-Dantzig pivoting

# _Z: a friction row deferred at x = 0 (interior) because it is linearly dependent on the
# clamped rows; its w stays 0 as long as that dependence lasts
_U, _C, _NC, _L, _H, _DEAD, _Z = 0, 1, 2, 3, 4, 5, 6
# ratio-test events: the driving row finishes (clamped / at lower / at upper bound) or would
# need an invalid bound; a clamped normal opens; an open normal closes; a clamped friction
# row reaches its lower / upper bound; a slaved friction row's w crosses zero; a deferred row's
# w starts to move (it is no longer dependent)
_DONE_C, _DONE_L, _DONE_H, _BAD, _C_NC, _NC_C, _C_L, _C_H, _SL_C, _Z_C = range(10)
# the set an event moves its row into (the driving row for _DONE_*; _BAD never moves a row)
_ENTERS = (_C, _L, _H, _U, _NC, _C, _L, _H, _C, _C)


class _Abort(Exception):
    pass


def _reverses(first: int, second: int) -> bool:
    """Whether event ``second`` on a row undoes event ``first`` on the same row."""
    return ((first in (_C_L, _C_H) and second == _SL_C)
            or (first == _SL_C and second in (_C_L, _C_H))
            or (first == _C_NC and second == _NC_C) or (first == _NC_C and second == _C_NC))


class _Dantzig:
    """One Baraff-Dantzig pass. ``run`` returns '' on success or why it gave up.

    The bookkeeping loops over rows in Python on lists: for the small problems that dominate
    a simulation this is several times cheaper than many tiny numpy calls, and for m in the
    hundreds the per-pivot linear solve dominates anyway.
    """

    EPS_W = 1e-12     # |w| below EPS_W * (scale of w) counts as zero
    # A normal row counts as separating (NC) when w_i >= -EPS_ROW * sum_j |A_ij x_j| as well:
    # the round-off of w_i is set by the terms summed into it, not by the problem's largest
    # entry and impulse. A light body under a heavy one (mass ratio 1e6) has a real approach
    # velocity of 1e-8 m/s at a corner that the global scale (max|A| max|x| ~ 1e4 m/s) hides;
    # accepted as zero, the light body rocks and sinks by that much every step.
    EPS_ROW = 1e-13
    EPS_RATE = 1e-11  # rates below EPS_RATE * max|A| * max|dx| are round-off

    def __init__(self, data: _Data, max_pivots: int, normals_first: bool = False) -> None:
        m = data.m
        self.data = data
        self.A, self.b, self.m = data.A, data.b, m
        nof = data.normal_of.tolist()
        self.nof = nof
        self.isn = [j < 0 for j in nof]
        self.lo = data.mu_lo.tolist()
        self.hi = data.mu_hi.tolist()
        self.frics: list[list[int]] = [[] for _ in range(m)]
        for k, j in enumerate(nof):
            if j >= 0:
                self.frics[j].append(k)
        # friction rows with lo = hi = 0 are x = 0 with w free: nothing to decide
        self.st = [_DEAD if j >= 0 and self.lo[k] == 0.0 and self.hi[k] == 0.0 else _U
                   for k, j in enumerate(nof)]
        self.x = [0.0] * m
        self.w = data.b.tolist()
        self.amax = data.amax or 1.0
        self.bmax = data.bmax
        self.max_pivots = max_pivots
        self.pivots = 0
        self.nodefer = [False] * m
        self.singular = 0
        self.normals_first = normals_first

    # -- linear algebra ---------------------------------------------------------------------

    def _eps_w(self) -> float:
        xmax = max(map(abs, self.x), default=0.0)
        return self.EPS_W * max(self.bmax, self.amax * xmax, 1e-300)

    def _approaching(self, rows: list[int]) -> list[int]:
        """The normal rows among ``rows`` whose negative w exceeds their own round-off
        (``EPS_ROW`` times the terms summed into w_i; ``EPS_W * max|b|`` at least)."""
        w = self.w
        neg = [i for i in rows if w[i] < 0.0]
        if not neg:
            return []
        scale = np.abs(self.A[neg]) @ np.abs(np.array(self.x))
        floor = self.EPS_W * max(self.bmax, 1e-300)
        return [i for i, s in zip(neg, scale.tolist(), strict=True)
                if w[i] < -max(floor, self.EPS_ROW * s)]

    def _solve(self, M: np.ndarray, r: np.ndarray) -> np.ndarray:
        n = r.shape[0]
        if n <= 2:
            # closed forms: most systems are this small and numpy's overhead would dominate
            if n == 1:
                a = float(M[0, 0])
                if abs(a) > 1e-13 * self.amax:
                    return r / a
            else:
                (a, b), (c, d) = M.tolist()
                det = a * d - b * c
                if abs(det) > 1e-12 * (abs(a * d) + abs(b * c)):
                    r0, r1 = r.tolist()
                    return np.array([(d * r0 - b * r1) / det, (a * r1 - c * r0) / det])
            self.singular += 1
            return np.linalg.lstsq(M, r, rcond=1e-12)[0]
        lu, piv, info = dgetrf(M)
        if info == 0:
            u = np.abs(np.diag(lu))
            if u.min() > 1e-12 * u.max():
                y, info = dgetrs(lu, piv, r)
                if info == 0 and np.isfinite(y).all():
                    return y
        # Redundant clamped rows (a tiny pivot): the minimum-norm solution keeps the
        # consistent part exact instead of sending the null-space component to 1e16.
        self.singular += 1
        return np.linalg.lstsq(M, r, rcond=1e-12)[0]

    def _columns(self, V: list[int]) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
        """Columns of the free unknowns V with slaved friction columns substituted into their
        (active) normals' columns; also the slaved rows as (row, normal, coefficient)."""
        st, nof, A = self.st, self.nof, self.A
        cols = A[:, V]
        pos = {v: p for p, v in enumerate(V)}
        slaved = []
        for k in range(self.m):
            s = st[k]
            if s == _L or s == _H:
                p = pos.get(nof[k])
                if p is not None:
                    c = -self.lo[k] if s == _L else self.hi[k]
                    if c != 0.0:
                        cols[:, p] += c * A[:, k]
                    slaved.append((k, nof[k], c))
        return cols, slaved

    def _direction(self, d: int, sigma: float) -> tuple[list[float], list[float]]:
        """Unit move of x_d by sigma keeping clamped rows' w fixed; returns (dx, dw)."""
        st, m = self.st, self.m
        cset = [i for i in range(m) if st[i] == _C]
        V = cset + [d]
        cols, slaved = self._columns(V)
        nc = len(cset)
        dxv = np.empty(nc + 1)
        dxv[nc] = sigma
        if nc:
            dxv[:nc] = self._solve(cols[cset, :nc], -sigma * cols[cset, nc])
        dw = (cols @ dxv).tolist()
        dx = [0.0] * m
        for v, val in zip(V, dxv.tolist()):
            dx[v] = val
        for k, j, c in slaved:
            dx[k] = c * dx[j]
        return dx, dw

    def _sync(self, d: int) -> None:
        """Re-impose the exact x of rows whose x is fixed by their set, then refresh w."""
        st, x, nof = self.st, self.x, self.nof
        for i in range(self.m):
            s = st[i]
            if i == d or s == _C:
                continue
            if s == _L or s == _H:
                j = nof[i]
                if st[j] == _C or j == d:
                    x[i] = (-self.lo[i] if s == _L else self.hi[i]) * x[j]
                else:
                    x[i] = 0.0
            else:
                x[i] = 0.0
        self.w = (self.A @ np.array(x) + self.b).tolist()

    # -- pivoting ---------------------------------------------------------------------------

    def _drive(self, d: int, sigma: float) -> None:
        st, isn, nof, lo, hi, m = self.st, self.isn, self.nof, self.lo, self.hi, self.m
        seen: set[tuple] = set()
        prev: tuple[int, int] | None = None
        while True:
            if self.pivots >= self.max_pivots:
                raise _Abort(f'pivot cap {self.max_pivots} reached driving row {d}')
            dx, dw = self._direction(d, sigma)
            x, w = self.x, self.w
            dxmax = max(1.0, max(map(abs, dx)))
            dtol = self.EPS_RATE * self.amax * dxmax
            xr = 1e-13 * dxmax
            # candidates (step, priority, row, event); priority 0 finishes d, 2 is invalid
            cands: list[tuple[float, int, int, int]] = []
            if isn[d]:
                if dw[d] > dtol:
                    cands.append((max(0.0, -w[d] / dw[d]), 0, d, _DONE_C))
                if sigma < 0.0:
                    # after a fold x_d runs backwards; back at 0 the drive has failed
                    cands.append((max(0.0, x[d]), 2, d, _BAD))
            else:
                if (w[d] > 0.0 and dw[d] < -dtol) or (w[d] < 0.0 and dw[d] > dtol):
                    cands.append((max(0.0, -w[d] / dw[d]), 0, d, _DONE_C))
                # reaching the bound that matches the sign of w_d finishes d; the other one
                # (possible when the bounds move) is a dead end
                j = nof[d]
                rate = -dx[d] - lo[d] * dx[j]
                if rate > xr:
                    good = w[d] > 0.0
                    cands.append((max(0.0, (x[d] + lo[d] * x[j]) / rate),
                                  0 if good else 2, d, _DONE_L if good else _BAD))
                rate = dx[d] - hi[d] * dx[j]
                if rate > xr:
                    good = w[d] < 0.0
                    cands.append((max(0.0, (hi[d] * x[j] - x[d]) / rate),
                                  0 if good else 2, d, _DONE_H if good else _BAD))
            for i in range(m):
                s = st[i]
                if i == d or s == _U or s == _DEAD:
                    continue
                if isn[i]:
                    if s == _C:
                        if dx[i] < -xr:
                            cands.append((max(0.0, x[i] / -dx[i]), 1, i, _C_NC))
                    elif dw[i] < -dtol:
                        cands.append((max(0.0, w[i] / -dw[i]), 1, i, _NC_C))
                    continue
                j = nof[i]
                if s == _C:
                    # the bounds move with the normal: x_i + t dx_i = mu (x_j + t dx_j)
                    rate = -dx[i] - lo[i] * dx[j]
                    if rate > xr:
                        cands.append((max(0.0, (x[i] + lo[i] * x[j]) / rate), 1, i, _C_L))
                    rate = dx[i] - hi[i] * dx[j]
                    if rate > xr:
                        cands.append((max(0.0, (hi[i] * x[j] - x[i]) / rate), 1, i, _C_H))
                elif st[j] == _C or j == d:
                    if s == _L:
                        if dw[i] < -dtol:
                            cands.append((max(0.0, w[i] / -dw[i]), 1, i, _SL_C))
                    elif s == _H:
                        if dw[i] > dtol:
                            cands.append((max(0.0, -w[i] / dw[i]), 1, i, _SL_C))
                    elif abs(dw[i]) > dtol:
                        # a clamped row it depended on has left C: clamp it now, before its
                        # w moves (this lets a redundant twin take over a saturated row's load)
                        cands.append((0.0, 1, i, _Z_C))
            if not cands:
                kind = 'normal' if isn[d] else 'friction'
                raise _Abort(f'no admissible step driving {kind} row {d} (dw_d = {dw[d]:.3g}: '
                             'infeasible, or non-PSD / Painleve-like)')
            smin = min(c[0] for c in cands)
            if not math.isfinite(smin):
                raise _Abort(f'non-finite step driving row {d}')
            lim = smin * (1.0 + 1e-12)
            _, prio, i, code = min((c for c in cands if c[0] <= lim), key=lambda c: c[1:3])
            if code == _BAD:
                raise _Abort(f'row {d} reached an invalid end (start or wrong bound) while '
                             'being driven')
            self.pivots += 1
            xscale = max(max(map(abs, x)), self.bmax / self.amax, 1e-300)
            if smin * dxmax > 1e-13 * xscale:
                seen.clear()
            else:
                key = (tuple(st), i, code, sigma)
                if key in seen:
                    if not self._rescue(d):
                        raise _Abort(f'cycling (repeated degenerate state) driving row {d}')
                    seen.clear()
                    prev = None
                    continue
                seen.add(key)
                if prev is not None and prev[0] == i and _reverses(prev[1], code):
                    # Fold of the solution path: the row that just changed set is infeasible
                    # in both sets for this direction (its Schur complement is negative, as
                    # with friction slaving). Lemke-style, follow the path backwards in x_d.
                    sigma = -sigma
                    prev = None
                    continue
            prev = (i, code)
            for r in range(m):
                x[r] += smin * dx[r]
            st[d if code <= _DONE_H else i] = _ENTERS[code]
            if code == _C_NC:
                x[i] = 0.0
                # an open contact has no friction; its rows are treated again if it closes
                for k in self.frics[i]:
                    if st[k] != _DEAD:
                        st[k] = _U
                        x[k] = 0.0
            self._sync(d)
            if prio == 0:
                return

    def _rescue(self, d: int) -> bool:
        """On cycling: clamp untreated friction rows of active normals whose w is already 0.

        A row waiting for its turn is invisible to the drive; when it is the redundant twin
        of a row being pushed against its bound (two contacts of one edge), the drive cycles
        between that row's C and NC+/- sets. Clamping the waiting row at x = 0 moves nothing
        and lets it take over the load. Returns whether any row was clamped."""
        eps = self._eps_w()
        st, nof = self.st, self.nof
        waiting = [k for k in range(self.m) if st[k] == _U and not self.isn[k]
                   and (st[nof[k]] == _C or nof[k] == d) and abs(self.w[k]) <= eps]
        for k in waiting:
            st[k] = _C
        return bool(waiting)

    def _dependent(self, k: int) -> bool:
        dx, dw = self._direction(k, 1.0)
        return abs(dw[k]) <= self.EPS_RATE * self.amax * max(1.0, max(map(abs, dx)))

    def _treat_friction(self, k: int) -> None:
        w = self.w[k]
        if abs(w) <= self._eps_w():
            if not self.nodefer[k] and self._dependent(k):
                self.st[k] = _Z
            else:
                self.st[k] = _C
        elif w > 0.0:
            if self.lo[k] == 0.0:
                self.st[k] = _L
            else:
                self._drive(k, -1.0)
        elif self.hi[k] == 0.0:
            self.st[k] = _H
        else:
            self._drive(k, 1.0)

    def run(self) -> str:
        try:
            self._main()
        except _Abort as exc:
            return str(exc)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError, ZeroDivisionError,
                OverflowError) as exc:
            return f'numerical failure: {exc}'
        return ''

    def _main(self) -> None:
        st, isn, nof, m = self.st, self.isn, self.nof, self.m
        budget = 20 * (self.max_pivots + m) + 100
        while True:
            budget -= 1
            if budget < 0:
                raise _Abort('row-selection budget exhausted')
            nr = [i for i in range(m) if st[i] == _U and isn[i]]
            fr = [k for k in range(m) if st[k] == _U and not isn[k] and st[nof[k]] == _C]
            if fr and not (self.normals_first and nr):
                self._treat_friction(fr[0])
                continue
            if nr:
                w = self.w
                j = min(nr, key=w.__getitem__)
                eps = self._eps_w()
                if w[j] >= -eps:
                    # zero on the problem's scale; some row may still approach on its own
                    late = self._approaching(nr)
                    if late:
                        self._drive(min(late, key=w.__getitem__), 1.0)
                        continue
                    for i in nr:
                        st[i] = _NC
                else:
                    self._drive(j, 1.0)
                continue
            # deferred (dependent) friction rows are fine at x = 0 while their w stays 0;
            # round-off below the event threshold can still move it: then drive the row
            eps = self._eps_w()
            bad = [k for k in range(m) if st[k] == _Z and st[nof[k]] == _C
                   and abs(self.w[k]) > eps]
            if not bad:
                break
            st[bad[0]] = _U
            self.nodefer[bad[0]] = True
        self._polish()

    def _polish(self) -> None:
        """Solve the final sets in one piece so that round-off from the pivots does not stay.

        Skipped after a few well-conditioned pivots, whose round-off is already negligible."""
        cset = [i for i in range(self.m) if self.st[i] == _C]
        if not cset or (self.pivots <= 4 and not self.singular):
            return
        cols, slaved = self._columns(cset)
        y = self._solve(cols[cset], -self.b[cset])
        if not np.isfinite(y).all():
            return
        x = np.zeros(self.m)
        x[cset] = y
        for k, j, c in slaved:
            x[k] = c * x[j]
        if self.data.residual(x) <= self.data.residual(np.array(self.x)):
            self.x = x.tolist()


def _dantzig(data: _Data, max_pivots: int) -> tuple[np.ndarray, int, str]:
    solver = _Dantzig(data, max_pivots)
    msg = solver.run()
    if not msg or not data.fidx.size or solver.pivots >= max_pivots:
        return np.array(solver.x), solver.pivots, msg
    # With friction, success depends on the treatment order; one retry with every normal row
    # treated before any friction row rescues most of the remaining failures.
    retry = _Dantzig(data, max_pivots - solver.pivots, normals_first=True)
    msg2 = retry.run()
    pivots = solver.pivots + retry.pivots
    if not msg2:
        return np.array(retry.x), pivots, ''
    # both aborted: hand on the closer of the two partial states (it may still pass the check)
    x1, x2 = np.array(solver.x), np.array(retry.x)
    x = x2 if data.residual(x2) < data.residual(x1) else x1
    return x, pivots, f'{msg}; normals-first retry: {msg2}'


# ---------------------------------------------------------------------------------------------
# Lemke


def _lemke_core(M: np.ndarray, q: np.ndarray, max_iter: int) -> tuple[np.ndarray, int, str]:
    """Standard LCP ``w = M z + q >= 0, z >= 0, z'w = 0`` by Lemke's method (covering vector 1).

    Variables: 0..n-1 are w, n..2n-1 are z, 2n is the artificial z0. The basis inverse is
    kept explicitly (rank-1 update per pivot, rebuilt every 200 pivots and before a ray
    termination is accepted). Returns (z, pivots, msg); msg is '' when z0 left the basis.
    """
    n = q.shape[0]
    if (q >= 0).all():
        return np.zeros(n), 0, ''
    scale = max(1e-300, float(np.abs(M).max()))
    zscale = max(1e-300, float(np.abs(q).max())) / scale

    basis = np.arange(n)
    Binv = np.eye(n)
    rhs = q.astype(float)
    B_all = np.hstack([np.eye(n), -M, -np.ones((n, 1))])    # columns of every variable

    def pivot(r: int, col: np.ndarray, entering: int) -> int:
        leaving = int(basis[r])
        prow = Binv[r] / col[r]
        prhs = rhs[r] / col[r]
        Binv[...] -= np.outer(col, prow)
        rhs[...] -= col * prhs
        Binv[r] = prow
        rhs[r] = prhs
        basis[r] = entering
        return leaving

    def refactor(final: bool) -> None:
        # Round-off of the rank-1 updates accumulates: rebuild the inverse now and then, and
        # the basic values once more from the original columns at the end.
        B = B_all[:, basis]
        try:
            if final:
                fresh = np.linalg.solve(B, q)
            else:
                inv = np.linalg.inv(B)
                fresh = inv @ q
                if np.isfinite(inv).all():
                    Binv[...] = inv
        except np.linalg.LinAlgError:
            return
        if np.isfinite(fresh).all():
            rhs[...] = np.maximum(fresh, 0.0)

    leaving = pivot(int(np.argmin(q)), -np.ones(n), 2 * n)
    np.maximum(rhs, 0.0, out=rhs)
    pivots = 1
    fresh_since = 1       # pivots since the inverse was last rebuilt
    while True:
        entering = leaving + n if leaving < n else leaving - n
        if pivots >= max_iter:
            return _lemke_z(basis, rhs, n), pivots, f'iteration cap {max_iter} reached'
        col = Binv @ B_all[:, entering]
        cand = np.flatnonzero(col > 1e-11 * max(float(np.abs(col).max()), 1e-3 * scale))
        if not cand.size and fresh_since > 0:
            # a ray ends the run: make sure it is not drift of the updated inverse
            refactor(final=False)
            fresh_since = 0
            col = Binv @ B_all[:, entering]
            cand = np.flatnonzero(col > 1e-11 * max(float(np.abs(col).max()), 1e-3 * scale))
        if not cand.size:
            return _lemke_z(basis, rhs, n), pivots, 'ray termination (no solution found)'
        ratio = rhs[cand] / col[cand]
        rmin = float(ratio.min())
        ties = cand[ratio <= rmin * (1.0 + 1e-12) + 1e-14 * zscale]
        art = ties[basis[ties] == 2 * n]
        if art.size:
            r = int(art[0])     # z0 can leave: take it, that ends the run
        else:
            # lexicographic rule: degenerate (tied) ratios cannot cycle
            for c in range(n):
                if ties.size == 1:
                    break
                v = Binv[ties, c] / col[ties]
                vmin = float(v.min())
                ties = ties[v <= vmin + 1e-12 * max(abs(vmin), float(np.abs(v).max()))]
            r = int(ties[0])
        leaving = pivot(r, col, entering)
        np.maximum(rhs, 0.0, out=rhs)
        pivots += 1
        if leaving == 2 * n:
            refactor(final=True)
            return _lemke_z(basis, rhs, n), pivots, ''
        fresh_since += 1
        if fresh_since >= 200:
            refactor(final=False)
            fresh_since = 0


def _lemke_z(basis: np.ndarray, rhs: np.ndarray, n: int) -> np.ndarray:
    z = np.zeros(n)
    zb = (basis >= n) & (basis < 2 * n)
    z[basis[zb] - n] = rhs[zb]
    return z


def _lemke(data: _Data, max_pivots: int | None) -> tuple[np.ndarray, int, str]:
    """Map the frictional problem to a standard LCP, solve it by Lemke, map x back.

    z = [x_N, x+_k (mu_hi > 0), x-_k (mu_lo > 0), lam+_k, lam-_k] with x_k = x+ - x-;
    x+ _|_ w_k + lam+,  x- _|_ -w_k + lam-,  lam+ _|_ mu_hi x_j - x+,  lam- _|_ mu_lo x_j - x-.
    A one-sided row needs only the side whose mu is positive; lo = hi = 0 rows drop out.
    """
    A, b, normal_of, mu_lo, mu_hi, m = (data.A, data.b, data.normal_of, data.mu_lo,
                                        data.mu_hi, data.m)
    nrm = data.nidx
    fr = normal_of >= 0
    fp = np.flatnonzero(fr & (mu_hi > 0))
    fm = np.flatnonzero(fr & (mu_lo > 0))
    nn, npl, nmi = nrm.size, fp.size, fm.size
    o_p, o_m, o_lp, o_lm = nn, nn + npl, nn + npl + nmi, nn + 2 * npl + nmi
    n = o_lm + nmi
    P = np.zeros((m, o_lp))          # x = P z[:o_lp]
    P[nrm, np.arange(nn)] = 1.0
    P[fp, o_p + np.arange(npl)] = 1.0
    P[fm, o_m + np.arange(nmi)] = -1.0
    AP = A @ P
    M = np.zeros((n, n))
    q = np.zeros(n)
    M[:nn, :o_lp] = AP[nrm]
    q[:nn] = b[nrm]
    M[o_p:o_m, :o_lp] = AP[fp]
    M[o_p + np.arange(npl), o_lp + np.arange(npl)] = 1.0
    q[o_p:o_m] = b[fp]
    M[o_m:o_lp, :o_lp] = -AP[fm]
    M[o_m + np.arange(nmi), o_lm + np.arange(nmi)] = 1.0
    q[o_m:o_lp] = -b[fm]
    col_of = np.full(m, -1)
    col_of[nrm] = np.arange(nn)
    M[o_lp + np.arange(npl), col_of[normal_of[fp]]] = mu_hi[fp]
    M[o_lp + np.arange(npl), o_p + np.arange(npl)] = -1.0
    M[o_lm + np.arange(nmi), col_of[normal_of[fm]]] = mu_lo[fm]
    M[o_lm + np.arange(nmi), o_m + np.arange(nmi)] = -1.0
    cap = max_pivots if max_pivots is not None else 10 * n + 50
    z, piv, msg = _lemke_core(M, q, cap)
    return P @ z[:o_lp], piv, msg


# ---------------------------------------------------------------------------------------------
# projected Gauss-Seidel


def _pgs(data: _Data, tol: float, max_sweeps: int) -> tuple[np.ndarray, int, str]:
    """Projected Gauss-Seidel; each normal is followed by its friction rows so that the
    friction bounds use the normal just updated. Returns the best iterate seen."""
    A, b, normal_of, m = data.A, data.b, data.normal_of, data.m
    x = np.zeros(m)
    diag = np.diag(A)
    # rows without a positive pivot cannot be relaxed; they keep x = 0
    usable = diag > 1e-12 * data.amax
    info = []
    for j in data.nidx.tolist():
        for i in [j, *np.flatnonzero(normal_of == j).tolist()]:
            if usable[i]:
                info.append((i, A[i], float(b[i]), float(diag[i]), int(normal_of[i]),
                             float(data.mu_lo[i]), float(data.mu_hi[i])))
    best_x, best_r = x.copy(), data.residual(x)
    since_gain = 0
    sweeps = 0
    check = 5 if m > 20 else 10
    while sweeps < max_sweeps:
        sweeps += 1
        for i, ai, bi, di, j, lo, hi in info:
            xi = x[i] - (float(ai @ x) + bi) / di
            if j < 0:
                x[i] = xi if xi > 0.0 else 0.0
            else:
                xj = x[j] if x[j] > 0.0 else 0.0
                x[i] = min(max(xi, -lo * xj), hi * xj)
        if sweeps % check == 0 or sweeps == max_sweeps:
            r = data.residual(x)
            if not math.isfinite(r):
                return best_x, sweeps, 'pgs diverged'
            since_gain += check
            if r < best_r:
                if r < 0.5 * best_r:
                    since_gain = 0
                best_x, best_r = x.copy(), r
            if r <= tol:
                return x, sweeps, ''
            if since_gain >= 400:
                return best_x, sweeps, f'pgs stalled at residual {best_r:.3g}'
    return best_x, sweeps, f'pgs sweep cap {max_sweeps} reached at residual {best_r:.3g}'


# ---------------------------------------------------------------------------------------------
# driver


def _frictionless(data: _Data, tol: float, max_pivots: int | None,
                  pgs_sweeps: int) -> tuple[np.ndarray, int, str]:
    """Friction x = 0; the normal rows alone by Dantzig, else PGS. Always finite."""
    nrm = data.nidx
    k = nrm.size
    none = np.full(k, -1)
    zeros = np.zeros(k)
    sub = _Data(data.A[np.ix_(nrm, nrm)], data.b[nrm], none, zeros, zeros)
    cap = max_pivots if max_pivots is not None else 50 * k + 50
    xn, piv, msg = _dantzig(sub, cap)
    if msg or sub.residual(xn) > tol:
        xp, sweeps, msg2 = _pgs(sub, tol, pgs_sweeps)
        piv += sweeps
        if sub.residual(xp) < sub.residual(xn):
            xn = xp
        msg = f'normal rows: {msg or "inaccurate"}; {msg2}' if msg2 else ''
    x = np.zeros(data.m)
    if np.isfinite(xn).all():
        x[nrm] = xn
    return x, piv, msg


def solve(problem: FrictionalLCP, *, tol: float = 1e-9, max_pivots: int | None = None,
          methods: Sequence[str] = METHODS) -> LCPResult:
    """Solve the frictional LCP by the fallback ladder ``methods`` (see the module docstring).

    ``max_pivots`` caps each method separately (PGS: sweeps); the defaults are 50 m + 50 for
    Dantzig, 10 n + 50 for Lemke (n = size of the split problem) and 2000 PGS sweeps.
    Raises ValueError only for an unknown method name or an empty ``methods``.
    """
    if isinstance(methods, str) or not methods:
        raise ValueError(f'methods must be a non-empty sequence drawn from {METHODS}')
    for meth in methods:
        if meth not in METHODS:
            raise ValueError(f'unknown method {meth!r}; choose from {METHODS}')
    b, normal_of = problem.b, problem.normal_of
    m = b.shape[0]
    if m == 0 or b[normal_of < 0].min(initial=0.0) >= 0.0:
        return LCPResult(np.zeros(m), b.copy(), 'trivial', 0, 0, 0.0, True, '')
    data = _Data.of(problem)
    pgs_sweeps = max_pivots if max_pivots is not None else 2000
    total = 0
    failures: list[str] = []
    best: tuple[float, np.ndarray, str] | None = None
    for meth in methods:
        try:
            with np.errstate(all='ignore'):
                if meth == 'dantzig':
                    x, piv, msg = _dantzig(
                        data, max_pivots if max_pivots is not None else 50 * m + 50)
                elif meth == 'lemke':
                    x, piv, msg = _lemke(data, max_pivots)
                elif meth == 'pgs':
                    x, piv, msg = _pgs(data, tol, pgs_sweeps)
                else:
                    x, piv, msg = _frictionless(data, tol, max_pivots, pgs_sweeps)
                res = data.residual(x)
                res_b = data.residual(x, on_b=True)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError, ZeroDivisionError,
                OverflowError, MemoryError) as exc:
            x, piv, msg = np.zeros(m), 0, f'{type(exc).__name__}: {exc}'
            res = res_b = math.inf
        total += piv
        if res <= tol and res_b <= math.sqrt(tol):
            return LCPResult(x, problem.A @ x + b, meth, total, len(failures), res, True,
                             '; '.join(failures))
        if not msg and res <= tol:
            msg = (f'residual {res:.3g} only on the scale of its own max|x| '
                   f'{np.abs(x).max():.3g}; {res_b:.3g} on the velocity scale of b')
        failures.append(f'{meth}: {msg or f"residual {res:.3g} > tol {tol:.3g}"}')
        if math.isfinite(res_b) and (best is None or res_b < best[0]):
            best = (res_b, res, x, meth)
    if best is None:
        x = np.zeros(m)
        best = (data.residual(x, on_b=True), data.residual(x), x, methods[-1])
    _, res, x, meth = best
    return LCPResult(x, problem.A @ x + b, meth, total, len(failures), res, False,
                     '; '.join(failures))


# why a numba Dantzig pass gave up (``_lcp_kernels`` abort codes)
_ABORTS = ('', 'pivot cap reached', 'no admissible step', 'non-finite step',
           'invalid end of a drive', 'cycling', 'row-selection budget exhausted',
           'numerical failure')


def dantzig_message(residual: float, codes) -> str:
    """The logged reason a compiled Dantzig answer was solved again by ``lcp.solve``."""
    msg = f'dantzig (numba): {_ABORTS[codes[0]] or f"residual {residual:.3g}"}'
    if codes[1]:
        msg += f'; normals-first retry: {_ABORTS[codes[1]]}'
    return msg + '; solved again by lcp.solve'
