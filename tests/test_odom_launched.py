"""Issue 52's check on the path a user deploys: the shipped six-wheel config served by `rovercan
sim --config` in a process of its own, the rover launched with `rovercan launch rover_launch.xml`,
armed with /arm and driven at 0.3 m/s on /cmd_vel by a probe node beside it.

- The simulator is SIGKILLed while /cmd_vel keeps coming: over the next 150 /odom messages (3 s at
  50 Hz) the pose advances less than 0.05 m, and /odom says it trusts nothing (variance 1e6).
- The simulator is started again, the rover re-armed and driven straight for 150 /odom messages:
  /odom's yaw turns less than 3 deg, and its distance is within 25 % of what the wheel positions on
  /joint_states say (each wheel's own travel, a new zero after the reboot left out).

Only the ports and the consumer times differ from config/rover.yaml: a free port (no fixed port in
a test), and host and heartbeat timeouts of 2 s and 2.5 s (tests/test_two_buses.py says why: a
starved test runner is not the subject here). Counts of messages, not clocks, decide."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from .conftest import REPO, requires_ros, wait_for
from .test_sim_cli import free_port

pytestmark = [requires_ros, pytest.mark.slow, pytest.mark.timeout(900)]
ROVER_LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml"
WHEELS = ["wheel_front_left", "wheel_middle_left", "wheel_rear_left",
          "wheel_front_right", "wheel_middle_right", "wheel_rear_right"]
HANG_S = 120.0  # a hang only: three Python processes on two busy cores
ODOM_3_S = 150  # /odom messages in 3 s (odom_rate_hz 50)


def shipped_rover(tmp_path: Path, port: int) -> Path:
    data = yaml.safe_load((REPO / "config" / "rover.yaml").read_text())
    for bus in data["buses"]:
        bus["kwargs"]["port"] = port
    for drive in data["drives"]:
        drive.update(host_timeout_ms=2000, heartbeat_timeout_ms=2500)
    path = tmp_path / "rover.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def start_simulator(config: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--config", str(config)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None and "simulated drive" in proc.stdout.readline()
    return proc


def stop(proc: subprocess.Popen[str], sig: int = signal.SIGTERM) -> str:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out or ""


class Probe:
    def __init__(self, name: str) -> None:
        import rclpy
        from geometry_msgs.msg import Twist
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger

        from nodes.process.qos import STATE_QOS
        from nodes.process.spinning import SpinThread

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.odom: list[Any] = []
        self.joints: list[Any] = []
        self.node.create_subscription(Odometry, "/odom", self.odom.append, STATE_QOS)
        self.node.create_subscription(JointState, "/joint_states", self._on_joints, STATE_QOS)
        self.arm_client = self.node.create_client(Trigger, "/arm")
        self.cmd = self.node.create_publisher(Twist, "/cmd_vel", 10)
        self.forward = Twist()
        self.forward.linear.x = 0.3
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(self.node)
        self.spin = SpinThread(executor, f"{name}-probe")

    def _on_joints(self, msg: Any) -> None:
        if set(WHEELS) <= set(msg.name):
            self.joints.append(msg)

    def close(self) -> None:
        import rclpy

        self.spin.stop(5.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def arm(self) -> None:
        from std_srvs.srv import Trigger

        assert self.arm_client.wait_for_service(timeout_sec=HANG_S), "no /arm service"

        def armed() -> bool:
            call = self.arm_client.call_async(Trigger.Request())
            wait_for(call.done, HANG_S, "/arm answered")
            return bool(call.result().success)

        wait_for(armed, HANG_S, "/arm succeeded")

    def drive(self, odom_messages: int) -> None:
        """/cmd_vel forward at each new /odom, for ``odom_messages`` of them."""
        start = len(self.odom)
        self.drive_until(lambda: len(self.odom) - start >= odom_messages, f"{odom_messages} /odom messages")

    def drive_until(self, done: Any, what: str) -> None:
        """/cmd_vel forward at each new /odom until ``done()``."""
        def one() -> bool:
            self.cmd.publish(self.forward)
            seen = len(self.odom)
            wait_for(lambda: len(self.odom) > seen, HANG_S, "the next /odom")
            return bool(done())

        wait_for(one, HANG_S * 4, f"{what} while driving")

    def fresh_joints(self) -> bool:
        return bool(self.joints) and all(math.isfinite(p) for p in self.joints[-1].position)


def pose(msg: Any) -> tuple[float, float, float]:
    q = msg.pose.pose.orientation
    return msg.pose.pose.position.x, msg.pose.pose.position.y, 2.0 * math.atan2(q.z, q.w)


def wheel_travels(joints: list[Any]) -> dict[str, float]:
    """Each wheel's own travel (rad) over ``joints``: the change from each position it had to its
    next one (across messages where it was NaN: stale or lost), a new zero (a jump faster than any
    wheel turns in the time between) left out."""
    travel = dict.fromkeys(WHEELS, 0.0)
    last: dict[str, tuple[float, float]] = {}
    for msg in joints:
        t = stamp_s(msg)
        for w, p in zip(msg.name, msg.position, strict=True):
            if w not in travel or not math.isfinite(p):
                continue
            if w in last and abs(p - last[w][0]) < 15.0 * abs(t - last[w][1]) + 0.3:
                travel[w] += p - last[w][0]
            last[w] = (p, t)
    return travel


def stamp_s(msg: Any) -> float:
    return float(msg.header.stamp.sec) + msg.header.stamp.nanosec * 1e-9


def wheel_travel_m(joints: list[Any], radius_m: float) -> float:
    """The mean wheel's rim travel over ``joints`` (m)."""
    travel = wheel_travels(joints)
    return sum(travel.values()) / len(travel) * radius_m


