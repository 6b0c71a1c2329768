"""The impulse-based method of Mirtich & Canny: every contact a collision, one point at a time.

* ``stepper``: the method, ``ImpulseBased``: candidates, settings, reports.
* ``_kernels``: the compiled run of steps, its collisions and time-of-impact search.
"""

from feeder_sim.contact.routh import collide, CollisionResult, LAWS
from feeder_sim.stepping.impulse_based.stepper import ImpulseBased, ImpulseSettings

__all__ = ['CollisionResult', 'ImpulseBased', 'ImpulseSettings', 'collide', 'LAWS']
