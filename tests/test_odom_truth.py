"""What the rover publishes under faults (issue 52), in a real rclpy graph: the shipped six-wheel
config, the simulator over socketcand, the driver node and the drive system as rover_driver runs
them, a probe subscribing to /odom, /tf, /joint_states and /diagnostics.

The yaw "the wheel positions give" is computed here, independently of the odometry, from the
/joint_states messages: for each pair of consecutive messages, each side's mean position change
over the wheels with a position in both (a lost wheel is NaN) and no jump (a new zero after a
reboot), times the radius, the difference over the track width. Every verdict waits on
conditions (counts of messages, states); no wall-clock bound decides anything."""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Iterator
from typing import Any

import pytest

from can_config import RoverConfig, load_config
from motor_driver import MotorDriver
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import REPO, in_process_stale_after_syncs, wait_for, with_bus_overrides

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import Twist  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from nodes.joints.driver_node import DriverNode  # noqa: E402
from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS, STATE_QOS  # noqa: E402
from nodes.process.spinning import SpinThread, make_executor  # noqa: E402
from nodes.rover.drive_system import DriveSystemNode  # noqa: E402

LEFT = ["wheel_front_left", "wheel_middle_left", "wheel_rear_left"]
RIGHT = ["wheel_front_right", "wheel_middle_right", "wheel_rear_right"]
#: a position change between two /joint_states messages larger than any wheel can turn in the
#: time between their stamps (720 deg/s, 12.6 rad/s; with a margin): a new zero, not motion (a
#: loaded probe may miss messages, so the bound follows the stamps, not the 50 Hz period)
MAX_WHEEL_RAD_S, JUMP_MARGIN_RAD = 15.0, 0.3
YAW_TOLERANCE_RAD = math.radians(2.0)
#: the consumer times both ways in a graph that shares one interpreter with six simulated
#: drives (tests/test_ros_interface.py says why)
HOST_TIMEOUT_S, HEARTBEAT_TIMEOUT_S = 2.0, 2.5


