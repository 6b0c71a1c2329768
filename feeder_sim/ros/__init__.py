"""The ROS 2 node: a thin shell over :class:`feeder_sim.simulator.Simulator`.

* :mod:`.node`: the ``feeder_sim`` node (parameters, topics, services, pacing, recording).
* :mod:`.messages`: the ROS messages it builds from frames.
* :mod:`.entry`: ``sim_node``'s ``main``.
* :mod:`.client`: ``feeder-sim node ...``, a client for a running node (no ``ros2`` CLI).

Imports rclpy and the message packages, the model, the simulator and :mod:`feeder_sim.output`;
never a stepper's internals nor the CLI's run loop.
"""
