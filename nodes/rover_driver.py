"""``rover_driver``: the ROS 2 face of every configured drive, and the rover's drive system.

Per drive (under the drive's ``namespace`` from the config, if any, then its joint name;
relative to the node's namespace):
  topics   <joint>/degree_cmd (std_msgs/Float32, deg; the joint's position_mode), <joint>/velocity_cmd (Float32, deg/s),
           <joint>/motor_state (rovercan_msgs/MotorState)
  services <joint>/enable, disable, halt, quick_stop, recover, home (std_srvs/Trigger),
           <joint>/set_mode (SetMode), <joint>/sdo_read (SdoRead), <joint>/sdo_write (SdoWrite)
All drives: /joint_states (rad, rad/s, Nm), /joint_commands (sensor_msgs/JointState targets),
/diagnostics; actions home_joint (rovercan_msgs/Home) and move_joint (MoveJoint) with
feedback and cancel (nodes/actions.py). The default joint also serves the team's /motor_degree_cmd and /motor_state.
With a ``drive_system`` in the config, ``drive_system`` takes /cmd_vel and publishes /odom.

Executors, by measurement (README): two single-threaded executors, a hot one for commands,
state and the drive system (small wait set: every wake-up rebuilds it in Python) and a cold
one, on its own thread, for the services, which block for up to seconds (enable, home); the
actions on one of their own (their goals are coroutines: nodes/actions.py).

What lives where: this module (the joints' topics, ``main``), :mod:`nodes.driver_services`
(services), :mod:`nodes.drive_system` (/cmd_vel), :mod:`nodes.refusals` (shared helpers).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import Executor
from rclpy.node import Node
from rovercan_msgs.msg import MotorState
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32

from can_config import heap, load_config
from can_config.errors import RovercanError
from can_config.stop import StopSignal
from motor_driver import Drive, MotorDriver
from motor_driver.health import bus_health, drive_health
from nodes import runtime
from nodes.actions import DriverActionsNode
from nodes.drive_system import DriveSystemNode
from nodes.driver_services import SERVICE_JOIN_S, DriverServicesNode, DriverStopsNode
from nodes.logbridge import bridge_core_logging, unbridge
from nodes.motor_controller import fill_motor_state
from nodes.params import declare, qos_depth
from nodes.qos import DIAGNOSTICS_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS, SETPOINT_QOS, state_qos
from nodes.refusals import DEG, WARN_THROTTLE_S, RefusalLog, stamp_header

T = TypeVar("T")


class DriverNode(Node):
    """Topics, services and diagnostics of every drive of a :class:`MotorDriver`."""

    def __init__(self, driver: MotorDriver, **kwargs: Any) -> None:
        super().__init__("rovercan_driver", **kwargs)
        declare(self, "config", "executor", "realtime_priority", "arm", "drive_system", "default_joint", "state_rate_hz",
                "diagnostics_rate_hz", "state_qos_depth")
        self.driver = driver
        self._state_qos = state_qos(qos_depth(self))
        self.refusals = RefusalLog(self.get_logger().warning)
        self._states: dict[str, MotorState] = {}
        self._state_pubs: dict[str, Any] = {}
        joints = list(driver.drives)
        default = str(self.get_parameter("default_joint").value) or joints[0]
        if default not in driver.drives:
            raise RovercanError(f"default_joint {default!r} is not a configured joint; joints: {joints}")
        for name, drive in driver.drives.items():
            self._add_drive(name, drive)
        self._default = default
        self._demo_state_pub = self.create_publisher(MotorState, "/motor_state", self._state_qos,
                                                     event_callbacks=NO_PUB_EVENTS)
        self.create_subscription(Float32, "/motor_degree_cmd", self._on_degree(default), SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self._joint_pub = self.create_publisher(JointState, "/joint_states", self._state_qos, event_callbacks=NO_PUB_EVENTS)
        self.create_subscription(JointState, "/joint_commands", self._on_joint_commands, SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS, event_callbacks=NO_PUB_EVENTS)
        self.state_period_s = 1.0 / float(self.get_parameter("state_rate_hz").value)
        self._tick_hooks: list[Callable[[], None]] = []
        self.create_timer(self.state_period_s, self._tick)
        self.create_timer(1.0 / float(self.get_parameter("diagnostics_rate_hz").value), self._publish_diagnostics)

    def arm_if_asked(self) -> None:
        """Enable every drive when the ``arm`` parameter says so. Called once every node and
        entity exists: creating ROS entities holds the interpreter (C++ under the GIL), and
        the drives watch the driver's heartbeat from the moment they are armed."""
        if self.get_parameter("arm").value:
            for drive in self.driver:
                self._guard(drive.name, "arm", drive.enable)

    # --------------------------------------------------------------------- wiring
    def _add_drive(self, name: str, drive: Drive) -> None:
        self._states[name] = MotorState()
        base = drive.config.ros_prefix
        self._state_pubs[name] = self.create_publisher(MotorState, f"{base}/motor_state", self._state_qos,
                                                       event_callbacks=NO_PUB_EVENTS)
        self.create_subscription(Float32, f"{base}/degree_cmd", self._on_degree(name), SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self.create_subscription(Float32, f"{base}/velocity_cmd", self._on_velocity(name), SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)

    def _guard(self, joint: str, what: str, fn: Callable[..., T], *args: float) -> T | None:
        """``fn(*args)``; every failure becomes a throttled warning and a diagnostic. ``what``
        (with ``{!r}`` for the value, if it shows it) is formatted only then: not once per command."""
        try:
            return fn(*args)
        except RovercanError as err:
            self.refusals.refuse(joint, f"{what.format(*args)}: {err}")
        except Exception as err:  # never raise into the executor
            self.refusals.refuse(joint, f"{what.format(*args)}: unexpected {err!r}")
        return None

    def _on_degree(self, joint: str) -> Callable[[Float32], None]:
        drive = self.driver.drives[joint]

        def on_message(msg: Float32) -> None:
            self._guard(joint, "degree command {!r}", drive.command_position, msg.data)
        return on_message

    def _on_velocity(self, joint: str) -> Callable[[Float32], None]:
        drive = self.driver.drives[joint]

        def on_message(msg: Float32) -> None:
            self._guard(joint, "velocity command {!r}", drive.command_velocity, msg.data)
        return on_message

    def _on_joint_commands(self, msg: JointState) -> None:
        for i, name in enumerate(msg.name):
            drive = self.driver.drives.get(name)
            if drive is None:
                self.refusals.refuse(name or "?", f"/joint_commands names unknown joint {name!r};"
                                     f" joints: {sorted(self.driver.drives)}")
                continue
            # the first field given for this joint; NaN means "not commanded" (ros2_control's
            # topic-based hardware interface sends NaN in the fields it does not command)
            position, velocity, effort = (_given(values, i) for values in (msg.position, msg.velocity, msg.effort))
            if position is not None:
                self._guard(name, "joint position", drive.command_position, position * DEG)
            elif velocity is not None:
                self._guard(name, "joint velocity", drive.command_velocity, velocity * DEG)
            elif effort is not None:
                self._guard(name, "joint effort", drive.command_torque, effort)
            else:
                self.refusals.refuse(name, "/joint_commands entry has no position, velocity or effort (or only NaN)")

    # --------------------------------------------------------------------- publishing
    def share_tick(self, period_s: float, hook: Callable[[], None]) -> bool:
        """Run ``hook`` from this node's state timer, before the states are published, when its
        period is this timer's (True; the caller then drops its own timer): one wake-up of the
        hot executor a period instead of two (the drive system's control loop: docs/performance.md)."""
        if not math.isclose(period_s, self.state_period_s, rel_tol=1e-9):
            return False
        self._tick_hooks.append(hook)
        return True

    def _tick(self) -> None:
        for hook in self._tick_hooks:
            try:
                hook()
            except Exception as err:  # the states are published all the same
                self.get_logger().error(f"tick of {hook!r} failed: {err!r}", throttle_duration_sec=WARN_THROTTLE_S)
        self._publish_states()

    def _publish_states(self) -> None:
        """MotorState per joint, /motor_state and /joint_states: each built and published only
        while something subscribes (a message nobody reads was a fifth of the node's interpreter
        time in the six-drive profile, docs/performance.md)."""
        try:
            joints = self._joint_pub.get_subscription_count() > 0
            joint = JointState() if joints else None  # a message's constructor: ~20 us, 50 times a second
            newest = 0.0
            for name, drive in self.driver.drives.items():
                mine = self._state_pubs[name].get_subscription_count() > 0
                demo = name == self._default and self._demo_state_pub.get_subscription_count() > 0
                if not (mine or demo or joints):
                    continue
                state = drive.snapshot()
                if mine or demo:
                    msg = fill_motor_state(self._states[name], state, drive.config.is_continuous)
                    if mine:
                        self._state_pubs[name].publish(msg)
                    if demo:
                        self._demo_state_pub.publish(msg)
                if joint is not None:
                    joint.name.append(name)
                    stale = math.nan if state.stale else 1.0  # stale joints: NaN, not the last values again
                    joint.position.append(math.radians(state.angle_deg) * stale)
                    joint.velocity.append(math.radians(state.velocity_deg_s) * stale)
                    joint.effort.append(state.torque_nm * stale)
                    newest = max(newest, state.stamp)
            if joint is not None:
                stamp_header(joint.header, newest or time.time())
                self._joint_pub.publish(joint)
        except Exception as err:
            self.get_logger().error(f"state publish failed: {err!r}", throttle_duration_sec=WARN_THROTTLE_S)

    def _publish_diagnostics(self) -> None:
        try:
            array = DiagnosticArray()
            stamp_header(array.header, time.time())
            for name, drive in self.driver.drives.items():
                refused, last = self.refusals.take(name)
                health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s,
                                      refused_since_last=refused, last_refusal=last,
                                      bus_lost=self.driver.bus_lost.get(drive.config.bus, False),
                                      tpdos_applied=drive.tpdo_count, safety=drive.safety)
                array.status.append(DiagnosticStatus(
                    level=bytes([health.level]), name=f"rovercan: {name}", message=health.message,
                    hardware_id=f"{drive.config.bus}/node{drive.node_id}",
                    values=[KeyValue(key=k, value=v) for k, v in health.values.items()]))
            refused, last = self.refusals.take_others(self.driver.drives)
            array.status.append(DiagnosticStatus(
                level=bytes([1 if refused else 0]), name="rovercan: command input",
                message=f"{refused} command(s) refused: {last}" if refused else "no refused commands",
                hardware_id="ros", values=[KeyValue(key="refused_commands", value=str(refused)),
                                           KeyValue(key="last_refusal", value=last)]))
            for bus_name, handle in self.driver.buses.items():
                kernel, why = self.driver.kernel_health(bus_name)
                health = bus_health(load=handle.stats.sample(), lost=self.driver.bus_lost.get(bus_name, False),
                                    frames=handle.stats.frames, error_frames=handle.stats.error_frames,
                                    kernel=kernel, why_unknown=why, tx_queue_full=handle.network.tx_queue_full,
                                    tx_not_sent=handle.network.tx_queue_dropped)
                array.status.append(DiagnosticStatus(
                    level=bytes([health.level]), name=f"rovercan: bus {bus_name}", message=health.message,
                    hardware_id=bus_name, values=[KeyValue(key=k, value=v) for k, v in health.values.items()]))
            self._diag_pub.publish(array)
        except Exception as err:
            self.get_logger().error(f"diagnostics publish failed: {err!r}", throttle_duration_sec=WARN_THROTTLE_S)