class Rover:
    def __init__(self, on_wheel_loss: str, sync_period_s: dict[str, float] | None = None, *,
                 sim_tick_s: float | None = None, sync_answer_s: dict[str, tuple[float, float]] | None = None) -> None:
        """``sync_period_s``: a bus's SYNC period other than the shipped one (by bus name);
        ``sim_tick_s``: the simulated drives' physics tick other than the simulator's own;
        ``sync_answer_s``: a bus's simulated drives answer SYNC late, from their start, by (delay,
        random 0 to jitter) (their ``sim:`` keys sync_answer_delay_ms and sync_answer_jitter_ms)."""
        config = load_config(REPO / "config" / "rover.yaml")
        assert config.drive_system is not None
        if sync_period_s:
            config = dataclasses.replace(config, buses=tuple(
                dataclasses.replace(b, sync_period_s=sync_period_s.get(b.name, b.sync_period_s)) for b in config.buses))
        late = sync_answer_s or {}
        config = dataclasses.replace(config, drives=tuple(
            dataclasses.replace(d, sim=dataclasses.replace(d.sim, sync_answer_delay_s=late[d.bus][0],
                                                           sync_answer_jitter_s=late[d.bus][1]))
            if d.bus in late else d for d in config.drives))
        drives = tuple(dataclasses.replace(d, host_timeout_s=HOST_TIMEOUT_S, heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S,
                                           stale_after_syncs=in_process_stale_after_syncs(config.bus(d.bus).sync_period_s))
                       for d in config.drives)
        config = dataclasses.replace(config, drives=drives, drive_system=dataclasses.replace(
            config.drive_system, on_wheel_loss=on_wheel_loss))
        self.config: RoverConfig = config
        self.sim = SimService.from_config(config, port=0, **({"tick_s": sim_tick_s} if sim_tick_s else {}))
        self.driver = MotorDriver(with_bus_overrides(config, host=self.sim.host, port=self.sim.port)).start()
        self.context = rclpy.Context()
        # a domain of its own where the suite's worker has none (a run outside xdist beside other
        # graphs on this machine: their /joint_states and /odom would be heard here)
        domain = None if os.environ.get("ROS_DOMAIN_ID") else 150 + os.getpid() % 80
        rclpy.init(context=self.context, domain_id=domain)
        self.driver_node = DriverNode(self.driver, context=self.context,
                                      parameter_overrides=[Parameter("diagnostics_rate_hz", value=5.0)])
        self.system = DriveSystemNode.beside(self.driver_node, self.driver, config, context=self.context)
        self.probe = rclpy.create_node("probe", context=self.context)
        self.odom: list[Any] = []
        self.joints: list[Any] = []
        self.tf: list[Any] = []
        self.diags: list[Any] = []
        self.probe.create_subscription(Odometry, "/odom", self.odom.append, STATE_QOS)
        self.probe.create_subscription(JointState, "/joint_states", self._on_joints, STATE_QOS)
        self.probe.create_subscription(TFMessage, "/tf", self.tf.append, 100)
        self.probe.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, DIAGNOSTICS_QOS)
        self.cmd = self.probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
        self.hot = make_executor("events", self.context)
        for node in (self.driver_node, self.system, self.probe):
            self.hot.add_node(node)
        self.spin = SpinThread(self.hot, "test-hot")
        self.sim_closed = False

    def _on_joints(self, msg: Any) -> None:
        if set(LEFT + RIGHT) <= set(msg.name):
            self.joints.append(msg)

    def close(self) -> None:
        self.spin.stop(5.0)
        for node in (self.driver_node, self.system, self.probe):
            node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.driver.close()
        if not self.sim_closed:
            self.sim.close()

    def arm(self) -> None:
        for name in LEFT + RIGHT:
            drive = self.driver.drive(name)
            wait_for(lambda drive=drive: drive.cache.booted and not drive.cache.lost, 30.0, f"{drive.name} configured")
            drive.enable()

    def drive_until(self, v: float, w: float, done: Any, what: str) -> None:
        """Publish /cmd_vel (v, w) at each new /odom message until ``done()``."""
        twist = Twist()
        twist.linear.x, twist.angular.z = v, w

        def step() -> bool:
            self.cmd.publish(twist)
            seen = len(self.odom)
            wait_for(lambda: len(self.odom) > seen, 10.0, "the next /odom")
            return bool(done())

        wait_for(step, 60.0, what)

    def stand_still(self) -> None:
        wait_for(lambda: all(abs(self.driver.drive(n).snapshot().velocity_deg_s) < 0.5 for n in LEFT + RIGHT
                             if not self.driver.drive(n).cache.lost), 30.0, "every wheel stopped")

    def odom_yaw(self) -> float:
        q = self.odom[-1].pose.pose.orientation
        return 2.0 * math.atan2(q.z, q.w)

    def wheel_yaw(self, since: int = 0, without: tuple[str, ...] = ()) -> float:
        """The heading change the /joint_states positions give, from message ``since`` on: each
        wheel's own travel (from each position it had to its next, across messages where it was
        NaN: stale or lost), a new zero (a jump faster than any wheel turns in the time between)
        left out; the right side's mean travel minus the left's, over the track."""
        cfg = self.config.drive_system
        assert cfg is not None
        travel = dict.fromkeys(LEFT + RIGHT, 0.0)
        last: dict[str, tuple[float, float]] = {}
        for msg in self.joints[since:]:
            t = stamp_s(msg)
            for name, p in zip(msg.name, msg.position, strict=True):
                if name not in travel or not math.isfinite(p):
                    continue
                if name in last and abs(p - last[name][0]) < MAX_WHEEL_RAD_S * abs(t - last[name][1]) + JUMP_MARGIN_RAD:
                    travel[name] += p - last[name][0]
                last[name] = (p, t)
        left = [travel[n] for n in LEFT if n not in without]
        right = [travel[n] for n in RIGHT if n not in without]
        return (sum(right) / len(right) - sum(left) / len(left)) * cfg.wheel_radius_m / cfg.track_width_m

    def sim_speed_rad_s(self, name: str) -> float:
        """The simulated wheel's own motor speed (read from the simulator, not the driver)."""
        cfg = next(d for d in self.config.drives if d.name == name)
        runner = self.sim.simulator_for(cfg.node_id, cfg.bus)
        return float(runner.call(lambda: abs(runner.drive(cfg.node_id).omega)))  # type: ignore[arg-type]

    def sim_stopped(self, names: list[str]) -> bool:
        return all(self.sim_speed_rad_s(n) < 0.01 for n in names)

    def said(self, text: str) -> bool:
        return any(text in st.message for array in self.diags for st in array.status
                   if st.name == "rovercan: drive_system")


