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

    from nodes.qos import COMMAND_QOS, STATE_QOS

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


def test_velocity_cmd_at_full_speed_never_passes_the_limit(rig: Rig) -> None:
    watch = Extremes(rig.sim, 1)
    pub = rig.probe.create_publisher(Float32, "arm/velocity_cmd", COMMAND_QOS)
    time.sleep(0.3)
    for speed in (300.0, 720.0, 40.0):  # fast, full (refused: it could not stop), then creeping on
        publish_for(pub, Float32(data=speed), 1.5)
    time.sleep(0.3)
    _, high = watch.stop()
    assert 80.0 < high <= 90.0, high
    assert rig.driver.drive("arm").limits.limit_stops > 0


def test_joint_commands_velocity_never_passes_the_limit(rig: Rig) -> None:
    watch = Extremes(rig.sim, 1)
    pub = rig.probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)
    time.sleep(0.3)
    for speed in (-5.0, -0.7):  # rad/s: 286 deg/s, then 40 deg/s, toward -90
        publish_for(pub, JointState(name=["arm"], velocity=[speed]), 1.5)
    time.sleep(0.3)
    low, _ = watch.stop()
    assert -90.0 <= low < -80.0, low


def test_inverted_joint_with_offset_in_motor_state_and_joint_states(rig: Rig) -> None:
    states: list[Any] = []
    joints: list[Any] = []
    rig.probe.create_subscription(MotorState, "mirrored/motor_state", states.append, STATE_QOS)
    rig.probe.create_subscription(JointState, "/joint_states", joints.append, STATE_QOS)
    pub = rig.probe.create_publisher(Float32, "mirrored/degree_cmd", COMMAND_QOS)
    time.sleep(0.3)
    pub.publish(Float32(data=30.0))
    wait_for(lambda: bool(states) and abs(states[-1].angle - 30.0) < 0.2, 5.0, "MotorState at 30 deg")
    runner = rig.sim.simulators["can0"]
    counts = float(runner.call(lambda: runner.drive(2).position_counts))  # type: ignore[arg-type]
    assert counts == pytest.approx(-20.0 * COUNTS_PER_DEG, abs=0.2 * COUNTS_PER_DEG)  # (30 - 10) deg, mirrored
    wait_for(lambda: bool(joints) and "mirrored" in joints[-1].name, 2.0, "/joint_states")
    last = joints[-1]
    assert last.position[list(last.name).index("mirrored")] == pytest.approx(math.radians(30.0), abs=0.005)
