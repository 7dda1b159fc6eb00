"""``rover_lifecycle``: the drive system as a managed (lifecycle) node, so that a launch system
or a lifecycle manager brings the rover up in order. Each transition is confirmed on the bus:

  configure   connect and boot every drive (not enabled); the drives' ROS interface (topics,
              services, actions, /cmd_vel) comes up
  activate    enable every drive (arm): each confirms Operation Enabled
  deactivate  quick stop, then disable voltage: each confirms Switch On Disabled
  cleanup     the ROS interface goes, the driver closes: the bus is released
  shutdown    from any state: as deactivate and cleanup

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
from rclpy.node import Node

from can_config import heap, load_config
from can_config.errors import RovercanError
from motor_driver import MotorDriver
from motor_driver import State as DriveState
from nodes import runtime
from nodes.actions import DriverActionsNode
from nodes.params import declare
from nodes.rover_driver import DriverNode, DriverServicesNode, DriverStopsNode, DriveSystemNode

logger = logging.getLogger(__name__)

class DriveLifecycleNode(LifecycleNode):
    def __init__(self, hot: Executor | None = None, **kwargs: Any) -> None:
        super().__init__("rovercan_lifecycle", **kwargs)
        declare(self, "config", "autostart", "realtime_priority")
        self.hot = hot  # where the drives' ROS interface spins (None: no interface, tests of the bus alone)
        self.driver: MotorDriver | None = None
        self.interface: list[Node] = []
        self._threads: list[runtime.SpinThread] = []  # the actions' and the stops' executors

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        try:
            config = load_config(str(self.get_parameter("config").value) or None)
            self.driver = MotorDriver(config).start()  # connect and boot; nothing enabled
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            self.driver = None
            return TransitionCallbackReturn.FAILURE
        if self.hot is not None:
            node = DriverNode(self.driver, context=self.context)
            self.interface = [node, DriverServicesNode(self.driver, context=self.context)]
            if config.drive_system is not None:
                self.interface.append(DriveSystemNode.beside(node, self.driver, config, context=self.context))
            for n in self.interface:
                self.hot.add_node(n)
            actions = DriverActionsNode(self.driver, context=self.context)
            stops = DriverStopsNode(self.driver, context=self.context)
            self.interface += [actions, stops]
            self._threads = [runtime.spin_alone(actions, "rovercan-actions"), runtime.spin_alone(stops, "rovercan-stops")]
        self.get_logger().info(f"configured: {len(self.driver.drives)} drive(s) booted, not enabled")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        assert self.driver is not None
        try:
            for drive in self.driver:
                drive.enable()  # confirmed by the drive's statusword
        except RovercanError as err:
            self.get_logger().error(f"activate failed: {err}; every drive is stopped again")
            self._stop_drives()
            return TransitionCallbackReturn.FAILURE
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        return super().on_deactivate(state) if self._stop_drives() else TransitionCallbackReturn.FAILURE

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._stop_drives()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self._stop_drives()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    # ------------------------------------------------------------------ helpers
    def _stop_drives(self) -> bool:
        """Quick stop, then disable voltage, on every drive; True when each confirmed it."""
        ok = True
        for drive in self.driver or ():
            try:
                if drive.state == DriveState.OPERATION_ENABLED:
                    drive.quick_stop()
                drive.disable_voltage()
            except RovercanError as err:
                self.get_logger().error(f"{drive.name}: stop failed: {err}")
                ok = False
        return ok

    def _release(self) -> None:
        for thread in self._threads:
            thread.stop(5.0)
        self._threads = []
        for n in self.interface:
            if self.hot is not None and n in self.hot.get_nodes():
                self.hot.remove_node(n)
            n.destroy_node()
        self.interface = []
        if self.driver is not None:
            self.driver.close()
            self.driver = None


def main(args: list[str] | None = None) -> int:
    runtime.init(args)
    with runtime.StopSignal() as stop:
        hot = runtime.make_executor("events")
        node = DriveLifecycleNode(hot)
        try:
            runtime.go_realtime(node)  # before configure makes the driver's threads: they inherit it
        except RovercanError as err:
            print(f"rover_lifecycle: {err}", file=sys.stderr)
            node.destroy_node()
            rclpy.try_shutdown()
            return 2
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
            node._stop_drives()
            node._release()
            node.destroy_node()
            rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
