"""Limits and polarity over ROS, on a real rclpy graph: a limited joint driven at full speed by
``velocity_cmd`` or ``/joint_commands`` stops before its limit; an inverted joint with an
offset reports in joint space on MotorState and /joint_states."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from can_config import load_config
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import HAVE_ROS, driver_node_spinning, requires_ros, wait_for
from .test_limits import COUNTS_PER_DEG, Extremes
from .test_ros_interface import in_process_host_timeout

pytestmark = requires_ros

if HAVE_ROS:
    from rovercan_msgs.msg import MotorState
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32

    from nodes.process.qos import COMMAND_QOS, STATE_QOS

CONFIG = """buses:
  - {{name: can0, interface: socketcand, channel: can0, kwargs: {{host: 127.0.0.1, port: {port}}}}}
drives:
  - {{name: arm, node_id: 1, joint: limited, min_deg: -90, max_deg: 90, gear_ratio: 50, counts_per_rev: 4096,
     max_velocity_deg_s: 720, profile_acceleration_deg_s2: 720}}
  - {{name: mirrored, node_id: 2, invert: true, offset_deg: 10, gear_ratio: 50, counts_per_rev: 4096}}
"""


class Rig:
    def __init__(self, sim: SimService, driver: MotorDriver, probe: Any) -> None:
        self.sim, self.driver, self.probe = sim, driver, probe


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    path = tmp_path / "rig.yaml"
    path.write_text(CONFIG.format(port=1))
    sim = SimService.from_config(load_config(path), port=0)
    path.write_text(CONFIG.format(port=sim.port))
    driver = MotorDriver(in_process_host_timeout(load_config(path))).start()
    for drive in driver:
        drive.enable()
    with driver_node_spinning(driver, probe_apart=True) as probe:
        yield Rig(sim, driver, probe)
    driver.close()
    sim.close()


def publish_for(publisher: Any, msg: Any, seconds: float, rate_hz: float = 50.0) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        publisher.publish(msg)
        time.sleep(1.0 / rate_hz)


def at_rest(rig: Rig) -> bool:
    """The arm's own velocity (its TPDO) near zero: stopped by the guard or the watchdog."""
    return abs(rig.driver.drive("arm").snapshot().velocity_deg_s) < 1.0


def test_velocity_cmd_at_full_speed_never_passes_the_limit(rig: Rig) -> None:
    watch = Extremes(rig.sim, 1)
    pub = rig.probe.create_publisher(Float32, "arm/velocity_cmd", COMMAND_QOS)
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, "the driver node subscribed to velocity_cmd")
    for speed in (300.0, 720.0, 40.0):  # fast, full (refused: it could not stop), then creeping on
        publish_for(pub, Float32(data=speed), 1.5)
    _, high = watch.after(lambda: at_rest(rig), "the arm at rest (the watchdog's stop)")
    assert 80.0 < high <= 90.0, high
    assert rig.driver.drive("arm").limits.limit_stops > 0


def test_joint_commands_velocity_never_passes_the_limit(rig: Rig) -> None:
    watch = Extremes(rig.sim, 1)
    pub = rig.probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, "the driver node subscribed to /joint_commands")
    for speed in (-5.0, -0.7):  # rad/s: 286 deg/s, then 40 deg/s, toward -90
        publish_for(pub, JointState(name=["arm"], velocity=[speed]), 1.5)
    low, _ = watch.after(lambda: at_rest(rig), "the arm at rest (the watchdog's stop)")
    assert -90.0 <= low < -80.0, low


def stamp_of(msg: Any) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


def test_inverted_joint_with_offset_in_motor_state_and_joint_states(rig: Rig) -> None:
    """Each topic is judged by the message that shows the state judged: the /joint_states of the
    measurement that put MotorState at 30 deg or a newer one (its stamp is the newest of its
    joints' measurements), not the newest one the probe happens to hold: a starved probe held one
    of the joint still on its way (0.5154 rad, issue 73)."""
    states: list[Any] = []
    joints: list[Any] = []
    rig.probe.create_subscription(MotorState, "mirrored/motor_state", states.append, STATE_QOS)
    rig.probe.create_subscription(JointState, "/joint_states", joints.append, STATE_QOS)
    pub = rig.probe.create_publisher(Float32, "mirrored/degree_cmd", COMMAND_QOS)
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, "the driver node subscribed to degree_cmd")
    pub.publish(Float32(data=30.0))
    wait_for(lambda: bool(states) and abs(states[-1].angle - 30.0) < 0.2, 5.0, "MotorState at 30 deg")
    at_30 = stamp_of(states[-1])
    runner = rig.sim.simulators["can0"]
    counts = float(runner.call(lambda: runner.drive(2).position_counts))  # type: ignore[arg-type]
    assert counts == pytest.approx(-20.0 * COUNTS_PER_DEG, abs=0.2 * COUNTS_PER_DEG)  # (30 - 10) deg, mirrored

    def shown() -> list[Any]:
        return [j for j in list(joints) if "mirrored" in j.name and stamp_of(j) >= at_30]

    wait_for(lambda: bool(shown()), 5.0, "the /joint_states of MotorState's 30 deg or newer")
    first = shown()[0]
    assert first.position[list(first.name).index("mirrored")] == pytest.approx(math.radians(30.0), abs=0.005)
