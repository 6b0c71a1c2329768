"""The event-driven method: closed-form or integrated smooth phases between exactly located events.

* ``stepper``: the method, ``EventDriven``: advancing, event cascades, reset.
* ``bookkeeping``: settings, tolerances, the held mode, the integrator's state vector and the
  record of contact impulses.
* ``modes``: what happens at an event: impacts, the force LCP choosing the next contact mode.
* ``events``: candidate collisions and the integrated phases (Dormand-Prince steps, locating an
  event).
* ``phases``: closed-form phases, the drive model and the hand-off to the compiled chain.
* ``_kernels``: the compiled per-event and per-step work.
* ``_chain``: one dynamic part's chain of closed-form phases, compiled.
"""

from feeder_sim.stepping.event_driven.stepper import EventDriven, EventSettings

__all__ = ['EventDriven', 'EventSettings']
