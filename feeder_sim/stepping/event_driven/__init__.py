"""The event-driven method: closed-form or integrated smooth phases between exactly located events.

``stepper`` holds the method (state and bookkeeping, event location, contact modes), ``_kernels``
its compiled per-event work and ``_chain`` one dynamic part's chain of closed-form phases.
"""

from feeder_sim.stepping.event_driven.stepper import EventDriven, EventSettings

__all__ = ['EventDriven', 'EventSettings']
