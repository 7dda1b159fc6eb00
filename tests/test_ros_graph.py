"""Real rclpy graph: /motor_degree_cmd -> driver -> CANopen -> simulated drive -> /motor_state."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import HAVE_ROS, make_config, requires_ros

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rovercan_msgs.msg import MotorState
    from std_msgs.msg import Float32

    from nodes.motor_controller import MotorControllerNode
    from nodes.qos import COMMAND_QOS, STATE_QOS


@pytest.fixture
def graph(driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> Iterator[dict[str, object]]:
    _, driver = driver_factory(make_config(1))
    context = rclpy.Context()
    rclpy.init(context=context)
    controller = MotorControllerNode(driver, context=context,
                                     parameter_overrides=[Parameter("arm", value=True)])
    probe = rclpy.create_node("probe", context=context)
    states: list[MotorState] = []
    probe.create_subscription(MotorState, "/motor_state", states.append, STATE_QOS)
    pub = probe.create_publisher(Float32, "/motor_degree_cmd", COMMAND_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(controller)
    executor.add_node(probe)

    def spin_until(pred: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
            if pred():
                return True
        return False

    yield {"pub": pub, "states": states, "spin_until": spin_until, "controller": controller, "driver": driver}
    controller.close()
    executor.shutdown()
    controller.destroy_node()
    probe.destroy_node()
    rclpy.shutdown(context=context)


def test_motor_state_angle_reaches_the_command(graph: dict[str, object]) -> None:
    pub, states, spin_until = graph["pub"], graph["states"], graph["spin_until"]
    assert spin_until(lambda: bool(states) and states[-1].enabled, 3.0)  # type: ignore[operator, attr-defined]
    pub.publish(Float32(data=42.0))  # type: ignore[attr-defined]
    assert spin_until(lambda: abs(states[-1].angle - 42.0) < 0.1, 5.0), states[-1]  # type: ignore[operator, index]
    last = states[-1]  # type: ignore[index]
    assert last.name == "joint1" and last.state == "OPERATION_ENABLED" and not last.fault
    assert last.header.stamp.sec > 0 and 0.0 < last.torque < 1.0


def test_wrap_takes_the_short_way(graph: dict[str, object]) -> None:
    pub, states, spin_until = graph["pub"], graph["states"], graph["spin_until"]
    pub.publish(Float32(data=359.9))  # type: ignore[attr-defined]
    assert spin_until(lambda: bool(states) and abs(states[-1].angle - 359.9) < 0.1, 5.0)  # type: ignore[operator, index]
    pub.publish(Float32(data=0.0))  # type: ignore[attr-defined]
    assert spin_until(lambda: states[-1].angle < 0.1 or states[-1].angle > 359.95, 5.0)  # type: ignore[operator, index]
    driver = graph["driver"]
    assert abs(driver.drive("joint1").angle_deg) < 0.2  # type: ignore[attr-defined]  # -0.1 -> 0.0, not 359.9 -> 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_bad_command_is_refused_no_motion_node_alive(graph: dict[str, object], bad: float) -> None:
    pub, states, spin_until, controller = graph["pub"], graph["states"], graph["spin_until"], graph["controller"]
    assert spin_until(lambda: bool(states), 3.0)  # type: ignore[operator]
    before = controller.drive.angle_deg  # type: ignore[attr-defined]
    pub.publish(Float32(data=bad))  # type: ignore[attr-defined]
    assert spin_until(lambda: controller.refused >= 1, 2.0)  # type: ignore[attr-defined, operator]
    count = len(states)  # type: ignore[arg-type]
    assert spin_until(lambda: len(states) > count + 5, 2.0)  # type: ignore[arg-type, operator]  # still publishing
    assert controller.drive.angle_deg == pytest.approx(before, abs=0.01)  # type: ignore[attr-defined]
    pub.publish(Float32(data=10.0))  # type: ignore[attr-defined]  # and still obeys good commands
    assert spin_until(lambda: abs(states[-1].angle - 10.0) < 0.1, 5.0)  # type: ignore[index, operator]
