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
``rover_driver`` enables them at start only with ``arm``. A stop signal (SIGINT, SIGTERM) during
the auto-start's configure ends it there: nothing is activated or armed. A failed transition logs
why and returns FAILURE; the node stays where it was (after a failed configure, with no driver and
no bus). A transition that raised unexpectedly is logged with its trace and counted
(``callback_failures`` of this node), and ends in ERROR as rclpy makes it: on_error closes the
driver, its safe stop first. A ``change_state`` request for a transition the current state does not
have (Nav2's RESET after PAUSE asks for deactivate twice) is answered ``success=false`` and logged,
as rclcpp's managed nodes answer it (rclpy's own sends no answer: its client, a lifecycle manager,
waits for ever). Transitions run one at a time: the auto-start's and the service's alike. While
active the node keeps a bond with a lifecycle manager (Nav2's waits for it after activate:
:mod:`nodes.process.bond`), unless ``bond_heartbeat_period`` is 0. The failure count is the
process's one: the driver node made at each configure keeps it too, and its /diagnostics ("rovercan:
driver") says this node's failures (the bond's callbacks'; a transition's from the next configure
on) with the drives' own.

Owner: the lifecycle transitions run on the node's service executor thread; the nodes it
makes at configure are served by the process's executors (nodes/assembly.py).
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import State, TransitionCallbackReturn

from can_config.errors import RovercanError
from motor_driver import MotorDriver, StopReport
from motor_driver.process import heap
from nodes.assembly import Assembly, config_of, set_up
from nodes.process import spinning
from nodes.process.bond import BondHeartbeat, bond_interface
from nodes.process.params import declare
from nodes.process.spinning import CallbackFailures

logger = logging.getLogger(__name__)

#: The hot executor counts as hung (the bond withholds its heartbeats) after this many of its state
#: timer's periods without a tick, never sooner than HOT_SILENT_MIN_S, and no later than
#: HOT_SILENT_MAX_S or HOT_SILENT_LEAST_PERIODS periods, whichever is longer (a manager's
#: bond_timeout, 4 s by default in Nav2, then breaks the bond: a state timer at 1 Hz was judged hung
#: only after 25 s; two periods late is a busy machine's, not a hang).
HOT_SILENT_PERIODS = 25
HOT_SILENT_MIN_S = 1.0
HOT_SILENT_MAX_S = 2.0
HOT_SILENT_LEAST_PERIODS = 3
#: How long the shutdown waits for a transition under way before it releases the driver, s.
TRANSITION_WAIT_S = 60.0

Transition = TypeVar("Transition", bound=Callable[..., TransitionCallbackReturn])


def supervised(transition: Transition) -> Transition:
    """A transition callback whose unexpected exception is logged with its trace and counted, then
    ends in ERROR as rclpy makes it (rclpy's lifecycle returns ERROR and logs nothing)."""
    @functools.wraps(transition)
    def call(node: DriveLifecycleNode, state: State) -> TransitionCallbackReturn:
        try:
            return transition(node, state)
        except Exception as err:
            node.callback_failures.record(f"transition {transition.__name__} of {node.get_name()}", err)
            node.get_logger().error(f"{transition.__name__.removeprefix('on_')} failed unexpectedly: {err!r} (its trace"
                                    " logged; counted in callback_failures); the node goes to error processing,"
                                    " which closes the driver, its safe stop first")
            return TransitionCallbackReturn.ERROR
    return call  # type: ignore[return-value]


def hot_silence(silent_s: float, state_period_s: float) -> str:
    """"" while the hot executor's last state tick (``silent_s`` ago, its timer's period
    ``state_period_s``) is recent enough, else why it counts as hung (HOT_SILENT_*)."""
    bound = min(max(HOT_SILENT_PERIODS * state_period_s, HOT_SILENT_MIN_S),
                max(HOT_SILENT_MAX_S, HOT_SILENT_LEAST_PERIODS * state_period_s))
    return "" if silent_s <= bound else (f"the driver's executor has run no state tick for {silent_s:.1f} s (over"
                                         f" {bound:g} s): hung, or starved of CPU")


