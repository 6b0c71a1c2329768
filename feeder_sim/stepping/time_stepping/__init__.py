"""The time-stepping method: Moreau's midpoint step with one frictional impulse LCP per island.

* ``stepper``: the method, ``TimeStepper``, with the Python reference of its step.
* ``_kernels``: the same step compiled whole, many steps per call.
"""

from feeder_sim.stepping.time_stepping.stepper import TimeStepper, TimeStepSettings

__all__ = ['TimeStepper', 'TimeStepSettings']
