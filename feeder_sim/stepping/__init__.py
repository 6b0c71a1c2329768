"""The stepping methods, one module each, behind one protocol (:mod:`.protocol`).

* :mod:`.time_stepping`: Moreau's midpoint scheme, one frictional impulse LCP per island per step.
* :mod:`.event_driven`: smooth phases in closed form or integrated, events located exactly.
* :mod:`.impulse_based`: Mirtich & Canny's impulse-based method, one contact point at a time.

:data:`STEPPERS` maps each name of :data:`feeder_sim.model.scene.METHODS` to its class, which
carries the method's policy (:class:`.protocol.Stepper`). A method imports the model and
contact layers and :mod:`.protocol`, never another method.
"""

from feeder_sim.model.scene import METHODS
from feeder_sim.stepping.event_driven import EventDriven, EventSettings
from feeder_sim.stepping.impulse_based import ImpulseBased, ImpulseSettings
from feeder_sim.stepping.protocol import StepContacts, Stepper
from feeder_sim.stepping.time_stepping import TimeStepper, TimeStepSettings

STEPPERS: dict[str, type[Stepper]] = {m.name: m for m in (EventDriven, TimeStepper, ImpulseBased)}
assert tuple(STEPPERS) == METHODS

__all__ = ['EventDriven', 'EventSettings', 'ImpulseBased', 'ImpulseSettings', 'METHODS',
           'STEPPERS', 'StepContacts', 'Stepper', 'TimeStepper', 'TimeStepSettings']