class DriveLifecycleNode(LifecycleNode):
    def __init__(self, hot: Executor | None = None, **kwargs: Any) -> None:
        """``hot``: where the drives' ROS interface spins; None (``main``): the process set-up from
        this node's parameters (nodes/assembly.py), which may raise :class:`ConfigError`."""
        super().__init__("rovercan_lifecycle", **kwargs)
        declare(self, "config", "sim", "autostart", "bond_heartbeat_period")
        self.hot = set_up(self).hot if hot is None else hot
        self.assembly: Assembly | None = None
        self.bond: BondHeartbeat | None = None  # with a lifecycle manager, while active (nodes/process/bond.py)
        self.callback_failures = CallbackFailures()  # spinning.spin_until counts what escapes here too
        self.transitions = threading.Lock()  # one transition at a time: the auto-start's, the service's
        self.exiting = False  # a stop signal came: no activate takes motion (set by main's thread, once)
        service = self._service_change_state
        service.callback = self._change_state_answered(service.callback)
        spinning.supervise(self, self.callback_failures)  # any other exception: answered, logged, counted

    @property
    def driver(self) -> MotorDriver | None:
        return None if self.assembly is None else self.assembly.driver

    @property
    def inactive(self) -> str:
        """Why motion is refused while the node is not active, and what to do."""
        return f"{self.get_name()} is inactive: activate it"

    @property
    def shutting_down(self) -> str:
        """Why motion is held after a stop signal."""
        return f"{self.get_name()} is shutting down (a stop signal)"

    def stop_for_exit(self) -> None:
        """A stop signal: motion held now, before the wait for a transition under way (it may run
        a minute: a configure's SDO waits), and no activate takes it back (:meth:`on_activate`)."""
        self.exiting = True
        if (driver := self.driver) is not None:
            driver.hold_motion(self.shutting_down)

    @property
    def state_label(self) -> str:
        """The lifecycle state now: "unconfigured", "inactive", "active", "finalized", ..."""
        return str(self._state_machine.current_state[1])

    def _change_state_answered(self, rclpy_change_state: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        """rclpy's change_state service callback, answering ``success=false`` where it raises for a
        transition the current state does not have, as rclcpp answers (rclpy sends no response)."""
        def change_state(request: Any, response: Any) -> Any:
            with self.transitions:
                try:
                    return rclpy_change_state(request, response)
                except RCLError as err:
                    allowed = ", ".join(f"{t[1]} ({t[0]})" for t in self._state_machine.available_transitions)
                    self.get_logger().error(
                        f"change_state refused: transition {request.transition.id}"
                        f"{f' ({request.transition.label})' if request.transition.label else ''} is not allowed from"
                        f" {self.state_label} ({err}); allowed from here: {allowed or 'none'}")
                    response.success = False
                    return response
        return change_state

    def autostart(self, stop: threading.Event) -> None:
        """Configure, then activate (arming only with ``arm``), as a lifecycle manager's STARTUP
        would; nothing after a stop was asked, nor a transition a manager made already."""
        with self.transitions:
            if not stop.is_set() and self.state_label == "unconfigured":
                self.trigger_configure()
            if stop.is_set():
                self.get_logger().info(f"auto-start ended by a stop signal ({self.state_label}): nothing activated")
            elif self.driver is not None and self.state_label == "inactive":
                self.trigger_activate()

    # ------------------------------------------------------------------ transitions
    @supervised
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        try:
            driver = MotorDriver(config_of(self))  # nothing sent yet
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            return TransitionCallbackReturn.FAILURE
        driver.hold_motion(self.inactive)  # before anything could enable a drive (arm_on_start included)
        # one count of the process's callback failures: the driver node's /diagnostics says this node's too
        self.assembly = Assembly(driver, self.hot, context=self.context, failures=self.callback_failures)
        try:
            self.assembly.build()  # the ROS interface first, then the bus (nodes/assembly.py says why)
            self.assembly.start(arm=False)  # connect and boot; nothing enabled: that is activate
        except RovercanError as err:
            self.get_logger().error(f"configure failed: {err}")
            self.release()
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"configured: {len(driver.drives)} drive(s) booted, not enabled; motion held until activate")
        return TransitionCallbackReturn.SUCCESS

    @supervised
    def on_activate(self, state: State) -> TransitionCallbackReturn:
        assembly = self.assembly
        assert assembly is not None and assembly.node is not None
        if not self.exiting:
            assembly.driver.allow_motion()
        if self.exiting:  # a stop signal came (main: stop_for_exit), before or while motion was taken: nothing armed
            assembly.driver.hold_motion(self.shutting_down)
            self.get_logger().error("activate refused: the process is shutting down (a stop signal)")
            return TransitionCallbackReturn.FAILURE
        drives = assembly.node.drives
        asked = None if assembly.node.get_parameter("arm").value else [
            name for name, drive in drives.items() if drive.config.arm_on_start]
        failed = assembly.arm(asked)
        if failed:
            assembly.driver.hold_motion(self.inactive)
            unconfirmed = self.stop_drives().lines  # each logged
            self.get_logger().error(f"activate failed: {'; '.join(failed)}; " + (
                f"{len(unconfirmed)} stop(s) not confirmed (above); motion held" if unconfirmed
                else "every drive is stopped again"))
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info("active: motion taken; " + (
            "every drive armed (arm:=true)" if asked is None else
            f"{', '.join(asked)} armed (arm_on_start); the others on /arm" if asked
            else "no drive enabled: call /arm (std_srvs/Trigger), or launch with arm:=true"))
        self._make_bond()
        return super().on_activate(state)

    @supervised
    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        if self.driver is not None:
            self.driver.hold_motion(self.inactive)  # first: nothing re-enables a drive once it is stopped
        report = self.stop_drives()
        failed = report.retry  # a lost drive's stop fails every deactivate alike: it is said, not retried
        if failed and self.driver is not None:  # the node stays active, its motion held all the same
            self.driver.hold_motion(f"{self.get_name()}'s deactivate did not confirm every stop"
                                    f" ({'; '.join(failed)}): deactivate it again")
            self.get_logger().error(f"deactivate failed: {len(failed)} stop(s) not confirmed; motion held;"
                                    " deactivate again")
            return TransitionCallbackReturn.FAILURE
        self._break_bond()  # as Nav2's managed nodes: the bond ends with the activity (kept while still active)
        lost = f" Lost, their stop unconfirmed: {'; '.join(report.lost)}." if report.lost else ""
        self.get_logger().info(f"inactive: motion held; {self._drives_safe(report)}; activate to take motion again.{lost}")
        return super().on_deactivate(state)

    @supervised
    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        said = self._drives_safe()
        self.release()
        self.get_logger().info(f"cleaned up: {said}; the driver closed and the bus released")
        return TransitionCallbackReturn.SUCCESS

    @supervised
    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        had = self.driver is not None
        self.release()  # the driver's close: its safe stop first
        self.get_logger().info(f"shut down from {state.label}: " + (
            "every drive quick-stopped if enabled and its voltage disabled, the driver closed and the bus released"
            if had else "no driver (nothing was configured)"))
        return TransitionCallbackReturn.SUCCESS

    @supervised
    def on_error(self, state: State) -> TransitionCallbackReturn:
        had = self.driver is not None
        self.release()
        self.get_logger().error("error processing: " + ("the driver closed (its safe stop first), the bus released"
                                                          if had else "no driver") + "; configure to start again")
        return TransitionCallbackReturn.SUCCESS

    def _drives_safe(self, report: StopReport | None = None) -> str:
        """What the drives are now, for a transition's line (``report``: the stop's, whose lost
        drives are not said to be stopped)."""
        driver = self.driver
        if driver is None:
            return "no driver"
        lost = len(report.lost) if report is not None else 0
        return f"{len(driver.drives) - lost} drive(s) quick-stopped if enabled and their voltage disabled" \
               f" (Switch On Disabled){f', {lost} lost' if lost else ''}"

    # ------------------------------------------------------------------ steps
    def stop_drives(self) -> StopReport:
        """The driver's safe stop; what was not confirmed, each also logged."""
        report = StopReport([], []) if self.assembly is None else self.assembly.stop_drives()
        for line in report.lines:
            self.get_logger().error(f"stop not confirmed: {line}")
        return report

    def destroy_node(self) -> None:
        super().destroy_node()
        # rclpy's LifecycleNode leaves its state machine, which holds the node's handle: the node
        # would stay in the graph after it was destroyed and its context shut down (a stale
        # rovercan_lifecycle whose change_state nobody answers)
        self._state_machine.destroy_when_not_in_use()

    def _make_bond(self) -> None:
        """The bond with a lifecycle manager (Nav2's waits for it after each activate), where asked
        (``bond_heartbeat_period`` > 0) and the bond interface is installed."""
        period = float(self.get_parameter("bond_heartbeat_period").value)
        if period <= 0.0 or self.bond is not None:
            return
        status = bond_interface()
        if status is None:
            self.get_logger().warning("no bond with a lifecycle manager: the bond interface package is not installed"
                                      " (apt: ros-jazzy-bond); a Nav2 lifecycle_manager with bond_timeout > 0 fails"
                                      " its STARTUP here: install it, or set the manager's bond_timeout to 0")
            return
        try:
            self.bond = BondHeartbeat(self, status, period, alive=self._work_runs)
        except Exception as err:  # activate stands (the drives are armed as asked): a manager will say the rest
            self.callback_failures.record(f"the bond of {self.get_name()}", err)
            self.get_logger().warning(f"no bond with a lifecycle manager: it could not be made ({err!r}); a Nav2"
                                      " lifecycle_manager with bond_timeout > 0 fails its STARTUP here")
            return
        spinning.supervise(self, self.callback_failures)  # its timer and subscription, as the node's others

    def _work_runs(self) -> str:
        """"" while the hot executor runs the driver node's state timer, else why not: the bond's
        heartbeats come from this node's own thread, which serves only the transitions, and a hung
        hot executor (no command, no /odom) would have kept them going."""
        node = self.assembly.node if self.assembly is not None else None
        if node is None:
            return ""
        return hot_silence(time.monotonic() - node.ticked_at, node.state_period_s)

    def _break_bond(self) -> None:
        """The bond broken where there is one; a failure of it logged and counted, never raised: it
        must not keep a stop or a release from running."""
        bond, self.bond = self.bond, None
        if bond is not None:
            try:
                bond.close()
            except Exception as err:
                self.callback_failures.record(f"breaking the bond of {self.get_name()}", err)

    def release(self) -> None:
        """The assembly closed (drives safe, threads joined, interface gone, bus released), then the
        bond broken."""
        try:
            if self.assembly is not None:
                self.assembly.close()
                self.assembly = None
        finally:
            self._break_bond()


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
                node.autostart(stop.event)
            heap.settle()  # built (and, with autostart, the driver too): keep it out of the collector's walks
            spinning.spin_until(hot, stop.event)
        finally:
            node.stop_for_exit()  # motion held before any wait: a transition under way arms nothing
            transitions.stop(5.0)
            # a transition a manager asked for may still run on the stopped executor's thread (a
            # configure's SDO waits): the release waits for it, else it would close a driver a
            # configure then replaced, or arm one being closed
            if not node.transitions.acquire(timeout=TRANSITION_WAIT_S):
                logger.error("a lifecycle transition still runs after %g s; releasing the driver all the same",
                             TRANSITION_WAIT_S)
            try:
                node.release()  # each step runs; a step that raised is logged and raised here
            finally:
                node.destroy_node()
                rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
