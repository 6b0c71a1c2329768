"""Contact impulses totalled per part: what a user of a feeder wants rather than raw points.

The raw report (:class:`feeder_sim.simulator.ContactReport`) lists every vertex-edge contact
with the normal and tangential impulse it carried since the previous report. Here those are
summed per dynamic body: the linear impulse (N s, world frame), the angular impulse about the
body's centre of mass (N m s) and the sum of the normal impulse magnitudes, which is the
quantity wear and damage scale with.

Sign convention (as in :mod:`feeder_sim.contact.dynamics`): a contact's normal points from the edge
body ``b`` towards the vertex body ``a`` and its tangent is the normal turned by +90 degrees;
``a`` receives ``normal_impulse * n + tangent_impulse * t`` and ``b`` the opposite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feeder_sim.model.world import perp


@dataclass
class PartImpulses:
    """Per-part totals over one report interval, indexed like ``parts``."""

    parts: np.ndarray            # (n,) body indices of the dynamic bodies, scene order
    impulse: np.ndarray          # (n, 2) N s, world frame
    angular_impulse: np.ndarray  # (n,) N m s about each part's centre of mass
    normal_impulse: np.ndarray   # (n,) N s, sum of the contacts' normal impulses
    contacts: np.ndarray         # (n,) number of contacts that carried impulse


def part_impulses(report, parts: np.ndarray, centre_of_mass: np.ndarray) -> PartImpulses:
    """Totals of ``report`` per body in ``parts``; ``centre_of_mass`` is (n_bodies, 2) m."""
    parts = np.asarray(parts, dtype=np.int64)
    n_bodies = len(centre_of_mass)
    slot = np.full(n_bodies, -1, dtype=np.int64)
    slot[parts] = np.arange(len(parts))
    n = len(parts)
    impulse = np.zeros((n, 2))
    angular = np.zeros(n)
    normal_sum = np.zeros(n)
    count = np.zeros(n, dtype=np.int64)
    if report.n:
        vector = (report.normal_impulse[:, None] * report.normal
                  + report.tangent_impulse[:, None] * perp(report.normal))
        for body, sign in ((report.body_a, 1.0), (report.body_b, -1.0)):
            s = slot[body]
            on = s >= 0
            if not on.any():
                continue
            s, p = s[on], sign * vector[on]
            r = report.point[on] - centre_of_mass[body[on]]
            np.add.at(impulse, s, p)
            np.add.at(angular, s, r[:, 0] * p[:, 1] - r[:, 1] * p[:, 0])
            np.add.at(normal_sum, s, report.normal_impulse[on])
            np.add.at(count, s, 1)
    return PartImpulses(parts, impulse, angular, normal_sum, count)
