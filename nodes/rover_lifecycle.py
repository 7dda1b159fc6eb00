"""``rover_lifecycle``: the drive system as a managed (lifecycle) node, so that a launch system
or a lifecycle manager brings the rover up in order. Each transition is confirmed on the bus:

  configure   connect and boot every drive (not enabled); the drives' ROS interface (topics,
              services, actions, /cmd_vel) comes up, its motion held
  activate    motion taken; a drive is enabled only when asked: /arm, <joint>/enable, or the
              ``arm`` parameter (every drive, each confirming Operation Enabled) or a drive's
              ``arm_on_start``
  deactivate  motion held, then quick stop and disable voltage: each confirms Switch On Disabled
  cleanup     the ROS interface goes, the driver closes: the bus is released
  shutdown    from any state: as deactivate and cleanup

Each transition is logged at INFO with what was done to the drives ("configured: 6 drive(s)
booted, not enabled; ...", "active: motion taken; no drive enabled: call /arm ...", "inactive:
motion held; 6 drive(s) quick-stopped if enabled ...", "cleaned up: ...", "shut down from
active: ..."); a failed one at ERROR with why. Once active, motion is no longer held: a drive
not enabled is "not armed" (its verdict, :mod:`motor_driver.drive.verdict`), and a refusal and
/diagnostics say that and what helps (/arm, or launch with arm:=true); the drive system's
/diagnostics says "inactive" at level OK while the node is inactive.

Motion held (unconfigured there is no driver at all; inactive, the driver's
:meth:`~motor_driver.MotorDriver.hold_motion`): every drive's command channel, the one way a
controlword or a set-point leaves, refuses every motion entry (/arm, <joint>/enable, recover,
home, set_mode, sdo_write, /cmd_vel, /joint_commands, the degree and velocity topics, the
actions) with "<node> is inactive: activate it", nothing sent; the stops are still taken and
the state topics still publish (docs/ros.md).

The drives' process is the assembly of ``rover_driver`` (:mod:`nodes.assembly`: the same nodes,
executors, callback groups and start order, the parameters ``drive_system`` and ``default_joint``
alike); each transition is a step of it: configure builds and starts it, activate takes motion (and
arms when asked), deactivate holds motion and is the driver's safe stop, cleanup closes it. The ROS
interface spins on the hot executor given.

With ``autostart`` (the team's demo) it configures and activates itself: the drives are enabled
only with ``arm`` too (``rover_launch.xml lifecycle:=true autostart:=true arm:=true``), as
``rover_driver`` enables them at start only with ``arm``. A failed transition
logs why and returns FAILURE; the node stays where it was (after a failed configure, with no
driver and no bus).

Owner: the lifecycle transitions run on the node's service executor thread; the nodes it
makes at configure are served by the process's executors (nodes/assembly.py).
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
from nodes.assembly import Assembly, set_up
from nodes.process import spinning
from nodes.process.params import declare

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

    @property
    def inactive(self) -> str:
        """Why motion is refused while the node is not active, and what to do."""
        return f"{self.get_name()} is inactive: activate it"

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        try:
            driver = MotorDriver(load_config(str(self.get_parameter("config").value) or None))  # nothing sent yet
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            return TransitionCallbackReturn.FAILURE
        driver.hold_motion(self.inactive)  # before anything could enable a drive (arm_on_start included)
        self.assembly = Assembly(driver, self.hot, context=self.context)
        try:
            self.assembly.build()  # the ROS interface first, then the bus (nodes/assembly.py says why)
            self.assembly.start(arm=False)  # connect and boot; nothing enabled: that is activate
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"configured: {len(driver.drives)} drive(s) booted, not enabled; motion held until activate")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        assembly = self.assembly
        assert assembly is not None and assembly.node is not None
        assembly.driver.allow_motion()
        drives = assembly.node.drives
        asked = None if assembly.node.get_parameter("arm").value else [
            name for name, drive in drives.items() if drive.config.arm_on_start]
        failed = assembly.arm(asked)
        if failed:
            self.get_logger().error(f"activate failed: {'; '.join(failed)}; every drive is stopped again")
            assembly.driver.hold_motion(self.inactive)
            assembly.stop_drives()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info("active: motion taken; " + (
            "every drive armed (arm:=true)" if asked is None else
            f"{', '.join(asked)} armed (arm_on_start); the others on /arm" if asked
            else "no drive enabled: call /arm (std_srvs/Trigger), or launch with arm:=true"))
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        if self.driver is not None:
            self.driver.hold_motion(self.inactive)  # first: nothing re-enables a drive once it is stopped
        failed = self.stop_drives()
        if failed and self.driver is not None:  # the node stays active, its motion held all the same
            self.driver.hold_motion(f"{self.get_name()}'s deactivate did not confirm every stop"
                                    f" ({'; '.join(failed)}): deactivate it again")
            self.get_logger().error(f"deactivate failed: {len(failed)} stop(s) not confirmed; motion held;"
                                    " deactivate again")
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"inactive: motion held; {self._drives_safe()}; activate to take motion again")
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        said = self._drives_safe()
        self.release()
        self.get_logger().info(f"cleaned up: {said}; the driver closed and the bus released")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        had = self.driver is not None
        self.release()  # the driver's close: its safe stop first
        self.get_logger().info(f"shut down from {state.label}: " + (
            "every drive quick-stopped if enabled and its voltage disabled, the driver closed and the bus released"
            if had else "no driver (nothing was configured)"))
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        had = self.driver is not None
        self.release()
        self.get_logger().error("error processing: " + ("the driver closed (its safe stop first), the bus released"
                                                          if had else "no driver") + "; configure to start again")
        return TransitionCallbackReturn.SUCCESS

    def _drives_safe(self) -> str:
        """What the drives are now, for a transition's line."""
        driver = self.driver
        if driver is None:
            return "no driver"
        return f"{len(driver.drives)} drive(s) quick-stopped if enabled and their voltage disabled (Switch On Disabled)"

    # ------------------------------------------------------------------ steps
    def stop_drives(self) -> list[str]:
        """The driver's safe stop; what was not confirmed, each also logged."""
        failed = [] if self.assembly is None else self.assembly.stop_drives()
        for line in failed:
            self.get_logger().error(f"stop not confirmed: {line}")
        return failed

    def destroy_node(self) -> None:
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine, which holds the node's handle: the node
        # would stay in the graph after it was destroyed and its context shut down (a stale
        # rovercan_lifecycle whose change_state nobody answers)
        self._state_machine.destroy_when_not_in_use()

    def release(self) -> None:
        """The assembly closed (drives safe, threads joined, interface gone, bus released)."""
        if self.assembly is not None:
            self.assembly.close()
            self.assembly = None


def main(args: list[str] | None = None) -> int:
    spinning.init(args)
    with spinning.StopSignal() as stop:
        try:
            node = DriveLifecycleNode()  # the process set-up before configure makes the driver's threads
        except RovercanError as err:
            print(f"rover_lifecycle: {err}", file=sys.stderr)
            rclpy.try_shutdown()
            return 2
        hot = node.hot
        cold = SingleThreadedExecutor()
        cold.add_node(node)
        transitions = spinning.SpinThread(cold, "rovercan-lifecycle")
        try:
            if node.get_parameter("autostart").value:
                node.trigger_configure()
                if node.driver is not None:
                    node.trigger_activate()
            heap.settle()  # built (and, with autostart, the driver too): keep it out of the collector's walks
            spinning.spin_until(hot, stop.event)
        finally:
            transitions.stop(5.0)
            node.release()
            node.destroy_node()
            rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
