"""Keep a feeder's outfeed queue filled from its sensors: a small ROS 2 cell controller.

Runs against the node on ``config/queue_cell.yaml``: boxes arrive on a vibrating track, travel
to an end stop and queue there. Two beams of the scene tell the state of the queue:
``at_stop`` (a box waits at the stop) and ``queue_full`` (the queue reaches back 4 box lengths).
The controller

* switches the drive off (``vibration_cmd`` amplitude 0) once both beams have been blocked for
  ``off_delay`` s of simulated time: the queue is full, more parts would only press on it;
* switches it on again as soon as either beam is clear: the robot took a box, or the queue
  shrank;
* plays the robot: every ``pick_period`` s it takes the box at the stop (``~/delete_entity``
  with the name of the part farthest along the track, from ``track_state``).

Times are simulated time (``/clock``), so the cell behaves the same at any real-time factor::

    .venv/bin/sim_node --ros-args -p scene:=queue_cell &
    .venv/bin/python examples/queue_controller.py
"""

from __future__ import annotations

import functools
import sys

from feeder_sim_interfaces.srv import DeleteEntity
import rclpy
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray


class QueueController(Node):
    """Drive on/off from the queue's beams, and a robot taking a box at a steady rate."""

    def __init__(self, **kwargs) -> None:
        super().__init__('queue_controller', **kwargs)
        p = {name: self.declare_parameter(name, default).value for name, default in (
            ('feeder', '/feeder_sim'),        # the simulator node's name
            ('amplitude', 5.0e-4),            # m, the drive when on
            ('frequency', 50.0),              # Hz
            ('off_delay', 0.2),               # s the queue must be full before the drive stops
            ('pick_period', 2.0),             # s between two picks of the robot
        )}
        self.amplitude, self.frequency = p['amplitude'], p['frequency']
        self.off_delay, self.pick_period = p['off_delay'], p['pick_period']
        feeder = p['feeder'].rstrip('/')
        self.t = 0.0
        self.blocked = {'queue_full': False, 'at_stop': False}
        self.head: str | None = None        # the part farthest along the track
        self.full_since: float | None = None
        self.drive_on = True
        self.last_pick = 0.0
        self.picks: list[tuple[float, str]] = []
        self.switches: list[tuple[float, bool]] = []
        for name in self.blocked:
            self.create_subscription(Bool, f'{feeder}/sensors/{name}/blocked',
                                     functools.partial(self._on_beam, name), 100)
        self.create_subscription(JointState, f'{feeder}/track_state', self._on_track, 10)
        self.create_subscription(Clock, '/clock', self._on_clock, 10)
        self.drive = self.create_publisher(Float64MultiArray, 'vibration_cmd', 10)
        self.pick = self.create_client(DeleteEntity, f'{feeder}/delete_entity')

    def _on_beam(self, name: str, msg: Bool) -> None:
        self.blocked[name] = msg.data

    def _on_track(self, msg: JointState) -> None:
        self.head = msg.name[max(range(len(msg.name)), key=msg.position.__getitem__)] \
            if msg.name else None

    def _on_clock(self, msg: Clock) -> None:
        self.t = msg.clock.sec + 1e-9 * msg.clock.nanosec
        full = self.blocked['queue_full'] and self.blocked['at_stop']
        if not full:
            self.full_since = None
            self._switch(True)
        else:
            if self.full_since is None:
                self.full_since = self.t
            if self.t - self.full_since >= self.off_delay:
                self._switch(False)
        if (self.blocked['at_stop'] and self.head is not None
                and self.t - self.last_pick >= self.pick_period and self.pick.service_is_ready()):
            self.last_pick = self.t
            self.picks.append((self.t, self.head))
            self.pick.call_async(DeleteEntity.Request(entity=self.head))

    def _switch(self, on: bool) -> None:
        if on == self.drive_on:
            return
        self.drive_on = on
        self.switches.append((self.t, on))
        self.drive.publish(Float64MultiArray(
            data=[self.amplitude if on else 0.0, self.frequency]))
        self.get_logger().info(f't = {self.t:.2f} s: drive {"on" if on else "off"}')


def main(argv: list[str] | None = None) -> int:
    rclpy.init(args=argv if argv is not None else sys.argv)
    node = QueueController()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
