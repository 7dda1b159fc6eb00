"""Real rclpy graph: /motor_degree_cmd -> driver -> CANopen -> simulated drive -> /motor_state."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import HAVE_ROS, make_config, requires_ros, wait_for
from .test_ros_interface import check_assembly

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.parameter import Parameter
    from rovercan_msgs.msg import MotorState
    from std_msgs.msg import Float32

    from nodes.assembly import Assembly
    from nodes.motor_controller import NODE_NAME
    from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS, STATE_QOS
    from nodes.process.spinning import SpinThread, make_executor


@pytest.fixture
def graph(sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> Iterator[dict[str, object]]:
    """motor_controller as its entry point assembles it (nodes/assembly.py: the driver node
    restricted to one joint, armed), a probe on its hot executor."""
    _, config = sim_factory(make_config(1))
    context = rclpy.Context()
    rclpy.init(context=context)
    hot = make_executor("events", context)
    assembly = Assembly(MotorDriver(config), hot, name=NODE_NAME, joints=["joint1"], context=context,
                        overrides=[Parameter("arm", value=True), Parameter("default_joint", value="joint1"),
                                   Parameter("diagnostics_rate_hz", value=10.0)])
    assembly.build()
    probe = rclpy.create_node("probe", context=context)
    states: list[MotorState] = []
    diags: list[DiagnosticArray] = []
    probe.create_subscription(MotorState, "/motor_state", states.append, STATE_QOS)
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, DIAGNOSTICS_QOS)
    pub = probe.create_publisher(Float32, "/motor_degree_cmd", COMMAND_QOS)
    hot.add_node(probe)
    assembly.start()
    check_assembly(assembly, NODE_NAME, ["joint1"])  # rover_driver's, restricted to one joint
    spin = SpinThread(hot, "test-hot")

    def refused() -> int:
        return sum(st.level == bytes([1]) and "degree command" in st.message
                   for array in list(diags) for st in array.status if st.name == "rovercan: joint1")

    yield {"pub": pub, "states": states, "refused": refused,
           "drive": assembly.driver.drive("joint1"), "driver": assembly.driver}
    spin.stop(5.0)
    assembly.close()
    probe.destroy_node()
    rclpy.shutdown(context=context)


def test_motor_state_angle_reaches_the_command(graph: dict[str, object]) -> None:
    pub, states = graph["pub"], graph["states"]
    wait_for(lambda: bool(states) and states[-1].enabled, 3.0, "an enabled /motor_state")  # type: ignore[attr-defined, index]
    pub.publish(Float32(data=42.0))  # type: ignore[attr-defined]
    wait_for(lambda: abs(states[-1].angle - 42.0) < 0.1, 5.0, "the angle at 42 deg",  # type: ignore[index]
             lambda: str(states[-1]))  # type: ignore[index]
    last = states[-1]  # type: ignore[index]
    assert last.name == "joint1" and last.state == "OPERATION_ENABLED" and not last.fault
    assert last.header.stamp.sec > 0 and 0.0 < last.torque < 1.0


def test_wrap_takes_the_short_way(graph: dict[str, object]) -> None:
    pub, states = graph["pub"], graph["states"]
    pub.publish(Float32(data=359.9))  # type: ignore[attr-defined]
    wait_for(lambda: bool(states) and abs(states[-1].angle - 359.9) < 0.1, 5.0, "359.9 deg")  # type: ignore[index]
    pub.publish(Float32(data=0.0))  # type: ignore[attr-defined]
    wait_for(lambda: states[-1].angle < 0.1 or states[-1].angle > 359.95, 5.0, "0 deg")  # type: ignore[index]
    driver = graph["driver"]
    assert abs(driver.drive("joint1").cache.angle_deg) < 0.2  # type: ignore[attr-defined]  # -0.1 -> 0.0, not 359.9 -> 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_bad_command_is_refused_no_motion_node_alive(graph: dict[str, object], bad: float) -> None:
    pub, states, drive = graph["pub"], graph["states"], graph["drive"]
    wait_for(lambda: bool(states), 3.0, "a /motor_state")
    before = drive.cache.angle_deg  # type: ignore[attr-defined]
    pub.publish(Float32(data=bad))  # type: ignore[attr-defined]
    wait_for(lambda: graph["refused"]() >= 1, 2.0, "a WARN diagnostic of the refusal")  # type: ignore[operator]
    count = len(states)  # type: ignore[arg-type]
    wait_for(lambda: len(states) > count + 5, 2.0, "more /motor_state: still publishing")  # type: ignore[arg-type]
    assert drive.cache.angle_deg == pytest.approx(before, abs=0.01)  # type: ignore[attr-defined]
    pub.publish(Float32(data=10.0))  # type: ignore[attr-defined]  # and still obeys good commands
    wait_for(lambda: abs(states[-1].angle - 10.0) < 0.1, 5.0, "the angle at 10 deg")  # type: ignore[index]
