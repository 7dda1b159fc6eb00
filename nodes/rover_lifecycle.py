"""``rover_lifecycle``: the drive system as a managed (lifecycle) node, so that a launch system
or a lifecycle manager brings the rover up in order. Each transition is confirmed on the bus:

  configure   connect and boot every drive (not enabled); the drives' ROS interface (topics,
              services, actions, /cmd_vel) comes up
  activate    enable every drive (arm): each confirms Operation Enabled
  deactivate  quick stop, then disable voltage: each confirms Switch On Disabled
  cleanup     the ROS interface goes, the driver closes: the bus is released
  shutdown    from any state: as deactivate and cleanup

The drives' process is the assembly of ``rover_driver`` (:mod:`nodes.assembly`: the same nodes,
executors, callback groups and start order, the parameters ``drive_system`` and ``default_joint``
alike); each transition is a step of it: configure builds and starts it, activate arms, deactivate
is the driver's safe stop, cleanup closes it. The ROS interface spins on the hot executor given.

With ``autostart`` (the team's demo) it configures and activates itself. A failed transition
logs why and returns FAILURE; the node stays where it was (after a failed configure, with no
driver and no bus).
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import rclpy
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import State, TransitionCallbackReturn

from can_config import load_config
from can_config.errors import RovercanError
from motor_driver import MotorDriver
from motor_driver.process import heap
from nodes import runtime
from nodes.assembly import Assembly, set_up
from nodes.params import declare

logger = logging.getLogger(__name__)


class DriveLifecycleNode(LifecycleNode):
    def __init__(self, hot: Executor | None = None, **kwargs: Any) -> None:
        """``hot``: where the drives' ROS interface spins; None (``main``): the process set-up from
        this node's parameters (nodes/assembly.py), which may raise :class:`ConfigError`."""
        super().__init__("rovercan_lifecycle", **kwargs)
        declare(self, "config", "autostart")
        self.hot = set_up(self).hot if hot is None else hot
        self.assembly: Assembly | None = None

    @property
    def driver(self) -> MotorDriver | None:
        return None if self.assembly is None else self.assembly.driver

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        try:
            driver = MotorDriver(load_config(str(self.get_parameter("config").value) or None))  # nothing sent yet
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            return TransitionCallbackReturn.FAILURE
        self.assembly = Assembly(driver, self.hot, context=self.context)
        try:
            self.assembly.build()  # the ROS interface first, then the bus (nodes/assembly.py says why)
            self.assembly.start(arm=False)  # connect and boot; nothing enabled: that is activate
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"configured: {len(driver.drives)} drive(s) booted, not enabled")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        assert self.assembly is not None
        failed = self.assembly.arm()
        if failed:
            self.get_logger().error(f"activate failed: {'; '.join(failed)}; every drive is stopped again")
            self.assembly.stop_drives()
            return TransitionCallbackReturn.FAILURE
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        failed = self.stop_drives()
        return TransitionCallbackReturn.FAILURE if failed else super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self.release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self.release()  # the driver's close: its safe stop first
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.release()
        return TransitionCallbackReturn.SUCCESS

    # ------------------------------------------------------------------ steps
    def stop_drives(self) -> list[str]:
        """The driver's safe stop; what was not confirmed, each also logged."""
        failed = [] if self.assembly is None else self.assembly.stop_drives()
        for line in failed:
            self.get_logger().error(f"stop not confirmed: {line}")
        return failed

    def release(self) -> None:
        """The assembly closed (drives safe, threads joined, interface gone, bus released)."""
        if self.assembly is not None:
            self.assembly.close()
            self.assembly = None


def main(args: list[str] | None = None) -> int:
    runtime.init(args)
    with runtime.StopSignal() as stop:
        try:
            node = DriveLifecycleNode()  # the process set-up before configure makes the driver's threads
        except RovercanError as err:
            print(f"rover_lifecycle: {err}", file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        hot = node.hot
        cold = SingleThreadedExecutor()
        cold.add_node(node)
        transitions = runtime.SpinThread(cold, "rovercan-lifecycle")
        try:
            if node.get_parameter("autostart").value:
                node.trigger_configure()
                if node.driver is not None:
                    node.trigger_activate()
            heap.settle()  # built (and, with autostart, the driver too): keep it out of the collector's walks
            runtime.spin_until(hot, stop.event)
        finally:
            transitions.stop(5.0)
            node.release()
            node.destroy_node()
            rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