def test_odom_stands_still_with_the_bus_killed_and_holds_its_heading_after(tmp_path: Path) -> None:
    port = free_port()
    config = shipped_rover(tmp_path, port)
    radius_m = yaml.safe_load(config.read_text())["drive_system"]["wheel_radius_m"]
    sims = [start_simulator(config)]  # served before the rover starts (its boot needs the drives)
    launch = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(ROVER_LAUNCH), f"config:={config}",
                               "--duration", "600"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    probe = Probe("odom_launched")
    try:
        probe.arm()
        wait_for(lambda: len(probe.odom) > 2 and probe.fresh_joints(), HANG_S, "/odom and /joint_states")
        probe.drive_until(lambda: pose(probe.odom[-1])[0] > 0.1, "0.1 m on /odom")
        x_killed = pose(probe.odom[-1])[0]
        stop(sims[0], signal.SIGKILL)
        killed_at = len(probe.odom)
        probe.drive(ODOM_3_S)
        after_kill = probe.odom[killed_at:killed_at + ODOM_3_S]
        advance = max(math.hypot(pose(m)[0] - x_killed, pose(m)[1]) for m in after_kill)
        assert advance < 0.05, f"/odom moved {advance:.3f} m with the bus dead"
        assert after_kill[-1].pose.covariance[0] >= 1e6 and after_kill[-1].twist.twist.linear.x == 0.0
        sims.append(start_simulator(config))
        wait_for(probe.fresh_joints, HANG_S, "the wheels heard again")
        probe.arm()
        probe.drive_until(lambda: abs(probe.odom[-1].twist.twist.linear.x) > 0.25, "up to speed")
        first, joints_from = len(probe.odom) - 1, len(probe.joints)
        probe.drive(ODOM_3_S)
        start, end = pose(probe.odom[first]), pose(probe.odom[-1])
        turned = abs(math.remainder(end[2] - start[2], math.tau))
        assert turned < math.radians(3.0), (f"/odom turned {math.degrees(turned):.2f} deg driving straight; the"
                                            f" wheels: {wheel_travels(probe.joints[joints_from:])}")
        odom_m = math.hypot(end[0] - start[0], end[1] - start[1])
        wheels_m = wheel_travel_m(probe.joints[joints_from:], radius_m)
        assert wheels_m > 0.3, f"the wheels drove {wheels_m:.3f} m"
        assert abs(odom_m - wheels_m) <= 0.25 * wheels_m, (odom_m, wheels_m)
        probe.cmd.publish(type(probe.forward)())
    finally:
        probe.close()
        out = stop(launch)
        for sim in sims:
            stop(sim)
        (tmp_path / "launch.log").write_text(out)
    assert "Traceback" not in out, out[-3000:]
    # the rover launch says what the team's demo topic drives: nothing, unless default_joint names it
    assert "the demo topic /motor_degree_cmd moves no joint (default_joint is empty)" in out, out[-3000:]