def stamp_s(msg: Any) -> float:
    return float(msg.header.stamp.sec) + msg.header.stamp.nanosec * 1e-9


@pytest.fixture
def rover(request: pytest.FixtureRequest) -> Iterator[Rover]:
    rover = Rover(getattr(request, "param", "stop"))
    yield rover
    rover.close()


def yaw_error(rover: Rover, without: tuple[str, ...] = ()) -> float:
    return abs(math.remainder(rover.odom_yaw() - rover.wheel_yaw(without=without), math.tau))


def test_odom_yaw_stays_the_wheels_through_an_unplugged_wheel_and_every_wheel_stops(rover: Rover) -> None:
    rover.arm()
    wait_for(lambda: len(rover.joints) > 2 and len(rover.odom) > 2, 30.0, "the state topics")
    rover.drive_until(0.3, 0.4, lambda: rover.odom_yaw() > 0.15, "a turn of 0.15 rad")
    assert yaw_error(rover) < YAW_TOLERANCE_RAD, (rover.odom_yaw(), rover.wheel_yaw())
    apply_action(rover.sim, {"action": "unplug", "node": 2, "channel": "can0"})  # wheel_middle_left
    # /cmd_vel keeps coming; on_wheel_loss: stop (the default): every wheel stops
    rover.drive_until(0.3, 0.4, lambda: rover.driver.drive("wheel_middle_left").cache.lost, "the wheel lost")
    rover.drive_until(0.3, 0.4, lambda: all(abs(rover.driver.drive(n).snapshot().velocity_deg_s) < 0.5
                                            for n in LEFT + RIGHT if n != "wheel_middle_left"),
                      "every other wheel stopped")
    # the halt's reason as the tick after the verdict says it: the wheel was late (no data) before it was
    # lost, and a tick that judged it late may be the newest when the cache turns lost
    rover.drive_until(0.3, 0.4, lambda: "wheel_middle_left: heartbeat lost" in rover.system.halted,
                      "the halt naming the lost wheel")
    wait_for(lambda: rover.said("stopped: /cmd_vel not applied: wheel_middle_left: heartbeat lost"), 30.0,
             "the real cause on /diagnostics")
    apply_action(rover.sim, {"action": "plug", "node": 2, "channel": "can0"})
    rover.arm()  # back: configured again (a new position reference), re-armed
    # after: the heading from here on, /odom's against the wheels' (while it was unplugged the wheel
    # ran on by itself until its host watch stopped it: nobody could see that, /odom least of all)
    before, joints_from = rover.odom_yaw(), len(rover.joints)
    rover.drive_until(0.3, 0.4, lambda: rover.odom_yaw() > before + 0.15, "another turn of 0.15 rad")
    cmd_stop = Twist()
    rover.cmd.publish(cmd_stop)
    rover.stand_still()
    seen = len(rover.odom)
    wait_for(lambda: len(rover.odom) > seen + 5, 30.0, "odometry after standstill")
    turned, wheels = rover.odom_yaw() - before, rover.wheel_yaw(since=joints_from)
    assert abs(math.remainder(turned - wheels, math.tau)) < YAW_TOLERANCE_RAD, (turned, wheels)


