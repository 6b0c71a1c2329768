"""What leaves a simulation: frames, MCAP logs, their replay in rerun, outcomes.

* :mod:`.frames`: the frame published and recorded at one simulated time; the recorder set-up.
* :mod:`.recording`, :mod:`.msgdefs`: MCAP writing and reading in ROS 2 CDR, without ROS.
* :mod:`.replay`: an MCAP log to a rerun recording.
* :mod:`.outcomes`: exits, feed rate, exit orientation, jams.
* :mod:`.impulses`: contact impulses totalled per part.

Imports the model and the simulator facade, never a stepping method's internals.
"""
