"""The driver node (``rover_driver``'s): the ROS 2 face of every configured drive, and the rover's
drive system beside it.

Per drive (under the drive's ``namespace`` from the config, if any, then its joint name;
relative to the node's namespace):
  topics   <joint>/degree_cmd (std_msgs/Float32, deg; the joint's position_mode), <joint>/velocity_cmd (Float32, deg/s),
           <joint>/motor_state (rovercan_msgs/MotorState)
  services <joint>/enable, disable, halt, quick_stop, recover, home (std_srvs/Trigger),
           <joint>/set_mode (SetMode), <joint>/sdo_read (SdoRead), <joint>/sdo_write (SdoWrite)
All drives: /joint_states (rad, rad/s, Nm), /joint_commands (sensor_msgs/JointState targets),
/diagnostics; actions home_joint (rovercan_msgs/Home) and move_joint (MoveJoint) with
feedback and cancel (nodes/actions/driver_actions.py). The default joint also serves the team's /motor_degree_cmd and /motor_state.
With a ``drive_system`` in the config, ``drive_system`` takes /cmd_vel and publishes /odom.
The demo topics /motor_degree_cmd and /motor_state are served for ``default_joint`` only when
it is set: the team's demo publisher moves no joint on a guess.

The process (executors, callback groups, start order, safe stop) is assembled in
:mod:`nodes.assembly`, the same for every entry point: four executors, the hot one for commands,
state and the drive system, one for the stops, one for the services that wait (a callback group
per joint: one joint's homing holds no other joint's services) and one for the actions.

What lives where: this module (the joints' topics), :mod:`nodes.rover_driver` (``main``), :mod:`nodes.joints.handoff` (a command
that waits for its drive, sent by a worker of its joint, off the hot thread),
:mod:`nodes.joints.driver_services` (services), :mod:`nodes.rover.drive_system` (/cmd_vel), :mod:`nodes.joints.refusals`
(shared helpers).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rovercan_msgs.msg import MotorState
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32

from can_config.errors import ConfigError, RovercanError
from motor_driver import Drive, DriveState, MotorDriver
from motor_driver.bus.adapters import HeldFramesLost
from motor_driver.diagnostics.frameloss import Counts, FrameLoss, Loss, total
from motor_driver.diagnostics.health import ERROR, JOB_FAULT_RECENT_S, OK, WARN, Rejections, bus_health, drive_health, with_boot
from motor_driver.protocol.units import DEG_PER_RAD
from motor_driver.recording.published import joint_entry
from nodes.joints.handoff import Handoff
from nodes.joints.messages import fill_motor_state, stamp_header
from nodes.joints.rawcmd import float32_data
from nodes.joints.refusals import RefusalLog
from nodes.process.params import DRIVER, ONE_JOINT, declare, qos_depth
from nodes.process.qos import DIAGNOSTICS_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS, SETPOINT_QOS, state_qos
from nodes.process.spinning import CallbackFailures


class DriverNode(Node):
    """Topics and diagnostics of the drives of a :class:`MotorDriver`: every drive, or the
    ``joints`` named (``motor_controller``: one)."""

    def __init__(self, driver: MotorDriver | None, name: str = "rovercan_driver", joints: Sequence[str] | None = None,
                 *, one_joint: bool = False, failures: CallbackFailures | None = None, **kwargs: Any) -> None:
        """Its parameters declared; with ``driver``, :meth:`serve` at once. ``failures``: where this
        process's callback failures are counted, if not a count of its own (rover_lifecycle's, which
        lives across configures: its transitions' and its bond's failures reach /diagnostics too). ``one_joint``
        (``motor_controller``): the node serves the joint of its ``joint`` parameter, which is its
        demo joint too. Without ``driver`` the entry point reads the process's parameters from this
        node first (nodes/assembly.py: the scheduling before the driver's threads exist), then serves."""
        super().__init__(name, **kwargs)
        #: the callbacks of this process's nodes that raised (nodes/process/spinning.py: supervise); in /diagnostics
        self.callback_failures = CallbackFailures() if failures is None else failures
        declare(self, *(ONE_JOINT if one_joint else DRIVER))
        self._one_joint = one_joint
        if driver is not None:
            self.serve(driver, joints)

    def joint(self) -> str:
        """``one_joint``: the ``joint`` parameter, which must name a joint (nothing moves on a guess)."""
        joint = str(self.get_parameter("joint").value)
        if not joint:
            raise ConfigError(f"parameter joint is empty: {self.get_name()} moves only the joint named;"
                              " set -p joint:=<joint of the config>")
        return joint

    def serve(self, driver: MotorDriver, joints: Sequence[str] | None = None) -> None:
        """Every ROS entity of the drives of ``driver`` (all, those of ``joints``, or with
        ``one_joint`` the ``joint`` parameter's); nothing sent on the bus."""
        if self._one_joint:
            joints = [self.joint()]
        self.driver = driver
        self.drives = served(driver, joints)
        self._state_qos = state_qos(qos_depth(self))
        self.refusals = RefusalLog(self.get_logger().warning)
        #: each drive's frames expected against received (the diagnostics timer's alone)
        self.frame_loss = {name: FrameLoss(d.cache.tpdos_per_sync, d.cache.sync_period_s,
                                           None if d.cache.guarding else d.config.heartbeat_period_s,
                                           d.config.frame_loss_window_syncs) for name, d in self.drives.items()}
        #: the joints' commands that must wait for their drive, off the hot thread (nodes/joints/handoff.py);
        #: the drive system beside this node sends through it too
        self.handoff = Handoff(self.drives)
        self._states: dict[str, MotorState] = {}
        self._state_pubs: dict[str, Any] = {}
        default = self.joint() if self._one_joint else str(self.get_parameter("default_joint").value)
        if default and default not in self.drives:
            raise RovercanError(f"parameter default_joint = {default!r}: not a joint of this node; joints:"
                                f" {list(self.drives)}; set -p default_joint:=<joint>, or leave it empty (no demo topics)")
        for joint, drive in self.drives.items():
            self._add_drive(joint, drive)
        self._default = default
        self._demo_state_pub = None
        self.get_logger().info(f"the demo topic /motor_degree_cmd moves {default}" if default else
                               "the demo topic /motor_degree_cmd moves no joint (default_joint is empty)")
        if default:  # the team's demo topics, for the joint named: never for a guessed one
            self._demo_state_pub = self.create_publisher(MotorState, "/motor_state", self._state_qos,
                                                         event_callbacks=NO_PUB_EVENTS)
            self._command_topic("/motor_degree_cmd", default, "degree command {!r}", self.drives[default].command_position)
        self._joint_pub = self.create_publisher(JointState, "/joint_states", self._state_qos, event_callbacks=NO_PUB_EVENTS)
        self.create_subscription(JointState, "/joint_commands", self._on_joint_commands, SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS, event_callbacks=NO_PUB_EVENTS)
        self.state_period_s = 1.0 / float(self.get_parameter("state_rate_hz").value)
        self._tick_hooks: list[Callable[[], None]] = []
        self.ticked_at = time.monotonic()  # the state timer's last run (monotonic): the hot executor's sign of life
        self._state_timer = self.create_timer(self.state_period_s, self._tick)
        self._diag_timer = self.create_timer(1.0 / float(self.get_parameter("diagnostics_rate_hz").value),
                                             self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._may_set)
        self.add_post_set_parameters_callback(self._apply_set)

    def arm_if_asked(self) -> None:
        """Enable every drive when the ``arm`` parameter says so. Called once every node and
        entity exists: creating ROS entities holds the interpreter (C++ under the GIL), and
        the drives watch the driver's heartbeat from the moment they are armed."""
        if self.get_parameter("arm").value:
            for name, drive in self.drives.items():
                try:
                    drive.enable()
                except Exception as err:  # every drive is tried; each failure said
                    self.refused(name, "arm", 0.0, err)

    # --------------------------------------------------------------------- parameters set at run time
    def _may_set(self, params: list[Parameter]) -> SetParametersResult:
        """Those read once at start are read-only (rclpy refuses them first: nodes/process/params.py); the
        state rate is refused while the drive system's control loop shares its timer."""
        if self._tick_hooks and any(p.name == "state_rate_hz" for p in params):
            return SetParametersResult(successful=False, reason=(
                "state_rate_hz: the drive system's control loop runs on this timer at odom_rate_hz, read at start;"
                " restart the node with both rates set"))
        return SetParametersResult(successful=True)

    def _apply_set(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name == "state_rate_hz":
                self.state_period_s = 1.0 / float(p.value)
                self._state_timer.timer_period_ns = int(self.state_period_s * 1e9)
            elif p.name == "diagnostics_rate_hz":
                self._diag_timer.timer_period_ns = int(1e9 / float(p.value))

    # --------------------------------------------------------------------- wiring
    def _add_drive(self, name: str, drive: Drive) -> None:
        self._states[name] = MotorState()
        base = drive.config.ros_prefix
        self._state_pubs[name] = self.create_publisher(MotorState, f"{base}/motor_state", self._state_qos,
                                                       event_callbacks=NO_PUB_EVENTS)
        self._command_topic(f"{base}/degree_cmd", name, "degree command {!r}", drive.command_position)
        self._command_topic(f"{base}/velocity_cmd", name, "velocity command {!r}", drive.command_velocity)

    def destroy_node(self) -> None:
        if hasattr(self, "handoff"):  # served
            self.handoff.close()
        super().destroy_node()

    def command(self, joint: str, what: str, command: Callable[..., object], value: float) -> bool:
        """``command(value)`` for ``joint``: sent at once from this (the hot) thread (True), or by the
        handoff's worker when it must wait for the drive (nodes/joints/handoff.py); a refusal, here or
        there, is counted and said by :meth:`refused`."""
        try:
            return self.handoff.send(joint, command, value, what, self.refused)
        except Exception as err:  # never raise into the executor
            self.refused(joint, what, value, err)
            return False

    def refused(self, joint: str, what: str, value: float, err: Exception) -> None:
        """A command of ``joint`` was refused: a throttled warning and a diagnostic (``what``, with
        ``{!r}`` for the value if it shows it, is formatted only now: not once per command)."""
        why = str(err) if isinstance(err, RovercanError) else f"unexpected {err!r}"
        self.refusals.refuse(joint, f"{what.format(value)}: {why}")

    def _on_float(self, topic: str, joint: str, what: str, command: Callable[..., None]) -> Callable[[bytes], None]:
        """A Float32 command topic's callback, its message taken raw (nodes/joints/rawcmd.py: no
        message object made per command)."""
        def on_message(raw: bytes) -> None:
            try:
                value = float32_data(raw, topic)
            except RovercanError as err:
                self.refusals.refuse(joint, str(err))
                return
            self.command(joint, what, command, value)
        return on_message

    def _command_topic(self, topic: str, joint: str, what: str, command: Callable[..., None]) -> None:
        self.create_subscription(Float32, topic, self._on_float(topic, joint, what, command),
                                 SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS, raw=True)

    def _on_joint_commands(self, msg: JointState) -> None:
        """Each joint named: its first field given, sent at once; the set-points of one message go
        out in one write a bus (MotorDriver.one_write). A bus that failed refuses the joints this
        thread commanded on it: those whose frames were lost (not one refused, handed to the worker or
        parked in its handshake), or all of them where the bus failed after the write."""
        if len(msg.name) < 2:  # nothing to put in one write
            for i, name in enumerate(msg.name):
                self._joint_command(msg, i, name)
            return
        sent: list[str] = []
        with self.driver.one_write() as failed:
            for i, name in enumerate(msg.name):
                if self._joint_command(msg, i, name):
                    sent.append(name)
        for bus, err in failed:
            lost = err.can_ids if isinstance(err, HeldFramesLost) else None
            why = (f"the set-point was not sent: bus {bus}: {err}" if lost is not None
                   else f"bus {bus} failed after the set-point was written: {err!r}")
            for name in sent:
                drive = self.drives[name]
                if drive.config.bus == bus and (lost is None or drive.channel.rpdo_ids.intersection(lost)):
                    self.refusals.refuse(name, f"/joint_commands: {why}")

    def _joint_command(self, msg: JointState, i: int, name: str) -> bool:
        """Entry ``i`` of a /joint_commands message: True when sent at once from this thread (else
        refused, or handed to the worker)."""
        drive = self.drives.get(name)
        if drive is None:
            self.refusals.refuse(name or "?", f"/joint_commands names unknown joint {name!r};"
                                 f" joints: {sorted(self.drives)}")
            return False
        # the first field given for this joint; NaN means "not commanded" (ros2_control's
        # topic-based hardware interface sends NaN in the fields it does not command)
        position, velocity, effort = (_given(values, i) for values in (msg.position, msg.velocity, msg.effort))
        if position is not None:
            return self.command(name, "joint position", drive.command_position, position * DEG_PER_RAD)
        if velocity is not None:
            return self.command(name, "joint velocity", drive.command_velocity, velocity * DEG_PER_RAD)
        if effort is not None:
            return self.command(name, "joint effort", drive.command_torque, effort)
        self.refusals.refuse(name, "/joint_commands entry has no position, velocity or effort (or only NaN)")
        return False

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
        self.ticked_at = time.monotonic()  # this thread's, read by the bond (nodes/rover_lifecycle.py)
        for hook in self._tick_hooks:
            try:
                hook()
            except Exception as err:  # the states are published all the same; logged once, counted
                self.callback_failures.record(f"timer {self.get_name()}: tick of {getattr(hook, '__qualname__', hook)}",
                                              err)
        self._publish_states()

    def _publish_states(self) -> None:
        """MotorState per joint, /motor_state and /joint_states: each built and published only
        while something subscribes (a message nobody reads was a fifth of the node's interpreter
        time in the six-drive profile, docs/performance.md)."""
        try:
            joints = self._joint_pub.get_subscription_count() > 0
            joint = JointState() if joints else None  # a message's constructor: ~20 us, 50 times a second
            newest = 0.0
            for name, drive in self.drives.items():
                mine = self._state_pubs[name].get_subscription_count() > 0
                demo = (name == self._default and self._demo_state_pub is not None
                        and self._demo_state_pub.get_subscription_count() > 0)
                if not (mine or demo or joints):
                    continue
                state = drive.snapshot()
                if mine or demo:
                    msg = fill_motor_state(self._states[name], state, drive.config.is_continuous)
                    if mine:
                        self._state_pubs[name].publish(msg)
                    if demo and self._demo_state_pub is not None:
                        self._demo_state_pub.publish(msg)
                if joint is not None:
                    joint.name.append(name)
                    position, velocity, effort = joint_entry(state)  # stale joints: NaN, not the last values again
                    joint.position.append(position)
                    joint.velocity.append(velocity)
                    joint.effort.append(effort)
                    newest = max(newest, state.stamp)
            if joint is not None:
                stamp_header(joint.header, newest or time.time())
                self._joint_pub.publish(joint)
        except Exception as err:
            self.callback_failures.record(f"timer {self.get_name()}: the state publish", err)

    def _publish_diagnostics(self) -> None:
        """/diagnostics: a status per drive, the command input, a status per bus and the driver's.
        A status whose making raised is counted and said in its place, ERROR: one drive's never
        silences the others', nor the driver's, which counts it."""
        try:
            array = DiagnosticArray()
            stamp_header(array.header, time.time())
            losses: dict[str, list[Loss]] = {}
            for name, drive in self.drives.items():
                array.status.append(self._status_of(f"rovercan: {name}", f"{drive.config.bus}/node{drive.node_id}",
                                                    partial(self._drive_status, name, drive, losses)))
            array.status.append(self._status_of("rovercan: command input", "ros", self._input_status))
            for bus_name in self.driver.buses:
                array.status.append(self._status_of(f"rovercan: bus {bus_name}", bus_name,
                                                    partial(self._bus_status, bus_name, losses)))
            array.status.append(self._status_of("rovercan: driver", "driver", self._driver_status))
            self._diag_pub.publish(array)
        except Exception as err:
            self.callback_failures.record(f"timer {self.get_name()}: the diagnostics publish", err)

    def _status_of(self, name: str, hardware_id: str, make: Callable[[], DiagnosticStatus]) -> DiagnosticStatus:
        """``make()``; if it raises, the failure counted and an ERROR status ``name`` saying it."""
        try:
            return make()
        except Exception as err:
            said = self.callback_failures.record(f"timer {self.get_name()}: the diagnostics of {name}", err)
            return DiagnosticStatus(level=bytes([ERROR]), name=name, hardware_id=hardware_id,
                                    message=f"its diagnostics failed: {said}")

    def _drive_status(self, name: str, drive: Drive, losses: dict[str, list[Loss]]) -> DiagnosticStatus:
        refused, last = self.refusals.take(name)
        rejected = self.driver.rejected(drive)
        state = drive.snapshot()
        loss = self._frame_loss(name, drive, state)
        if loss is not None:
            losses.setdefault(drive.config.bus, []).append(loss)
        health = drive_health(state, heartbeat_period_s=drive.config.heartbeat_period_s,
                              refused_since_last=refused, last_refusal=last,
                              bus_lost=self.driver.bus_lost.get(drive.config.bus, False),
                              tpdos_applied=drive.cache.tpdo_count, safety=drive.boot.safety,
                              rejected=Rejections.of(rejected, time.monotonic()),
                              frame_loss=loss, frame_loss_warn_percent=drive.config.frame_loss_warn_percent)
        if (record := self.driver.supervisor.records.get(name)) is not None:
            health = with_boot(health, record)
        health.values["wrong_length_tpdos"] = str(drive.cache.wrong_length_tpdos)
        health.values["stale_statuswords"] = str(drive.cache.stale_statuswords)
        return DiagnosticStatus(level=bytes([health.level]), name=f"rovercan: {name}", message=health.message,
                                hardware_id=f"{drive.config.bus}/node{drive.node_id}",
                                values=[KeyValue(key=k, value=v) for k, v in health.values.items()])

    def _input_status(self) -> DiagnosticStatus:
        refused, last = self.refusals.take_others(self.drives)
        return DiagnosticStatus(
            level=bytes([1 if refused else 0]), name="rovercan: command input",
            message=f"{refused} command(s) refused: {last}" if refused else "no refused commands",
            hardware_id="ros", values=[KeyValue(key="refused_commands", value=str(refused)),
                                       KeyValue(key="last_refusal", value=last)])

    def _bus_status(self, bus_name: str, losses: dict[str, list[Loss]]) -> DiagnosticStatus:
        handle = self.driver.buses[bus_name]
        kernel, why = self.driver.kernel_health(bus_name)
        health = bus_health(load=handle.stats.sample(), lost=self.driver.bus_lost.get(bus_name, False),
                            frames=handle.stats.frames, error_frames=handle.stats.error_frames,
                            kernel=kernel, why_unknown=why, tx_queue_full=handle.network.tx_queue_full,
                            tx_not_sent=handle.network.tx_queue_dropped,
                            rejected_frames=handle.network.rejected_frames,
                            frame_loss=total(losses.get(bus_name, ())))
        if self.driver.recorder is not None:  # a babbling node pushed frames out of the flight recorder
            health.values["recorder_frames_dropped"] = str(self.driver.recorder.dropped().get(bus_name, 0))
        return DiagnosticStatus(level=bytes([health.level]), name=f"rovercan: bus {bus_name}", message=health.message,
                                hardware_id=bus_name, values=[KeyValue(key=k, value=v) for k, v in health.values.items()])

    def _driver_status(self) -> DiagnosticStatus:
        """The driver's background jobs, and the callbacks of this process that raised (nodes/process/spinning.py:
        a bug, answered and carried on): counted, the last named, WARN while recent as a job's failure."""
        jobs = self.driver.jobs_health()
        level, message = jobs.level, jobs.message
        failed, last, age_s = self.callback_failures.snapshot()
        if failed:
            recent = age_s < JOB_FAULT_RECENT_S
            level = max(level, WARN if recent else OK)
            message += f"; {failed} callback failure(s), the last: {last}" if recent else \
                f"; {failed} callback failure(s) so far"
        values = {**jobs.values, "callback_failures": str(failed), "last_callback_failure": last}
        return DiagnosticStatus(level=bytes([level]), name="rovercan: driver", message=message, hardware_id="driver",
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def _frame_loss(self, name: str, drive: Drive, state: DriveState) -> Loss | None:
        """The drive's counters into its window (measured only while its data is news and it is
        operational), and the window's figures."""
        cache = drive.cache
        syncs = self.driver.buses[drive.config.bus].stats.syncs
        window = self.frame_loss[name]
        window.add(Counts(time.monotonic(), syncs, cache.sync_tpdos, cache.heartbeats),
                   measuring=state.verdict.fresh and state.nmt == "OPERATIONAL")
        return window.loss()


def _given(values: Sequence[float], i: int) -> float | None:
    """``values[i]`` when the message has it and it is not NaN (NaN: the field is not commanded);
    an infinite value is given, and the driver refuses it by name."""
    if i >= len(values) or math.isnan(values[i]):
        return None
    return float(values[i])


def served(driver: MotorDriver, joints: Sequence[str] | None) -> dict[str, Drive]:
    """The drives a node serves: every drive of ``driver``, or those of ``joints``, by name."""
    if joints is None:
        return dict(driver.drives)
    unknown = [j for j in joints if j not in driver.drives]
    if unknown:
        raise RovercanError(f"joint(s) {unknown} not in the config; joints: {list(driver.drives)}")
    return {j: driver.drives[j] for j in joints}



__all__ = ["DriverNode", "served"]