@pytest.mark.parametrize("rover", ["continue"], indirect=True)
def test_with_continue_the_other_wheels_drive_on_and_diagnostics_say_degraded(rover: Rover) -> None:
    rover.arm()
    wait_for(lambda: len(rover.joints) > 2 and len(rover.odom) > 2, 30.0, "the state topics")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.1, "0.1 m straight")
    apply_action(rover.sim, {"action": "unplug", "node": 1, "channel": "can1"})  # wheel_front_right
    rover.drive_until(0.3, 0.0, lambda: "wheel_front_right" in rover.system.wheels_out.out, "the wheel left out")
    x = rover.odom[-1].pose.pose.position.x
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > x + 0.2, "0.2 m more on five wheels")
    others = [n for n in LEFT + RIGHT if n != "wheel_front_right"]
    assert all(rover.driver.drive(n).snapshot().velocity_deg_s > 20.0 for n in others)  # still driving
    assert not rover.system.halted
    wait_for(lambda: rover.said("degraded: wheel_front_right out"), 30.0, "degraded on /diagnostics")
    out = ("wheel_front_right",)
    assert yaw_error(rover, out) < YAW_TOLERANCE_RAD, (rover.odom_yaw(), rover.wheel_yaw(without=out))
    assert abs(rover.odom_yaw()) < YAW_TOLERANCE_RAD  # straight


def test_a_control_loop_that_keeps_failing_is_said_on_diagnostics_and_the_wheels_stop(rover: Rover) -> None:
    """The drive system's tick raises at every period (a bug in its odometry): /diagnostics says so,
    ERROR, naming the failure (its publish sat after the failing step: the drive system's status
    vanished while the driver's said OK), no /odom goes out, and the wheels stop (the driver's
    command watchdog: no velocity follows); once it works again, it says so no more."""
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.05, "0.05 m")
    working = rover.system.odometry.step

    def broken(samples: Any) -> Any:
        raise ZeroDivisionError("a bug in the odometry (the test's)")

    rover.system.odometry.step = broken  # type: ignore[method-assign]
    failing = "the control loop failed (ZeroDivisionError: a bug in the odometry (the test's)"
    wait_for(lambda: rover.said(failing), 30.0, "the failing tick on /diagnostics")
    assert any(st.level == bytes([2]) for array in rover.diags for st in array.status if failing in st.message)
    seen = len(rover.odom)
    rover.stand_still()  # no velocity follows: the driver's watchdog stopped them
    assert len(rover.odom) == seen  # nothing measured was integrated: nothing published
    rover.system.odometry.step = working  # type: ignore[method-assign]
    rover.diags.clear()
    wait_for(lambda: any(st.name == "rovercan: drive_system" for a in rover.diags for st in a.status), 30.0,
             "the drive system's next status")
    wait_for(lambda: len(rover.odom) > seen, 30.0, "/odom again")
    rover.diags.clear()
    wait_for(lambda: any(st.name == "rovercan: drive_system" for a in rover.diags for st in a.status), 30.0,
             "a status after /odom came back")
    assert not rover.said("the control loop failed")


def test_one_drive_s_failing_diagnostics_silence_no_other_status(rover: Rover) -> None:
    """The making of one wheel's status raises at every period (a bug): /diagnostics carries that
    wheel's status as ERROR naming the failure, and every other status as before, the driver's
    counting the failure (the whole array was one try: nothing went out, the status that would
    have said why included)."""
    rejected = rover.driver.rejected

    def broken(drive: Any) -> Any:
        if drive.name == "wheel_front_left":
            raise KeyError("a bug in a drive's diagnostics (the test's)")
        return rejected(drive)

    rover.driver.rejected = broken  # type: ignore[method-assign]
    rover.diags.clear()

    def failed_array() -> Any:
        return next((a for a in list(rover.diags) if any(
            st.name == "rovercan: wheel_front_left" and "its diagnostics failed" in st.message for st in a.status)), None)

    wait_for(lambda: failed_array() is not None, 30.0, "the failing wheel's status")
    statuses = {st.name: st for st in failed_array().status}
    assert statuses["rovercan: wheel_front_left"].level == bytes([2])
    assert "KeyError" in statuses["rovercan: wheel_front_left"].message
    assert {f"rovercan: {n}" for n in LEFT + RIGHT} | {"rovercan: driver", "rovercan: command input"} <= set(statuses)
    assert all(f"rovercan: bus {b.name}" in statuses for b in rover.config.buses)
    driver = {kv.key: kv.value for kv in statuses["rovercan: driver"].values}
    assert int(driver["callback_failures"]) >= 1 and "wheel_front_left" in driver["last_callback_failure"]


