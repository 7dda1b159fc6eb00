"""``motor_degree``: the team's demo publisher. Every 0.1 s the command grows by 0.1 degree,
modulo 360, on ``/motor_degree_cmd`` (std_msgs/Float32).

Owner: its executor's one thread (the timer callback).
"""

from __future__ import annotations

import sys

from rclpy.node import Node
from std_msgs.msg import Float32

from motor_driver.process.stop import StopSignal
from nodes.process import spinning
from nodes.process.params import NODES, declare
from nodes.process.qos import COMMAND_QOS

TENTHS_PER_TURN = 3600


class MotorDegreeNode(Node):
    def __init__(self, **kwargs: object) -> None:
        super().__init__("motor_degree", **kwargs)  # type: ignore[arg-type]
        declare(self, *NODES["motor_degree"])
        period = float(self.get_parameter("period_s").value)
        self._step_tenths = self._tenths_of("step_deg")
        self._tenths = self._tenths_of("start_deg")
        self._pub = self.create_publisher(Float32, "/motor_degree_cmd", COMMAND_QOS)
        self._timer = self.create_timer(period, self._tick)

    def _tenths_of(self, name: str) -> int:
        """A parameter in whole tenths of a degree (the command's unit: no float drift), a value
        between them rounded and said (a step of 0.04 is none at all)."""
        value = float(self.get_parameter(name).value)
        tenths = round(value * 10)
        if abs(tenths / 10 - value) > 1e-9:
            self.get_logger().warning(f"{name} {value:g} taken as {tenths / 10:g} deg: the command moves in tenths of"
                                      " a degree")
        return tenths

    def _tick(self) -> None:
        # integer tenths: no float drift however long it runs
        self._tenths = (self._tenths + self._step_tenths) % TENTHS_PER_TURN
        self._pub.publish(Float32(data=self._tenths / 10.0))


def main(args: list[str] | None = None) -> int:
    spinning.init(args)
    with StopSignal() as stop:
        spinning.spin_node(MotorDegreeNode(), stop.event)
    return 0


if __name__ == "__main__":
    sys.exit(main())
