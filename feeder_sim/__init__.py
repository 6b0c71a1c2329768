"""feeder_sim: 2D rigid-body simulation of vibratory parts feeders.

The physics (``feeder_sim.model``, ``feeder_sim.contact``, ``feeder_sim.stepping``) never imports
ROS; the ROS 2 node is a thin shell over :class:`feeder_sim.simulator.Simulator`, which also runs
from the ``feeder-sim`` command line and from Python.
"""

__version__ = '0.1.0'
