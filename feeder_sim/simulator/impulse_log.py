"""The contacts a simulation reports between two reads, with the impulses (N s) they
transmitted, summed per vertex-edge feature."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feeder_sim.contact._feature_kernels import sum_by_feature
from feeder_sim.stepping import StepContacts


@dataclass
class ContactReport:
    """Contacts active since the previous report, with the impulses (N s) they transmitted."""

    point: np.ndarray            # (k, 2) m, latest position
    normal: np.ndarray           # (k, 2)
    normal_impulse: np.ndarray   # (k,) N s, summed over the interval (collisions included)
    tangent_impulse: np.ndarray  # (k,) N s
    body_a: np.ndarray           # (k,) vertex body
    body_b: np.ndarray           # (k,) edge body

    @property
    def n(self) -> int:
        return len(self.normal_impulse)


class ImpulseLog:
    """Sums impulses per vertex-edge feature between two reports.

    A pile has hundreds of contacts per step, so nothing is done per contact in Python:
    ``add`` keeps each step's arrays and they are reduced by feature (compiled:
    ``contact._feature_kernels.sum_by_feature``) every ``_REDUCE_STEPS`` steps, which bounds
    the memory when nobody takes reports, and in ``take``. The report is what summing step by
    step gives: features in order of first appearance since the previous report
    (deterministic, so recordings are too), the latest point and normal, impulses summed in
    step order from -0.0, so even the bits and the sign of a zero match a running ``+=``.
    """

    _REDUCE_STEPS = 64

    def __init__(self) -> None:
        # the reduced part (if any) first, then one per step since the last reduction:
        # (key, point, normal, p_n, p_t, body_a, body_b)
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._steps = 0             # parts added since the last reduction

    def add(self, sc: StepContacts) -> None:
        c = sc.cs.contacts
        if not c.n:
            return
        key = (c.vertex_a.astype(np.int64) << 32) | c.edge_b.astype(np.int64)
        self._parts.append((key, c.point, c.normal, sc.normal_impulse, sc.tangent_impulse,
                            c.body_a, c.body_b))
        self._steps += 1
        if self._steps >= self._REDUCE_STEPS:
            self._reduce()

    def _reduce(self) -> None:
        """Replace the parts by one with a row per feature."""
        if not self._steps:
            return
        self._steps = 0
        self._parts = [sum_by_feature(*(np.concatenate(f)
                                        for f in zip(*self._parts, strict=True)))]

    def take(self) -> ContactReport:
        self._reduce()
        parts, self._parts = self._parts, []
        if parts:
            _, point, normal, p_n, p_t, body_a, body_b = parts[0]
            on = p_n > 0.0
            if on.any():
                return ContactReport(point.compress(on, axis=0), normal.compress(on, axis=0),
                                     p_n[on], p_t[on], body_a[on].astype(np.int64),
                                     body_b[on].astype(np.int64))
        z = np.zeros(0)
        return ContactReport(np.zeros((0, 2)), np.zeros((0, 2)), z, z.copy(),
                             np.zeros(0, int), np.zeros(0, int))
