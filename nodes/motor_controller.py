"""``motor_controller``: moves one drive from ``/motor_degree_cmd`` and publishes
``/motor_state`` (rovercan_msgs/MotorState).

Thin: parameters in, calls on :class:`motor_driver.MotorDriver`, snapshots out. A callback
never raises into the executor: refused commands (NaN, beyond limits, drive faulted) are
logged with a throttled warning and nothing moves.
"""

from __future__ import annotations

import math
import sys

import rclpy
from rclpy.node import Node
from rovercan_msgs.msg import MotorState
from std_msgs.msg import Float32

from can_config import RoverConfig, load_config
from can_config.errors import CommandRejected, MotorError, RovercanError
from can_config.stop import StopSignal
from motor_driver import DriveState, MotorDriver
from nodes import runtime
from nodes.logbridge import bridge_core_logging, unbridge
from nodes.params import declare
from nodes.qos import SETPOINT_QOS, STATE_QOS
from nodes.refusals import WARN_THROTTLE_S, RefusalLog


def fill_motor_state(msg: MotorState, state: DriveState, continuous: bool) -> MotorState:
    """Copy a driver snapshot into a MotorState (angle wrapped to [0, 360) on continuous joints;
    NaN values and ``stale`` when no PDO came for ``stale_after_syncs`` SYNC periods)."""
    angle = state.angle_deg % 360.0 if continuous else state.angle_deg
    # stale data is not repeated as if it were news: NaN, with the flag and its age
    msg.angle = math.nan if state.stale else float(angle)
    msg.torque = math.nan if state.stale else float(state.torque_nm)
    msg.velocity = math.nan if state.stale else float(state.velocity_deg_s)
    msg.stale = state.stale
    msg.data_age = float(min(state.data_age_s, 1e9))
    msg.name = state.name
    msg.state = "LOST" if state.lost else state.state.name
    msg.enabled = state.enabled
    msg.fault = state.fault
    msg.error_code = state.error_code
    stamp = state.stamp
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
    msg.header.frame_id = state.name
    return msg


class MotorControllerNode(Node):
    def __init__(self, driver: MotorDriver | None = None, **kwargs: object) -> None:
        super().__init__("motor_controller", **kwargs)  # type: ignore[arg-type]
        self.declare_parameter("config", "")
        declare(self, "realtime_priority")
        self._owns_driver = driver is None
        if driver is None:  # standalone (ros2 run / launch): the node owns its driver, and its process
            runtime.go_realtime(self)  # real-time before the driver's threads start: they inherit it
            driver = start_driver(load_config(str(self.get_parameter("config").value) or None))
        self.driver = driver
        self._log_handler = bridge_core_logging(self)
        self.declare_parameter("joint", next(iter(driver.drives)))
        self.declare_parameter("state_rate_hz", 50.0)
        self.declare_parameter("arm", False)
        joint = str(self.get_parameter("joint").value)
        self.drive = driver.drive(joint)
        self._continuous = self.drive.config.is_continuous
        self._refusals = RefusalLog(self.get_logger().warning)
        self._state_pub = self.create_publisher(MotorState, "/motor_state", STATE_QOS)
        self.create_subscription(Float32, "/motor_degree_cmd", self._on_command, SETPOINT_QOS)
        rate = float(self.get_parameter("state_rate_hz").value)
        self.create_timer(1.0 / rate, self._publish_state)
        self._msg = MotorState()
        if self.get_parameter("arm").value:
            self.drive.enable()
            self.get_logger().info(f"{joint}: armed (Operation Enabled)")

    def close(self) -> None:
        """Safe state before the node goes: the owned driver quick-stops and disables."""
        unbridge(self._log_handler)
        if self._owns_driver:
            self.driver.close()

    def _on_command(self, msg: Float32) -> None:
        try:
            self.drive.move_to(msg.data)
        except CommandRejected as err:
            self._refuse(f"command refused: {err}")
        except MotorError as err:
            self._refuse(f"command not executed: {err}")
        except Exception as err:  # never raise into the executor
            self._refuse(f"unexpected error on command {msg.data!r}: {err!r}")

    def _refuse(self, why: str) -> None:
        self._refusals.refuse(self.drive.name, why)

    @property
    def refused(self) -> int:
        """Commands refused so far (the refusal log's count; nothing takes it here)."""
        return self._refusals.count.get(self.drive.name, 0)

    def _publish_state(self) -> None:
        try:
            self._state_pub.publish(fill_motor_state(self._msg, self.drive.snapshot(), self._continuous))
        except Exception as err:
            self.get_logger().error(f"state publish failed: {err!r}", throttle_duration_sec=WARN_THROTTLE_S)


def start_driver(config: RoverConfig) -> MotorDriver:
    driver = MotorDriver(config)
    try:
        return driver.start()
    except BaseException:
        driver.close()
        raise


def main(args: list[str] | None = None) -> int:
    runtime.init(args)
    with StopSignal() as stop:
        try:
            node = MotorControllerNode()
        except RovercanError as err:
            print(f"motor_controller: {err}", file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        runtime.spin_node(node, stop.event, on_stop=node.close)  # close: quick stop + disable first
    return 0


if __name__ == "__main__":
    sys.exit(main())
