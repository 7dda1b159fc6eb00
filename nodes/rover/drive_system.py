"""The rover's /cmd_vel drive system: skid-steer wheels from a Twist, odometry from the wheels'
measured positions (/odom and /tf odom -> base_link), stops on a command timeout, and what to
do when a wheel is lost (``drive_system.on_wheel_loss``); a node beside the driver node, in the
same process.

It reads each wheel's verdict (:mod:`motor_driver.drive.verdict`; a wheel it left out is judged with
that fact) and nothing else: it drives only usable wheels; with ``on_wheel_loss: stop`` any
wheel not usable stops every wheel, with ``continue`` a wheel not usable (late too) is left out
and told to stop, and a side with no wheel left stops every wheel, naming the side.

What it publishes is what was measured: /odom integrates each usable wheel's own position
deltas (:mod:`motor_driver.rover.odometry`), never a command or a velocity times a tick; a side with no
trusted wheel stops the integration (pose kept, twist zero, every variance 1e6) and
/diagnostics says why; the pose variances grow with the travel estimated rather than measured.
/odom and /tf are stamped when the wheels measured the pose (the odometry's common instant of both
sides' samples, each bus's own receive times paired: :mod:`motor_driver.rover.odometry`), and sent
with a measured covariance only for a step both sides measured: while a side's data is late (within
its staleness bound) nothing is sent, and once that side is not trusted (its bus dead, its wheels
late, lost or stopped) /odom carries the last trusted pose with every variance 1e6, stamped now,
and /tf nothing: no transform is stamped later than the last trusted step, however long it lasts.
Every refusal names the real cause and what helps (:mod:`nodes.rover.wheels`).

Owner: the executor thread that runs its tick (the driver node's state timer, or its own),
which alone touches the ramp, the odometry and the wheels-out book; a wheel left out is told to
stop on a worker of its own (a stop waits for the drive; the tick never does); the tick reads
each stop's result: a stop that failed (whatever it raised) is logged with its cause, counted,
said in /diagnostics (ERROR until a stop of that wheel succeeds) and tried again after
STOP_RETRY_S. A wheel's
velocity that must wait for the drive (its first, a switch to profile velocity) goes through the
driver node's handoff (nodes/joints/handoff.py), whose worker hands a refusal back to the next tick.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TransformStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile
from tf2_msgs.msg import TFMessage

from can_config import RoverConfig
from can_config.errors import RovercanError
from motor_driver import Drive, MotorDriver
from motor_driver.diagnostics.health import ERROR, OK, WARN
from motor_driver.drive import DriveState
from motor_driver.drive.verdict import UNREACHABLE, Condition
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.protocol.units import DEG_PER_RAD
from motor_driver.rover.odometry import UNKNOWN_VARIANCE, OdometryStep, WheelOdometry
from motor_driver.rover.skid_steer import SkidSteer, Twist2D
from nodes.joints.handoff import Handoff
from nodes.joints.messages import stamp_header
from nodes.joints.refusals import RefusalLog
from nodes.process.params import declare, qos_depth
from nodes.process.qos import DIAGNOSTICS_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS, SETPOINT_QOS, state_qos
from nodes.rover.wheels import WheelsOut, odometry_samples, out_verdict, problems

if TYPE_CHECKING:
    from nodes.joints.driver_node import DriverNode

logger = logging.getLogger(__name__)
#: the drive system's own /diagnostics status, besides every change of it
DIAGNOSTICS_PERIOD_S = 1.0
#: A wheel's stop that failed is tried again after this long.
STOP_RETRY_S = 0.5
#: The clock of /odom's, /tf's and /diagnostics' stamps: the system's wall clock (a test steps it).
wall_clock: Callable[[], float] = time.time
#: tf2's own publishers keep 100 (a late listener's buffer fills from them)
TF_QOS = QoSProfile(depth=100)



class DriveSystemNode(Node):
    """/cmd_vel -> skid-steer wheel velocities (ramped, a timed-out /cmd_vel stops), /odom and /tf
    from the wheels' measured positions.

    The node commands the wheels only while /cmd_vel is fresh and while it ramps them down after
    /cmd_vel timed out (cmd_timed_out); once stopped it leaves them alone (bench tools and per-joint topics
    may then use them).
    """

    def __init__(self, driver: MotorDriver, config: RoverConfig, refusals: RefusalLog | None = None,
                 handoff: Handoff | None = None, **kwargs: Any) -> None:
        super().__init__("drive_system", **kwargs)
        declare(self, "odom_rate_hz", "odom_frame", "base_frame", "state_qos_depth", "publish_tf")
        system = config.drive_system
        if system is None:
            raise RovercanError("the config has no drive_system section")
        self.system = system
        self.left = [driver.drive(n) for n in system.left]
        self.right = [driver.drive(n) for n in system.right]
        self.wheels = self.left + self.right
        self._pdo_period_s = {d.name: d.cache.sync_period_s for d in self.wheels}  # a TPDO every SYNC
        slowest_deg_s = min(d.config.max_velocity_deg_s for d in self.wheels)
        self.steer = SkidSteer(system.track_width_m, system.wheel_radius_m, system.max_accel_m_s2,
                               system.max_speed_m_s, max_angular_rad_s=system.max_angular_rad_s,
                               max_wheel_rad_s=math.radians(slowest_deg_s))
        self.odometry = WheelOdometry(system.left, system.right, system.track_width_m, system.wheel_radius_m)
        self.wheels_out = WheelsOut(system.left, system.right) if system.on_wheel_loss == "continue" else None
        self.refusals = refusals or RefusalLog(self.get_logger().warning)
        # the driver node's (one book of which joint's command is with a worker), else its own
        self._own_handoff = handoff is None
        self.handoff = handoff or Handoff([d.name for d in self.wheels])
        self._refused_late: queue.SimpleQueue[tuple[str, float, Exception]] = queue.SimpleQueue()
        self._target = Twist2D()
        self._last_cmd = -math.inf
        self._last_tick = time.monotonic()
        self.cmd_timed_out = True
        self.active = False  # commanding the wheels (fresh /cmd_vel or ramping down after it)
        self.halted = ""  # why every wheel was stopped, until a fresh /cmd_vel drives again
        self.last_odometry = OdometryStep(self.odometry.pose, Twist2D(), False, "odometry: no wheel sampled yet")
        self._measured_sent = 0.0  # when the newest /odom sent was measured (monotonic clock, s)
        # a worker a wheel (made when first needed): a stop that waits for its drive holds no other's
        self._stopper = ThreadPoolExecutor(len(self.wheels), thread_name_prefix="drive_system-stop")
        self._stops: dict[str, Future[None]] = {}
        self._stop_retry_at: dict[str, float] = {}  # a failed stop's next try (the tick's)
        self.stop_failing: dict[str, str] = {}  # a wheel whose last stop failed, and why (the tick's)
        self.stop_failures = 0  # stops that failed so far (the tick's)
        self.tick_failures = 0  # ticks that raised so far (the tick's; /diagnostics says them)
        self.tick_failing = ""  # why the last tick failed, "" it did not (the tick's)
        self._tick_errors: set[type[BaseException]] = set()  # kinds of tick failure whose trace was logged
        self.held = ""  # why motion is held, from the wheels' verdicts (the lifecycle node inactive), "" not
        self._stop_log = RateLimitedLog(logger)
        self._odom_frame = str(self.get_parameter("odom_frame").value)
        self._base_frame = str(self.get_parameter("base_frame").value)
        self.create_subscription(Twist, "/cmd_vel", self._on_cmd_vel, SETPOINT_QOS, event_callbacks=NO_SUB_EVENTS)
        self._odom_pub = self.create_publisher(Odometry, "/odom", state_qos(qos_depth(self)), event_callbacks=NO_PUB_EVENTS)
        self._tf_pub = self.create_publisher(TFMessage, "/tf", TF_QOS, event_callbacks=NO_PUB_EVENTS) \
            if self.get_parameter("publish_tf").value else None
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS,
                                               event_callbacks=NO_PUB_EVENTS)
        self._period_s = 1.0 / float(self.get_parameter("odom_rate_hz").value)
        self._timer = self.create_timer(self._period_s, self._tick)
        # /diagnostics from the tick every DIAGNOSTICS_PERIOD_S (no wake-up of its own), and at once on a change
        self._diag_every = max(1, round(float(self.get_parameter("odom_rate_hz").value) * DIAGNOSTICS_PERIOD_S))
        self._ticks = 0

    @classmethod
    def beside(cls, driver_node: DriverNode, driver: MotorDriver, config: RoverConfig, **kwargs: Any) -> DriveSystemNode:
        """The drive system of a process with ``driver_node`` on the same executor (rover_driver,
        rover_lifecycle): its control loop on that node's state timer where the rates match."""
        node = cls(driver, config, driver_node.refusals, driver_node.handoff, **kwargs)
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

    def destroy_node(self) -> None:
        self._stopper.shutdown(wait=False, cancel_futures=True)
        if self._own_handoff:
            self.handoff.close()
        super().destroy_node()

    def _on_cmd_vel(self, msg: Twist) -> None:
        v, w = msg.linear.x, msg.angular.z
        if not (math.isfinite(v) and math.isfinite(w)):
            self.refusals.refuse("drive_system", f"/cmd_vel with non-finite values (linear.x={v}, angular.z={w})")
            return
        self._target = Twist2D(v, w)
        self._last_cmd = time.monotonic()

    # ------------------------------------------------------------------ the control loop
    def _tick(self) -> None:
        try:
            now = time.monotonic()
            dt = min(now - self._last_tick, 0.5)
            self._last_tick = now
            states = {d.name: d.snapshot() for d in self.wheels}
            self.held = next((s.verdict.helps for s in states.values() if s.verdict.condition is Condition.HELD), "")
            if self.wheels_out is not None:
                self._book_wheels_out(states, now)
                states = {n: self._judged(s) for n, s in states.items()}
            self._integrate(states)
            self._control(states, now, dt)
            self.tick_failing = ""
        except Exception as err:
            self._tick_failed(err)
        self._ticks += 1  # /diagnostics whatever the tick did: a tick that keeps failing is said there
        if self._ticks % self._diag_every == 0:
            try:
                self.publish_diagnostics()
            except Exception as err:
                self._tick_failed(err)

    def _tick_failed(self, err: Exception) -> None:
        self.tick_failures += 1
        self.tick_failing = f"{type(err).__name__}: {err}"
        if type(err) not in self._tick_errors:  # its trace once; then at most a line a period
            self._tick_errors.add(type(err))
            logger.exception("drive system tick failed (%d so far); the next tick tries again", self.tick_failures,
                             exc_info=err)
        else:
            self._stop_log.log(logging.ERROR, ("tick", type(err)), "drive system tick failed (%d so far): %r",
                               self.tick_failures, err)

    def _control(self, states: dict[str, DriveState], now: float, dt: float) -> None:
        late = self._refused_on_workers()
        if late:  # a wheel's velocity refused on the handoff's worker: as if here
            self._halt("/cmd_vel not applied: " + "; ".join(f"wheel {name} refused {speed:.2f} rad/s ({err})"
                                                            for name, speed, err in late) + "; every wheel stopped")
            return
        self.cmd_timed_out = now - self._last_cmd > self.system.cmd_timeout_s
        if not self.cmd_timed_out:
            if self.held:  # the drives' own verdict (the lifecycle node inactive): said as it is, not as "not armed"
                self._halt(f"/cmd_vel not applied: {self.held}; nothing was sent", diagnose=False)
                return
            side = self.wheels_out.empty_side() if self.wheels_out is not None else ""
            if side:
                names = self.left if side == "left" else self.right
                self._halt(f"/cmd_vel not applied: the {side} side has no usable wheel ({problems(states[d.name] for d in names)});"
                           " every wheel stopped")
                return
            blocked = [s for s in states.values() if not s.verdict.usable] if self.wheels_out is None else []
            if blocked:  # on_wheel_loss: stop (all or none: a turn driven by some wheels is worse than none)
                self._halt(f"/cmd_vel not applied: {problems(blocked)}; no wheel is driven")
                return
            self.active = True
            self.halted = ""
        left, right = self.steer.step(Twist2D() if self.cmd_timed_out else self._target, dt)
        if self.cmd_timed_out and not self.active:
            return
        if self.cmd_timed_out and left == 0.0 and right == 0.0:
            self.active = False  # stopped: send this last zero, then leave the wheels to others
        for drives, speed in ((self.left, left), (self.right, right)):
            for drive in drives:
                if not states[drive.name].verdict.usable:
                    continue  # not ours to drive (ramping down: the others still stop); a wheel out is left alone
                try:
                    self.handoff.send(drive.name, drive.set_velocity, speed * DEG_PER_RAD, "velocity", self._wheel_refused)
                except RovercanError as err:
                    self._halt(f"/cmd_vel not applied: wheel {drive.name} refused {speed:.2f} rad/s ({err});"
                               " every wheel stopped")
                    return

    def _book_wheels_out(self, states: dict[str, DriveState], now: float) -> None:
        """on_wheel_loss: continue: a wheel that is not usable while the rover drives (late too) is
        told to stop and left out; the body's limits shrink to the wheels left."""
        assert self.wheels_out is not None
        driving = self.active or now - self._last_cmd <= self.system.cmd_timeout_s
        went, back = self.wheels_out.update(states, driving=driving)
        self._read_stops(now)
        for name in back:  # taken back (armed again): a stop of its time out is neither tried again nor sent late
            self.stop_failing.pop(name, None)
            self._stop_retry_at.pop(name, None)
            if (pending := self._stops.get(name)) is not None:
                pending.cancel()  # one not yet started; the tick still reads it (_read_stops)
        retried = [name for name in self.stop_failing if name in self.wheels_out.out]
        enabling = [d.name for d in self.wheels if d.channel.enabling]  # /arm taking it back
        for name in [*retried, *went, *self.wheels_out.still_running(states, enabling)]:
            if now >= self._stop_retry_at.get(name, 0.0):
                self._tell_to_stop(name)
        for name in went:
            self.get_logger().warning(f"degraded: {name} out ({self.wheels_out.out[name].reason}); driving on the others")
        for name in back:
            self.get_logger().info(f"{name} is back in the drive system (enabled again)")
        self.steer.limit_to(self.wheels_out.share())
        if went or back:
            self.publish_diagnostics()

    def _judged(self, state: DriveState) -> DriveState:
        """A wheel's snapshot with the verdict that counts here: "out" while the book has it out."""
        out = self.wheels_out.out.get(state.name) if self.wheels_out is not None else None
        if out is None:
            return state
        verdict = out_verdict(state, out.reason)
        return dataclasses.replace(state, judged=(state.facts._replace(left_out=out.reason), verdict))

    def _wheel_refused(self, name: str, what: str, value: float, err: Exception) -> None:
        """The handoff's worker: a wheel's velocity refused there; the next tick halts them all."""
        self._refused_late.put((name, value / DEG_PER_RAD, err))

    def _refused_on_workers(self) -> list[tuple[str, float, Exception]]:
        """Every wheel refused on a worker since the last tick, but a wheel left out (continue)."""
        late = []
        while not self._refused_late.empty():
            name, speed, err = self._refused_late.get()
            if self.wheels_out is None or name not in self.wheels_out.out:
                late.append((name, speed, err))
        return late

    def _tell_to_stop(self, name: str) -> None:
        pending = self._stops.get(name)
        if pending is not None and not pending.done():
            return
        drive = next(d for d in self.wheels if d.name == name)
        self._stops[name] = self._stopper.submit(self._quick_stop, drive)

    @staticmethod
    def _quick_stop(drive: Drive) -> None:
        drive.quick_stop()  # what it raises is read by the tick (_failed_stops)

    def _read_stops(self, now: float) -> None:
        """The tick: each finished stop read; a wheel whose stop failed, whatever the failure was,
        is in ``stop_failing`` (tried again once STOP_RETRY_S passed) until a stop of it succeeds."""
        for name, stop in list(self._stops.items()):
            if not stop.done():
                continue
            del self._stops[name]
            err = None if stop.cancelled() else stop.exception()
            if err is None:
                self.stop_failing.pop(name, None)
                continue
            self.stop_failures += 1
            self.stop_failing[name] = f"{type(err).__name__}: {err}"
            self._stop_retry_at[name] = now + STOP_RETRY_S
            if isinstance(err, RovercanError):  # it cannot hear us: its own host watch stops it
                self._stop_log.log(logging.WARNING, (name, "refused"), "drive system: %s left out, its quick stop"
                                   " failed (%s); it stops by itself when it hears no heartbeat from this host;"
                                   " tried again", name, err)
            else:
                self._stop_log.log(logging.ERROR, (name, type(err)), "drive system: %s left out, its quick stop"
                                   " failed unexpectedly (%s); tried again", name, self.stop_failing[name])

    def _halt(self, reason: str, diagnose: bool = True) -> None:
        """Stop every wheel that still runs and forget the ramp, so that nothing (a stale
        ramp-down, a recovered wheel) brings them back without a fresh /cmd_vel. The command
        that was refused is spent: only one received after this drives again (it was driving all
        six for a moment when the wheel came back within its timeout). ``diagnose``: /diagnostics
        says the stop until a command drives again (False: motion held, said as "inactive")."""
        self.steer.halt()
        self._last_cmd = -math.inf
        self.cmd_timed_out = True
        if self.active:
            for drive in self.wheels:  # a wheel whose data is only late hears us: a zero is taken on late data
                if drive.verdict().condition not in UNREACHABLE:
                    try:
                        self.handoff.send(drive.name, drive.set_velocity, 0.0, "stop", _cannot_move)
                    except RovercanError:
                        pass  # that wheel cannot move anyway
        self.active = False
        if diagnose and self.halted != reason:
            self.halted = reason
            self.publish_diagnostics()
        self.refusals.refuse("drive_system", reason)

    # ------------------------------------------------------------------ what was measured
    def _integrate(self, states: dict[str, DriveState]) -> None:
        sides = (self.system.left, self.system.right)
        step = self.odometry.step(odometry_samples(states, sides, self._pdo_period_s))
        was = self.last_odometry.trusted
        self.last_odometry = step
        if was != step.trusted:
            self.publish_diagnostics()
        if not step.trusted:  # the last trusted pose, said to be unknown now (stamped now: it is no measurement)
            measured = time.monotonic()
        elif step.measured_at:  # a step measured on both sides: stamped when they measured it
            measured = step.measured_at
        else:  # trusted, but nothing measured on both sides since the last step (a side's PDO late,
            return  # within its staleness bound): nothing is said as measured, nor repeated
        # each /odom and /tf later than the one before on the monotonic clock; the stamp is that
        # instant on the wall clock now (a step of the system clock shows in the stamps, as in
        # every node's, and silences nothing: compared on the wall clock, a step back of an hour
        # held /odom for an hour)
        if measured > self._measured_sent:
            self._measured_sent = measured
            self._publish_odom(step, measured + wall_clock() - time.monotonic())

    def _publish_odom(self, step: OdometryStep, stamp: float) -> None:
        pose, twist = step.pose, step.twist
        qz, qw = math.sin(pose.yaw_rad / 2.0), math.cos(pose.yaw_rad / 2.0)
        if self._odom_pub.get_subscription_count():
            odom = Odometry()
            stamp_header(odom.header, stamp)
            odom.header.frame_id = self._odom_frame
            odom.child_frame_id = self._base_frame
            odom.pose.pose.position.x = pose.x_m
            odom.pose.pose.position.y = pose.y_m
            odom.pose.pose.orientation.z = qz
            odom.pose.pose.orientation.w = qw
            odom.twist.twist.linear.x = twist.linear_m_s
            odom.twist.twist.angular.z = twist.angular_rad_s
            odom.pose.covariance = covariance(self.system.pose_covariance_diagonal, step.trusted,
                                              estimated=pose_estimate_variance(step, self.system.track_width_m))
            odom.twist.covariance = covariance(self.system.twist_covariance_diagonal, step.trusted)
            self._odom_pub.publish(odom)
        if self._tf_pub is not None and step.trusted and self._tf_pub.get_subscription_count():
            # only a measured pose: while untrusted no transform claims where base_link is now
            tf = TransformStamped()
            stamp_header(tf.header, stamp)
            tf.header.frame_id = self._odom_frame
            tf.child_frame_id = self._base_frame
            tf.transform.translation.x = pose.x_m
            tf.transform.translation.y = pose.y_m
            tf.transform.rotation.z = qz
            tf.transform.rotation.w = qw
            self._tf_pub.publish(TFMessage(transforms=[tf]))

    def health(self) -> tuple[int, str, dict[str, str]]:
        """The drive system's level, message and values for /diagnostics."""
        odom = self.last_odometry
        values = {"on_wheel_loss": self.system.on_wheel_loss, "odometry": "integrating" if odom.trusted else
                  odom.why_not, "wheels_out": self.wheels_out.summary() if self.wheels_out else "", "driving": str(self.active),
                  "stop_failures": str(self.stop_failures), "tick_failures": str(self.tick_failures)}
        if self.tick_failing:  # no wheel driven, no /odom: the driver's command watchdog stops the wheels
            return ERROR, (f"the control loop failed ({self.tick_failing}; {self.tick_failures} so far): no wheel"
                           " is driven and /odom is not published; a bug, please report it with the logged trace"), values
        if self.stop_failing:
            return ERROR, "a wheel's stop failed, tried again: " + "; ".join(
                f"{name} ({why})" for name, why in self.stop_failing.items()), values
        if self.held:  # a state, not a failure (the lifecycle node inactive); the holder's reason says which
            values["held"] = self.held  # each drive's own status says one still enabled under the hold
            return OK, f"motion held: {self.held}", values
        if self.halted:
            return ERROR, f"stopped: {self.halted}" + ("" if odom.trusted else f"; {odom.why_not}"), values
        if self.wheels_out is not None and self.wheels_out.out:
            return WARN, f"degraded: {self.wheels_out.summary()}", values
        if not odom.trusted:
            return ERROR if self.active else WARN, odom.why_not, values
        return OK, "driving" if self.active else "idle", values

    def publish_diagnostics(self) -> None:
        level, message, values = self.health()
        array = DiagnosticArray()
        stamp_header(array.header, wall_clock())
        status = DiagnosticStatus(level=bytes([level]), name="rovercan: drive_system", message=message,
                                  hardware_id="drive_system")
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        array.status = [status]
        self._diag_pub.publish(array)


