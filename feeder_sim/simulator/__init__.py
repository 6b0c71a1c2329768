"""One simulated world and the way to drive it: the API the CLI, the ROS node and scripts share.

>>> sim = Simulator('track_one_box')
>>> sim.advance_to(0.5)              # integrate to t = 0.5 s of simulated time
>>> sim.advance_by(0.1)              # and 0.1 s more
>>> names, origins, angles = sim.part_poses()
>>> sim.command_vibration(amplitude_m=0.5e-3, frequency_hz=50.0)

* ``simulator``: the facade, :class:`Simulator`: a scene's world, its state, the stepping
  method, commands, parts added and removed, the checks of what comes from outside.
* ``impulse_log``: the contacts and impulses reported between two reads.
* ``energy_check``: the energy invariant of passive contact, a debug mode.
* ``feed``: a scene's sources and sinks.
* ``time_step_pilot``: ``time_step: auto``, the step a pilot run picks.
"""

from feeder_sim.simulator.energy_check import CHECK_ENERGY_VAR, EnergyCheck, EnergyInvariantError
from feeder_sim.simulator.feed import Feed
from feeder_sim.simulator.impulse_log import ContactReport
from feeder_sim.simulator.simulator import (
    MAX_PUBLISH_RATE_HZ,
    MAX_STEPS_PER_RUN,
    Simulator,
    UnknownPart,
)

__all__ = ['CHECK_ENERGY_VAR', 'ContactReport', 'EnergyCheck', 'EnergyInvariantError', 'Feed',
           'MAX_PUBLISH_RATE_HZ', 'MAX_STEPS_PER_RUN', 'Simulator', 'UnknownPart']