def test_a_killed_bus_leaves_odom_standing_with_a_large_covariance(rover: Rover) -> None:
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.1, "0.1 m")
    rover.sim.close()  # both buses' server dies; /cmd_vel keeps coming
    rover.sim_closed = True
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.covariance[0] >= 1e6, "a large covariance")
    held = rover.odom[-1].pose.pose.position.x
    seen = len(rover.odom)
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > seen + 50, "50 more /odom")
    after = rover.odom[seen:]
    assert all(m.pose.pose.position.x == held and m.twist.twist.linear.x == 0.0 for m in after)
    assert all(m.pose.covariance[0] >= 1e6 and m.twist.covariance[0] >= 1e6 for m in after)
    wait_for(lambda: rover.said("odometry stopped: no trusted wheel"), 30.0, "the reason on /diagnostics")


def test_tf_carries_odom_to_base_link_from_the_same_odometry(rover: Rover) -> None:
    rover.arm()
    rover.drive_until(0.3, 0.3, lambda: len(rover.tf) > 10 and rover.odom[-1].pose.pose.position.x > 0.05, "/tf")
    transforms = [t for m in rover.tf for t in m.transforms]
    assert {(t.header.frame_id, t.child_frame_id) for t in transforms} == {("odom", "base_link")}
    by_stamp = {(o.header.stamp.sec, o.header.stamp.nanosec): o for o in rover.odom}
    paired = [(t, by_stamp[(t.header.stamp.sec, t.header.stamp.nanosec)]) for t in transforms
              if (t.header.stamp.sec, t.header.stamp.nanosec) in by_stamp]
    assert paired, "a /tf with the stamp of an /odom"
    for tf, odom in paired:
        assert tf.transform.translation.x == odom.pose.pose.position.x
        assert tf.transform.rotation.z == odom.pose.pose.orientation.z
    # the configured diagonal, plus the square of travel estimated rather than measured (a wheel
    # whose TPDO came late on a crowded machine): e^2 on x and y, (e / track)^2 on yaw
    for odom in rover.odom[-5:]:
        pose_cov = odom.pose.covariance
        estimated_sq = pose_cov[0] - 0.001
        assert 0.0 <= estimated_sq < 0.01, pose_cov  # trusted: never the 1e6 of an unmeasured pose
        assert pose_cov[7] == pytest.approx(0.001 + estimated_sq)
        assert pose_cov[35] == pytest.approx(0.01 + estimated_sq / rover.config.drive_system.track_width_m ** 2)
        assert min(pose_cov[i * 7] for i in range(6)) > 0


def test_a_step_back_of_the_wall_clock_silences_neither_odom_nor_tf(rover: Rover,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The system clock stepped back an hour (chrony at boot, an RTC ahead): /odom and /tf go on at
    once, stamped on the stepped clock (each still a later measurement than the one before on the
    monotonic clock). Compared on the wall clock, every stamp fell below the last one sent and
    nothing was published for the hour."""
    from nodes.rover import drive_system

    rover.arm()
    rover.drive_until(0.3, 0.0, lambda: len(rover.tf) > 5 and rover.odom[-1].pose.pose.position.x > 0.02, "/odom")
    before = stamp_s(rover.odom[-1])
    seen, tf_seen = len(rover.odom), len(rover.tf)
    monkeypatch.setattr(drive_system, "wall_clock", lambda: time.time() - 3600.0)
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > seen + 20 and len(rover.tf) > tf_seen + 20,
                      "20 /odom and /tf after the step")
    stepped = [stamp_s(m) for m in rover.odom[seen:] if stamp_s(m) < before - 3000.0]
    assert len(stepped) >= 20 and stepped == sorted(stepped)
    assert all(m.pose.covariance[0] < 1e6 for m in rover.odom[-5:])  # measured, not the untrusted hold
    assert stamp_s(rover.tf[-1].transforms[0]) < before - 3000.0