def _cannot_move(name: str, what: str, value: float, err: Exception) -> None:
    """A halted wheel's zero refused on the handoff's worker: logged (such a wheel is faulted, lost
    or not enabled, or else the driver's command watchdog stops it when no velocity follows)."""
    logger.warning("drive system: the stop of %s was refused on its worker (%s)", name,
                   err if isinstance(err, RovercanError) else repr(err))


def covariance(diagonal: tuple[float, ...], trusted: bool, estimated: tuple[float, ...] = ()) -> list[float]:
    """A 6x6 row-major covariance with ``diagonal`` plus ``estimated`` (every entry
    UNKNOWN_VARIANCE when not trusted)."""
    out = [0.0] * 36
    for i, value in enumerate(diagonal):
        extra = estimated[i] if i < len(estimated) else 0.0
        out[i * 7] = min(value + extra, UNKNOWN_VARIANCE) if trusted else UNKNOWN_VARIANCE
    return out


def pose_estimate_variance(step: OdometryStep, track_width_m: float) -> tuple[float, ...]:
    """The variances (x, y, z, roll, pitch, yaw) the travel estimated rather than measured adds:
    its square on x and y, and the heading it could have turned, squared, on yaw."""
    e = step.estimated_m
    return e * e, e * e, 0.0, 0.0, 0.0, (e / track_width_m) ** 2
