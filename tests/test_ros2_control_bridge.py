"""ros2_control through the topic-based hardware interface (docs/ros2_control.md): the bridge's
side played with rclpy as it behaves (reliable depth-1 commands with NaN in the fields it does
not command, velocity commands at the controller rate, a best-effort sensor-data subscriber on
/joint_states) against the driver and six simulated wheels; and the example files parse."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import Any

import pytest
import yaml

from can_config import load_config

from .conftest import HAVE_ROS, REPO, publish_until, requires_ros, wait_for
from .test_ros_interface import WHEELS, Graph, graph  # noqa: F401 (the fixture)

EXAMPLE = REPO / "ros" / "rovercan_bringup" / "ros2_control"

if HAVE_ROS:
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from nodes.process.qos import COMMAND_QOS


def test_the_example_urdf_and_controllers_parse_and_match_the_rover() -> None:
    rover = load_config(REPO / "config" / "rover.yaml")
    robot = ET.parse(EXAMPLE / "rover.urdf").getroot()
    control = robot.find("ros2_control")
    assert control is not None
    hardware = control.find("hardware")
    assert hardware is not None
    assert hardware.findtext("plugin") == "joint_state_topic_hardware_interface/JointStateTopicSystem"
    params = {p.get("name"): (p.text or "").strip() for p in hardware.findall("param")}
    assert params["joint_commands_topic"] == "/joint_commands" and params["joint_states_topic"] == "/joint_states"
    assert float(params["trigger_joint_command_threshold"]) < 0  # every command sent: the watchdog
    joints = [j.get("name") for j in control.findall("joint")]
    assert joints == [d.name for d in rover.drives]
    assert all(j.find("command_interface").get("name") == "velocity" for j in control.findall("joint"))  # type: ignore[union-attr]
    controllers = yaml.safe_load((EXAMPLE / "controllers.yaml").read_text())
    diff = controllers["diff_drive_controller"]["ros__parameters"]
    assert rover.drive_system is not None
    assert diff["left_wheel_names"] == list(rover.drive_system.left)
    assert diff["right_wheel_names"] == list(rover.drive_system.right)
    assert diff["wheel_separation"] == rover.drive_system.track_width_m
    assert diff["wheel_radius"] == rover.drive_system.wheel_radius_m
    assert controllers["controller_manager"]["ros__parameters"]["update_rate"] >= 1000 / 500 * 4  # inside the watchdog


def bridge_command(velocities: dict[str, float]) -> Any:
    """What the topic-based interface publishes for velocity command interfaces."""
    msg = JointState()
    msg.name = list(velocities)
    msg.position = [math.nan] * len(velocities)
    msg.velocity = list(velocities.values())
    msg.effort = [math.nan] * len(velocities)
    return msg


@requires_ros
def test_the_bridge_s_velocity_commands_turn_the_wheels_and_stopping_them_stops_the_wheels(graph: Graph) -> None:  # noqa: F811
    for wheel in WHEELS:
        assert graph.call(Trigger, f"wheels/{wheel}/enable").success
    states: list[Any] = []
    graph.probe.create_subscription(JointState, "/joint_states", states.append, qos_profile_sensor_data)
    commands = graph.probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)
    wanted = {w: (2.0 if "left" in w else 3.0) for w in WHEELS}  # rad/s: a left turn

    def at_speed() -> bool:
        return all(math.radians(graph.driver.drive(wheel).snapshot().velocity_deg_s) == pytest.approx(rad_s, rel=0.1)
                   for wheel, rad_s in wanted.items())

    def published_at_speed() -> bool:  # the bridge's best-effort subscriber reads the speeds too
        if not (states and at_speed()):
            return False
        seen = dict(zip(states[-1].name, states[-1].velocity, strict=True))
        return set(seen) == set(WHEELS) and all(seen[w] == pytest.approx(rad_s, rel=0.15) for w, rad_s in wanted.items())

    # the controller manager's 50 Hz, until the wheels turn at the commanded speeds and /joint_states
    # says so: read while the commands flow (once they stop, the watchdog stops the wheels, and a
    # starved test process read the stopped wheels' /joint_states)
    publish_until(lambda: commands.publish(bridge_command(wanted)), published_at_speed, 30.0,
                  "every wheel at its speed, on the wheels and on /joint_states", period_s=0.02)
    # the controller stops publishing (deactivated, crashed): the watchdog stops every wheel
    wait_for(lambda: all(abs(graph.driver.drive(w).snapshot().velocity_deg_s) < 1.0 for w in WHEELS), 30.0,
             "every wheel stopped after the commands stopped")


@requires_ros
def test_one_commands_set_points_go_out_in_one_write_a_bus_and_a_failed_write_refuses_that_bus_s_joints(
        graph: Graph) -> None:  # noqa: F811
    """A /joint_commands message's set-points of one bus go out in one write of its socket (the
    driver's one_write, as a trajectory group's SYNC does): seen by a hook on each bus's write, which
    a command sent a frame at a time never calls. A write that fails refuses the joints of that bus
    only, naming the bus, on /diagnostics; the other bus's joints are not blamed."""
    from diagnostic_msgs.msg import DiagnosticArray

    from motor_driver.bus.adapters import GuardedNetwork
    from nodes.process.qos import DIAGNOSTICS_QOS

    for wheel in WHEELS:
        assert graph.call(Trigger, f"wheels/{wheel}/enable").success
    by_bus: dict[str, list[str]] = {}
    for wheel in WHEELS:
        by_bus.setdefault(graph.driver.drive(wheel).config.bus, []).append(wheel)
    writes: dict[str, list[bytes]] = {bus: [] for bus in by_bus}
    failing: set[str] = set()
    restore = []
    for bus, wheels in by_bus.items():
        network = graph.driver.drive(wheels[0]).network
        assert isinstance(network, GuardedNetwork)
        made_for, direct = network._direct()
        assert direct is not None, "the shipped buses are socketcand"

        def write(payload: bytes, bus: str = bus, real: Any = direct.write) -> None:
            writes[bus].append(payload)
            if bus in failing:
                raise OSError(32, "Broken pipe")
            real(payload)
        network._sender = (made_for, direct._replace(write=write))
        restore.append((network, made_for, direct))
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
    commands = graph.probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)
    wanted = {w: 1.0 for w in WHEELS}
    try:
        publish_until(lambda: commands.publish(bridge_command(wanted)),
                      lambda: all(any(p.count(b"< send ") == len(by_bus[bus]) for p in writes[bus]) for bus in by_bus),
                      30.0, "each bus's wheels' set-points of one message in one write", period_s=0.02)
        failed_bus, other_bus = sorted(by_bus)[1], sorted(by_bus)[0]
        failing.add(failed_bus)
        # one wheel of the failing bus commanded nothing (NaN): refused for that, never for the write
        victim, *sent = by_bus[failed_bus]
        wanted[victim] = math.nan

        def said(wheel: str, text: str) -> bool:
            return any(st.name == f"rovercan: {wheel}" and st.level == bytes([1]) and text in st.message
                       for array in diags for st in array.status)

        def warned(wheel: str) -> bool:
            return said(wheel, f"the set-point was not sent: bus {failed_bus}: ")
        publish_until(lambda: commands.publish(bridge_command(wanted)),
                      lambda: all(warned(w) for w in sent) and said(victim, "no position, velocity or effort"), 30.0,
                      f"the wheels of {failed_bus} refused, naming the bus", period_s=0.02)
        assert not any(said(w, f"bus {failed_bus}") for w in [victim, *by_bus[other_bus]]), \
            f"{other_bus}'s wheels or {victim} (refused at once) blamed for {failed_bus}'s write"
    finally:
        for network, made_for, direct in restore:
            network._sender = (made_for, direct)
