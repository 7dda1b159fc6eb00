"""The rover's /cmd_vel drive system: skid-steer wheels from a Twist, odometry, stops on a
command timeout; a node beside the driver node, in the same process.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node

from can_config import RoverConfig
from can_config.errors import RovercanError
from motor_driver import Drive, MotorDriver
from motor_driver.skid_steer import SkidSteer, Twist2D
from nodes.params import declare, qos_depth
from nodes.qos import NO_PUB_EVENTS, NO_SUB_EVENTS, SETPOINT_QOS, state_qos
from nodes.refusals import DEG, WARN_THROTTLE_S, RefusalLog, stamp_header

if TYPE_CHECKING:
    from nodes.rover_driver import DriverNode


def not_armed(blocked: list[Drive]) -> str:
    """Why the wheels in ``blocked`` cannot be driven, and how to arm them."""
    first = blocked[0].snapshot()
    if first.lost:
        why = f"wheel {blocked[0].name} is lost (no heartbeat)"
    elif first.state.name == "OPERATION_ENABLED":
        why = f"wheel {blocked[0].name} is not armed by this driver (the drive says OPERATION_ENABLED)"
    else:
        why = f"wheel {blocked[0].name} is {first.state.name}"
    others = f" (and {len(blocked) - 1} more)" if len(blocked) > 1 else ""
    return (f"{why}{others}; arm the rover with the service /arm (std_srvs/Trigger), or launch with"
            " arm:=true")


class DriveSystemNode(Node):
    """/cmd_vel -> skid-steer wheel velocities (ramped, stale commands stop), /odom from wheel feedback.

    The node commands the wheels only while /cmd_vel is fresh and while it ramps them down after
    /cmd_vel went stale; once stopped it leaves them alone (bench tools and per-joint topics
    may then use them).
    """

    def __init__(self, driver: MotorDriver, config: RoverConfig, refusals: RefusalLog | None = None,
                 **kwargs: Any) -> None:
        super().__init__("drive_system", **kwargs)
        declare(self, "odom_rate_hz", "odom_frame", "base_frame", "state_qos_depth")
        system = config.drive_system
        if system is None:
            raise RovercanError("the config has no drive_system section")
        self.system = system
        self.left = [driver.drive(n) for n in system.left]
        self.right = [driver.drive(n) for n in system.right]
        self.wheels = self.left + self.right
        slowest_deg_s = min(d.config.max_velocity_deg_s for d in self.wheels)
        self.steer = SkidSteer(system.track_width_m, system.wheel_radius_m, system.max_accel_m_s2,
                               system.max_speed_m_s, max_angular_rad_s=system.max_angular_rad_s,
                               max_wheel_rad_s=math.radians(slowest_deg_s))
        self.refusals = refusals or RefusalLog(self.get_logger().warning)
        self._target = Twist2D()
        self._last_cmd = -math.inf
        self._last_tick = time.monotonic()
        self.stale = True
        self.active = False  # commanding the wheels (fresh /cmd_vel or ramping down after it)
        self._odom_frame = str(self.get_parameter("odom_frame").value)
        self._base_frame = str(self.get_parameter("base_frame").value)
        self.create_subscription(Twist, "/cmd_vel", self._on_cmd_vel, SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self._odom_pub = self.create_publisher(Odometry, "/odom", state_qos(qos_depth(self)), event_callbacks=NO_PUB_EVENTS)
        self._period_s = 1.0 / float(self.get_parameter("odom_rate_hz").value)
        self._timer = self.create_timer(self._period_s, self._tick)

    @classmethod
    def beside(cls, driver_node: DriverNode, driver: MotorDriver, config: RoverConfig, **kwargs: Any) -> DriveSystemNode:
        """The drive system of a process with ``driver_node`` on the same executor (rover_driver,
        rover_lifecycle): its control loop on that node's state timer where the rates match."""
        node = cls(driver, config, driver_node.refusals, **kwargs)
        node.tick_with(driver_node)
        return node

    def tick_with(self, driver_node: DriverNode) -> bool:
        """The control loop run from the driver node's state timer when their rates match (one
        wake-up of the executor they share, not two; measured in docs/performance.md); True if so.
        Both nodes must spin on the same executor."""
        if not driver_node.share_tick(self._period_s, self._tick):
            return False
        self.destroy_timer(self._timer)
        return True

    def _on_cmd_vel(self, msg: Twist) -> None:
        v, w = msg.linear.x, msg.angular.z
        if not (math.isfinite(v) and math.isfinite(w)):
            self.refusals.refuse("drive_system", f"/cmd_vel with non-finite values (linear.x={v}, angular.z={w})")
            return
        self._target = Twist2D(v, w)
        self._last_cmd = time.monotonic()

    def _tick(self) -> None:
        try:
            now = time.monotonic()
            dt = min(now - self._last_tick, 0.5)
            self._last_tick = now
            self.stale = now - self._last_cmd > self.system.cmd_timeout_s
            if not self.stale:
                # all or none: a turn driven by one side only is worse than no motion
                blocked = [d for d in self.wheels if not d.snapshot().enabled]
                if blocked:
                    self._halt(f"/cmd_vel not applied: {not_armed(blocked)}; no wheel is driven")
                    self._publish_odom(dt)
                    return
                self.active = True
            left, right = self.steer.step(Twist2D() if self.stale else self._target, dt)
            if self.stale and not self.active:
                self._publish_odom(dt)
                return
            if self.stale and left == 0.0 and right == 0.0:
                self.active = False  # stopped: send this last zero, then leave the wheels to others
            for drives, speed in ((self.left, left), (self.right, right)):
                for drive in drives:
                    if self.stale and not drive.snapshot().enabled:
                        continue  # ramping down: the others still stop
                    try:
                        drive.set_velocity(speed * DEG)
                    except RovercanError as err:
                        self._halt(f"/cmd_vel not applied: wheel {drive.name} refused {speed:.2f} rad/s ({err});"
                                   " every wheel stopped")
                        self._publish_odom(dt)
                        return
            self._publish_odom(dt)
        except Exception as err:
            self.get_logger().error(f"drive system tick failed: {err!r}", throttle_duration_sec=WARN_THROTTLE_S)

    def _halt(self, reason: str) -> None:
        """Stop every wheel that still runs and forget the ramp, so that nothing (a stale
        ramp-down, a recovered wheel) brings them back without a fresh /cmd_vel. The command
        that was refused is spent: only one received after this drives again (it was driving all
        six for a moment when the wheel came back within its timeout)."""
        self.steer.halt()
        self._last_cmd = -math.inf
        self.stale = True
        if self.active:
            for drive in self.wheels:
                if drive.snapshot().enabled:
                    try:
                        drive.set_velocity(0.0)
                    except RovercanError:
                        pass  # that wheel cannot move anyway
        self.active = False
        self.refusals.refuse("drive_system", reason)

    def _publish_odom(self, dt: float) -> None:
        def mean_rad_s(drives: list[Drive]) -> float:
            return sum(math.radians(d.velocity_deg_s) for d in drives) / len(drives)  # not a snapshot each, 50 Hz

        pose, twist = self.steer.odometry(mean_rad_s(self.left), mean_rad_s(self.right), dt)
        if self._odom_pub.get_subscription_count() == 0:
            return  # integrated all the same; built and published only for a reader
        odom = Odometry()
        stamp_header(odom.header, time.time())
        odom.header.frame_id = self._odom_frame
        odom.child_frame_id = self._base_frame
        odom.pose.pose.position.x = pose.x_m
        odom.pose.pose.position.y = pose.y_m
        odom.pose.pose.orientation.z = math.sin(pose.yaw_rad / 2.0)
        odom.pose.pose.orientation.w = math.cos(pose.yaw_rad / 2.0)
        odom.twist.twist.linear.x = twist.linear_m_s
        odom.twist.twist.angular.z = twist.angular_rad_s
        self._odom_pub.publish(odom)