def _given(values: Sequence[float], i: int) -> float | None:
    """``values[i]`` when the message has it and it is not NaN (NaN: the field is not commanded);
    an infinite value is given, and the driver refuses it by name."""
    if i >= len(values) or math.isnan(values[i]):
        return None
    return float(values[i])


def main(args: list[str] | None = None) -> int:
    runtime.init(args)
    with StopSignal() as stop:
        return _run(stop)


def _run(stop: StopSignal) -> int:
    # read before the driver node exists (same name, so a params file's values apply)
    boot = rclpy.create_node("rovercan_driver")
    declare(boot, "config", "executor", "realtime_priority")
    path = str(boot.get_parameter("config").value) or None
    executor_kind = str(boot.get_parameter("executor").value)
    try:
        # before the driver's threads exist: each inherits it (DDS's, made already, are set here)
        runtime.go_realtime(boot)
    except RovercanError as err:
        print(f"rover_driver: {err}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    finally:
        boot.destroy_node()
    try:
        hot = runtime.make_executor(executor_kind)
        config = load_config(path)
        driver = MotorDriver(config)  # buses opened, drives made: nothing sent, no heartbeat yet
    except RovercanError as err:
        print(f"rover_driver: {err}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    nodes: list[Node] = []
    spinning: list[runtime.SpinThread] = []
    handler = None
    rc = 0
    try:
        # every ROS entity first: making them holds the interpreter (rclpy's C++ under the GIL) for
        # up to a second on a slow machine, and once the driver has started, its heartbeat must not
        # wait (the drives' 150 ms host watch tripped in 2 of 10 launches of the shipped rover)
        node = DriverNode(driver)
        nodes.append(node)
        handler = bridge_core_logging(node)
        if config.drive_system is not None and node.get_parameter("drive_system").value:
            nodes.append(DriveSystemNode.beside(node, driver, config))  # both on the hot executor
        waiting = (DriverServicesNode(driver), DriverStopsNode(driver), DriverActionsNode(driver))
        # executors (measured: README): the hot one for commands, state and the drive system;
        # a cold one, on its own thread, for the services that block (enable, home); one for
        # the stops, which never queue behind those; one for the actions, whose goals are
        # coroutines (nodes/actions.py)
        for n in nodes:
            hot.add_node(n)
        nodes += waiting
        heap.settle()  # the nodes are built: what exists now lives as long as the process (a full
        # collection stops every thread, so it comes before the heartbeat starts)
        rc = _start_and_spin(driver, node, waiting, hot, spinning, stop)
    finally:
        # order: drives safe first (a service blocked on a drive then fails fast), then the
        # service thread joined, then nodes destroyed, then the context
        driver.close()
        joined = all([spin.stop(timeout_s=SERVICE_JOIN_S) for spin in spinning])  # every one stopped
        if handler is not None:
            unbridge(handler)
        if joined:  # a thread still inside rclpy must not see its node destroyed under it
            for n in nodes:
                n.destroy_node()
        rclpy.try_shutdown()
    return rc


def _start_and_spin(driver: MotorDriver, node: DriverNode, waiting: tuple[Node, Node, Node], hot: Executor,
                    spinning: list[runtime.SpinThread], stop: StopSignal) -> int:
    """Start the driver (look for another master, boot every drive: their host watch is armed
    from here on), the threads of the services, stops and actions, arm if asked, and spin the hot
    executor until stopped."""
    try:
        driver.start()
    except RovercanError as err:
        print(f"rover_driver: {err}", file=sys.stderr)
        return 2
    node.get_logger().info(f"{len(driver.drives)} drive(s) on {len(driver.config.buses)} bus(es) booted; "
                           + ("arming them" if node.get_parameter("arm").value else
                              "not armed: call /arm (std_srvs/Trigger) or launch with arm:=true"))
    for waiter, name in zip(waiting, ("rovercan-services", "rovercan-stops", "rovercan-actions"), strict=True):
        spinning.append(runtime.spin_alone(waiter, name))
    node.arm_if_asked()
    runtime.spin_until(hot, stop.event)
    return 0


__all__ = ["DriveSystemNode", "DriverNode", "DriverServicesNode", "DriverStopsNode", "main"]

if __name__ == "__main__":
    sys.exit(main())
