"""The reports: numbers and figures that check the physics and show what it does.

* :mod:`.pointmass`: the point-mass conveying reference (closed-form phases, exact events).
* :mod:`.accuracy`: ``feeder-sim accuracy``, error against run time per method and peer.
* :mod:`.stability`: ``feeder-sim stability``, stiff and extreme cases with numeric bounds.
* :mod:`.paper`: ``feeder-sim paper``, the paper's figures.

Imports every layer below (model, contact, stepping, the simulator, output, the run loop) and
matplotlib; nothing below imports a report.
"""
