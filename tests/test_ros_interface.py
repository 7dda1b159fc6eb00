"""Real rclpy graph tests of the complete ROS interface against simulated drives."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from can_config import RoverConfig, load_config, with_bus_overrides
from can_config.errors import CommandRejected
from motor_driver import MotorDriver, State
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import (
    HAVE_ROS,
    REPO,
    in_process_stale_after_syncs,
    publish_until,
    requires_ros,
    stop_reason,
    wait_for,
)

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rovercan_msgs.msg import MotorState
    from rovercan_msgs.srv import SdoRead, SdoWrite, SetMode
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32
    from std_srvs.srv import Trigger

    from nodes.assembly import Assembly
    from nodes.joints.driver_node import DriverNode
    from nodes.joints.driver_services import DriverServicesNode
    from nodes.process import spinning
    from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS, STATE_QOS
    from nodes.process.spinning import SpinThread, make_executor
    from nodes.rover.drive_system import DriveSystemNode

WHEELS = ["wheel_front_left", "wheel_middle_left", "wheel_rear_left",
          "wheel_front_right", "wheel_middle_right", "wheel_rear_right"]


class Graph:
    def __init__(self, sim: SimService, assembly: Assembly, context: Any, probe: Any) -> None:
        self.sim, self.assembly, self.driver, self.context, self.probe = sim, assembly, assembly.driver, context, probe
        self.driver_node, self.system_node = assembly.nodes[0], assembly.nodes[1]
        self.inbox: dict[str, list[Any]] = {}
        self.clients: dict[str, Any] = {}

    def listen(self, msg_type: Any, topic: str, qos: Any = None) -> list[Any]:
        box: list[Any] = []
        self.probe.create_subscription(msg_type, topic, box.append, qos or STATE_QOS)
        return box

    def call(self, srv_type: Any, name: str, request: Any = None, timeout_s: float = 15.0) -> Any:
        client = self.clients.get(name)
        if client is None:  # one client per service: creating ROS entities holds the interpreter
            client = self.clients[name] = self.probe.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=5.0), f"no service {name}"
        future = client.call_async(request if request is not None else srv_type.Request())
        deadline = time.monotonic() + timeout_s
        while not future.done():
            assert time.monotonic() < deadline, f"service {name} did not answer"
            time.sleep(0.01)
        return future.result()


#: The consumer time of the drives' host watch in graphs where the simulated drives, the bus
#: server, the driver, the nodes and the test share one interpreter: the suite's process (six
#: drives simulated in Python at 1 kHz, a server thread per client, ROS entities created while
#: drives are enabled) has held the driver's supervisor up to 0.1 s, which the shipped 150 ms
#: does not cover; with two busy loops beside the suite on two cores the whole process was once
#: starved 0.9 s, and every drive rightly stopped itself in the middle of a test of the drive
#: system. The driver process alone is measured by the benchmarks (host heartbeat gap).
IN_PROCESS_HOST_TIMEOUT_S = 2.0
#: The driver's consumer time of the drives' heartbeats in these graphs, for the same reason.
GRAPH_HEARTBEAT_TIMEOUT_S = 2.5


def in_process_host_timeout(config: RoverConfig) -> RoverConfig:
    """The in-process consumer times both ways and the staleness bound, longer than a starved test
    process's pause."""
    drives = tuple(dataclasses.replace(d, host_timeout_s=IN_PROCESS_HOST_TIMEOUT_S,
                                       heartbeat_timeout_s=GRAPH_HEARTBEAT_TIMEOUT_S,
                                       stale_after_syncs=in_process_stale_after_syncs(config.bus(d.bus).sync_period_s))
                   for d in config.drives)
    return dataclasses.replace(config, drives=drives)


#: The wheel that homes slowly in these graphs (no other test homes it): method 17 at 0.5 deg/s
#: toward the index, which the test that needs it moves far away in the simulated drive.
SLOW_HOMING = "wheel_middle_right"


def slow_homing(config: RoverConfig, joint: str) -> RoverConfig:
    drives = tuple(dataclasses.replace(d, homing_method=17, homing_speed_deg_s=0.5, homing_timeout_s=600.0)
                   if d.name == joint else d for d in config.drives)
    return dataclasses.replace(config, drives=drives)


@pytest.fixture
def graph(monkeypatch: pytest.MonkeyPatch) -> Iterator[Graph]:
    """The rover_driver process as its entry point assembles it (nodes/assembly.py), in this
    process: the hot executor on a thread of the test's, a probe node on it."""
    # the idle executors never poll here: whatever they serve must wake them (a goal's pause, a stop)
    monkeypatch.setattr(spinning, "IDLE_POLL_S", 600.0)
    config = slow_homing(in_process_host_timeout(load_config(REPO / "config" / "rover.yaml")), SLOW_HOMING)
    sim = SimService.from_config(config, port=0)
    context = rclpy.Context()
    rclpy.init(context=context)
    hot = make_executor("events", context)
    assembly = Assembly(MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)), hot, context=context,
                        overrides=[Parameter("diagnostics_rate_hz", value=5.0),
                                   Parameter("default_joint", value="wheel_front_left")])
    assembly.build()
    assert isinstance(assembly.nodes[1], DriveSystemNode)
    assert not list(assembly.nodes[1].timers)  # the control loop on the state timer, as rover_driver runs it
    probe = rclpy.create_node("probe", context=context)
    hot.add_node(probe)
    assembly.start()
    check_assembly(assembly, "rovercan_driver", WHEELS)  # rover_driver's
    spin = SpinThread(hot, "test-hot")
    yield Graph(sim, assembly, context, probe)
    spin.stop(5.0)
    assembly.close()
    probe.destroy_node()
    rclpy.shutdown(context=context)
    sim.close()


def check_assembly(assembly: Assembly, driver_node: str, joints: list[str]) -> None:
    """What every entry point's process is made of (nodes/assembly.py): the driver node (and the
    drive system, with every joint) on the hot executor; the stops, the waiting services and the
    actions each on an executor thread of their own; the services in one callback group per joint
    and one for /arm; /motor_degree_cmd on the command path of the joints' degree_cmd."""
    hot = type(assembly.hot).__name__
    expected = {driver_node: (hot, "hot"),
                "rovercan_driver_stops": ("SingleThreadedExecutor", "rovercan-stops"),
                "rovercan_driver_services": ("MultiThreadedExecutor", "rovercan-services"),
                "rovercan_driver_actions": ("SingleThreadedExecutor", "rovercan-actions")}
    if assembly.driver.config.drive_system is not None and len(joints) == len(assembly.driver.drives):
        expected["drive_system"] = (hot, "hot")
    assert assembly.layout() == expected
    services = next(n for n in assembly.nodes if isinstance(n, DriverServicesNode))
    assert sorted(services.groups) == sorted(["", *joints])
    assert len({id(g) for g in services.groups.values()}) == len(services.groups)  # one group each
    assert all(isinstance(g, MutuallyExclusiveCallbackGroup) for g in services.groups.values())
    assert isinstance(assembly.node, DriverNode) and list(assembly.node.drives) == joints


def eventually(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    wait_for(pred, timeout_s, what)


#: A bound for a hang: what a test waits for comes much sooner, later on a crowded machine.
HANG_S = 30.0


def test_per_drive_topics_and_joint_states(graph: Graph) -> None:
    joint = "wheel_rear_right"
    assert graph.call(Trigger, f"wheels/{joint}/enable").success
    states = graph.listen(MotorState, f"wheels/{joint}/motor_state")
    joints = graph.listen(JointState, "/joint_states")
    degree = graph.probe.create_publisher(Float32, f"wheels/{joint}/degree_cmd", COMMAND_QOS)
    wait_for(lambda: degree.get_subscription_count() > 0, 10.0, "degree_cmd matched")
    drive = graph.driver.drive(joint)
    for step in range(1, 13):  # the wheels' degree_cmd is a stream (position_mode: cyclic): 10 deg steps
        degree.publish(Float32(data=10.0 * step))
        eventually(lambda step=step: abs(drive.cache.angle_deg - 10.0 * step) < 1.0, 5.0, f"angle {10 * step}")
    eventually(lambda: bool(states) and abs(states[-1].angle - 120.0) < 0.2, 8.0, "angle 120")
    assert states[-1].name == joint and states[-1].enabled
    velocity = graph.probe.create_publisher(Float32, f"wheels/{joint}/velocity_cmd", COMMAND_QOS)
    for _ in range(30):
        velocity.publish(Float32(data=-90.0))
        time.sleep(0.02)
    eventually(lambda: abs(states[-1].velocity + 90.0) < 2.0, 3.0, "velocity -90 deg/s")
    last = joints[-1]
    assert list(last.name) == WHEELS
    i = last.name.index(joint)
    assert last.velocity[i] == pytest.approx(math.radians(states[-1].velocity), abs=0.1)
    assert abs(last.header.stamp.sec + last.header.stamp.nanosec * 1e-9 - time.time()) < 1.0
    assert graph.call(Trigger, f"wheels/{joint}/quick_stop").success


def test_services_answer_with_what_happened(graph: Graph) -> None:
    joint = "wheel_front_left"
    drive = graph.driver.drive(joint)
    reply = graph.call(Trigger, f"wheels/{joint}/enable")
    assert reply.success and "OPERATION_ENABLED" in reply.message
    assert graph.call(Trigger, f"wheels/{joint}/halt").success
    assert graph.call(Trigger, f"wheels/{joint}/disable").success
    assert drive.cache.state is State.READY_TO_SWITCH_ON
    mode = graph.call(SetMode, f"wheels/{joint}/set_mode", SetMode.Request(mode="profile_velocity"))
    assert mode.success and "confirmed by 0x6061" in mode.message
    bad = graph.call(SetMode, f"wheels/{joint}/set_mode", SetMode.Request(mode="warp"))
    assert not bad.success and "allowed: PROFILE_POSITION" in bad.message
    unsupported = graph.call(SetMode, f"wheels/{joint}/set_mode", SetMode.Request(mode="interpolated_position"))
    assert not unsupported.success and "not supported" in unsupported.message
    read = graph.call(SdoRead, f"wheels/{joint}/sdo_read", SdoRead.Request(index=0x1018, subindex=1))
    assert read.success and read.value == 0x00524F56
    missing = graph.call(SdoRead, f"wheels/{joint}/sdo_read", SdoRead.Request(index=0x2345, subindex=0))
    assert not missing.success and "0x06020000" in missing.message and "does not exist" in missing.message
    refused = graph.call(SdoWrite, f"wheels/{joint}/sdo_write", SdoWrite.Request(index=0x607A, subindex=0, value=99999))
    assert not refused.success and "refused" in refused.message
    for index, subindex, why in ((0x60C1, 1, "motion target"), (0x60B0, 0, "motion target"),
                                 (0x6091, 1, "the drive's units"), (0x607E, 0, "set invert")):
        said = graph.call(SdoWrite, f"wheels/{joint}/sdo_write", SdoWrite.Request(index=index, subindex=subindex, value=1))
        assert not said.success and "refused" in said.message and why in said.message, (hex(index), said.message)
    ro = graph.call(SdoWrite, f"wheels/{joint}/sdo_write", SdoWrite.Request(index=0x1000, subindex=0, value=1))
    assert not ro.success and "read only" in ro.message
    ok = graph.call(SdoWrite, f"wheels/{joint}/sdo_write", SdoWrite.Request(index=0x6065, subindex=0, value=30000))
    assert ok.success
    assert graph.call(Trigger, f"wheels/{joint}/enable").success
    assert graph.call(Trigger, f"wheels/{joint}/home").success
    stop = graph.call(Trigger, f"wheels/{joint}/quick_stop")
    assert stop.success and drive.cache.state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED), stop.message
    assert graph.call(Trigger, f"wheels/{joint}/enable").success
    apply_action(graph.sim, {"action": "fault", "node": 1, "code": 0x2310})  # node 1 on can0
    eventually(lambda: drive.cache.state is State.FAULT, 2.0, "fault")
    recover = graph.call(Trigger, f"wheels/{joint}/recover")
    assert recover.success, recover.message
    assert drive.cache.state is State.OPERATION_ENABLED


def test_diagnostics_levels_follow_the_rules(graph: Graph) -> None:
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)

    def status(name: str) -> Any:
        for array in reversed(diags):
            for st in array.status:
                if st.name == f"rovercan: {name}":
                    return st
        return None

    def bus_values(name: str) -> dict[str, str]:
        st = status(f"bus {name}")
        return {} if st is None else {kv.key: kv.value for kv in st.values}

    eventually(lambda: status("wheel_front_left") is not None and status("bus can0") is not None, 10.0, "diagnostics")
    assert status("wheel_front_left").level == bytes([0])
    keys = {kv.key for kv in status("wheel_front_left").values}
    assert {"nmt_state", "cia402_state", "last_emcy_code", "last_emcy_text", "heartbeat_age_s"} <= keys
    # the load is a rate over the last sample window: the first status may come before one closed
    eventually(lambda: float(bus_values("can0").get("load", "0")) > 0.0, 10.0, "a bus load measured")
    bus = bus_values("can0")
    # one status per bus; a socketcand bus has no kernel controller: its state is said to be unknown
    assert status("bus can1") is not None and bus["can_state"] == "unknown (socketcand: no kernel controller to read)"
    apply_action(graph.sim, {"action": "fault", "node": 2, "code": 0x4210})  # wheel_middle_left
    eventually(lambda: status("wheel_middle_left") is not None and status("wheel_middle_left").level == bytes([2]),
               10.0, "ERROR on fault")
    assert "0x4210" in status("wheel_middle_left").message and "temperature" in status("wheel_middle_left").message
    apply_action(graph.sim, {"action": "unplug", "node": 3})  # wheel_rear_left
    eventually(lambda: status("wheel_rear_left").level == bytes([2]) and "heartbeat lost" in status("wheel_rear_left").message,
               10.0, "ERROR on heartbeat loss")


@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e9])
def test_bad_commands_refused_no_motion_warning_diagnostic(graph: Graph, bad: float) -> None:
    joint = "wheel_front_right"
    drive = graph.driver.drive(joint)
    assert graph.call(Trigger, f"wheels/{joint}/enable").success
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
    eventually(lambda: bool(diags), 10.0, "a first /diagnostics")  # matched: a refusal is said once
    before = drive.cache.angle_deg
    pub = graph.probe.create_publisher(Float32, f"wheels/{joint}/degree_cmd", COMMAND_QOS)
    vel = graph.probe.create_publisher(Float32, f"wheels/{joint}/velocity_cmd", COMMAND_QOS)
    commands = graph.probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)
    wait_for(lambda: all(p.get_subscription_count() > 0 for p in (pub, vel, commands)), 10.0, "the topics matched")
    target = drive.channel.target_counts
    pub.publish(Float32(data=bad))
    vel.publish(Float32(data=bad))
    commands.publish(JointState(name=["no_such_joint"], position=[0.1]))

    def warned(name: str, text: str) -> bool:
        return any(st.name == f"rovercan: {name}" and st.level == bytes([1]) and text in st.message
                   for array in diags for st in array.status)

    # the refusal names the command and its value (formatted only for a refused one)
    eventually(lambda: warned(joint, f" command {Float32(data=bad).data!r}: "), 10.0, "a WARN diagnostic for the refused command")
    eventually(lambda: warned("command input", "unknown joint 'no_such_joint'"), 10.0,
               "a WARN diagnostic for the unknown joint")
    # nothing moved, by what the driver sent: no new target, no velocity command (both were refused)
    assert drive.channel.target_counts == target and not drive.channel.velocity_commanded
    assert drive.cache.angle_deg == pytest.approx(before, abs=0.01)
    pub.publish(Float32(data=before + 10.0))  # still alive, still obeys (one step of the wheel's stream)
    eventually(lambda: abs(drive.cache.angle_deg - before - 10.0) < 0.2, 5.0, "good command after bad ones")


def test_cmd_vel_drives_the_wheels_by_the_kinematics_and_stops_when_stale(graph: Graph) -> None:
    for wheel in WHEELS:
        assert graph.call(Trigger, f"wheels/{wheel}/enable").success
    odom = graph.listen(Odometry, "/odom")
    cmd = graph.probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
    twist = Twist()
    twist.linear.x, twist.angular.z = 0.4, 0.5
    # left = (0.4 - 0.5*0.3)/0.1 = 2.5 rad/s, right = (0.4 + 0.15)/0.1 = 5.5 rad/s
    # the simulated servos share this process (and its GIL) with ROS and the driver: their
    # speed wobbles by a few percent under that load, so 10 % here, and the ratio tighter

    def wheels_at_speed() -> bool:
        left = graph.driver.drive("wheel_middle_left").snapshot().velocity_deg_s
        right = graph.driver.drive("wheel_middle_right").snapshot().velocity_deg_s
        return (math.radians(left) == pytest.approx(2.5, rel=0.1) and math.radians(right) == pytest.approx(5.5, rel=0.1)
                and right / left == pytest.approx(5.5 / 2.5, rel=0.08))

    def odom_integrated() -> bool:
        last = odom[-1] if odom else None
        return (last is not None and last.twist.twist.linear.x == pytest.approx(0.4, rel=0.1)
                and last.twist.twist.angular.z == pytest.approx(0.5, rel=0.15) and last.pose.pose.position.x > 0.3)

    # a stream, published until its outcome: a starved graph reaches the speeds later, not otherwise
    publish_until(lambda: cmd.publish(twist), lambda: wheels_at_speed() and odom_integrated(), HANG_S,
                  "the wheels at the kinematics' speeds and /odom integrating them")
    # the right side is mounted mirrored (invert: true in config/rover.yaml): forward in joint
    # space is a negative velocity on its drives, positive on the left side's
    for channel, sign in (("can0", 1), ("can1", -1)):
        runner = graph.sim.simulators[channel]
        drive_velocity = float(runner.call(lambda runner=runner: runner.drive(2).store.get(0x606C, 0)))
        assert drive_velocity * sign > 0, (channel, drive_velocity)
    # no more /cmd_vel: after the timeout (0.5 s) the wheels ramp down (1 m/s^2) and stop
    eventually(lambda: all(abs(graph.driver.drive(w).snapshot().velocity_deg_s) < 1.0 for w in WHEELS), HANG_S,
               "wheels stopped after /cmd_vel went stale")
    assert graph.system_node.cmd_timed_out
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
    eventually(lambda: bool(diags), 10.0, "a first /diagnostics")  # matched: a refusal is said once
    bad = Twist()
    bad.linear.x = math.nan
    cmd.publish(bad)
    eventually(lambda: any(st.name == "rovercan: command input" and st.level == bytes([1]) and
                           "/cmd_vel with non-finite values" in st.message for a in diags for st in a.status),
               HANG_S, "a WARN diagnostic for the NaN twist")
    # the NaN was refused before any frame: no wheel has a velocity command live
    assert not any(graph.driver.drive(w).channel.velocity_commanded for w in WHEELS)
    assert all(abs(graph.driver.drive(w).snapshot().velocity_deg_s) < 1.0 for w in WHEELS)


def test_the_control_loop_shares_the_state_timer_only_at_its_rate(graph: Graph) -> None:
    """rover_driver runs the drive system's loop from the driver node's state timer (one wake-up
    of their executor a period, not two; the test above drove the wheels and read /odom so); a
    drive system at another rate keeps a timer of its own."""
    assert not list(graph.system_node.timers)
    other = DriveSystemNode(graph.driver, load_config(REPO / "config" / "rover.yaml"), context=graph.context,
                            parameter_overrides=[Parameter("odom_rate_hz", value=20.0)])
    try:
        assert not other.tick_with(graph.driver_node) and len(list(other.timers)) == 1
    finally:
        other.destroy_node()


def test_bus_lost_is_published_and_nodes_keep_running(graph: Graph) -> None:
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
    states = graph.listen(MotorState, "wheels/wheel_front_left/motor_state")
    graph.sim.close()  # both buses' server dies

    def bus_error() -> bool:
        return any(st.name == "rovercan: bus can0" and st.level == bytes([2]) and st.message == "bus lost"
                   for array in diags[-3:] for st in array.status)

    eventually(bus_error, 15.0, "bus lost on /diagnostics")
    eventually(lambda: bool(states) and states[-1].state == "LOST" and states[-1].fault, 10.0, "MotorState LOST")
    count = len(states)
    eventually(lambda: len(states) > count + 10, 2.0, "MotorState still published")


def tpdo_velocities(frames: list[Any], counts_per_deg: float) -> list[float]:
    """Joint speeds (deg/s, unsigned) in the drives' TPDO2 (0x28N: position, velocity)."""
    return [abs(int.from_bytes(m.data[4:8], "little", signed=True)) / counts_per_deg
            for m in frames if 0x281 <= m.arbitration_id <= 0x283 and len(m.data) == 8]


def test_cmd_vel_beyond_every_limit_is_scaled_whole_and_nothing_moves_after_it_stops(graph: Graph) -> None:
    import can

    from virtual_can.server import RAWMODE_HOLD_S

    from .conftest import drain

    for wheel in WHEELS:
        assert graph.call(Trigger, f"wheels/{wheel}/enable").success
    listeners: list[can.BusABC] = []
    try:
        odom = graph.listen(Odometry, "/odom")
        cmd = graph.probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
        twist = Twist()
        twist.linear.x, twist.angular.z = 1.0, 4.0  # right wheel: 22 rad/s, 2.2 m/s at the rim
        peak, at_limit, deadline = 0.0, 0, time.monotonic() + 60.0
        while at_limit < 20:  # commanded until the fastest wheel is at its limit, then one second more
            assert time.monotonic() < deadline, f"the fastest wheel reached {math.radians(peak):.2f} rad/s only"
            cmd.publish(twist)
            peak = max([peak] + [abs(graph.driver.drive(w).snapshot().velocity_deg_s) for w in WHEELS])
            at_limit += math.radians(peak) >= 10.0 * 0.9
            time.sleep(0.05)
        # scaled as a whole: the fastest wheel at the 1.0 m/s rim limit (10 rad/s), the turn kept
        assert math.radians(peak) <= 10.0 * 1.05
        assert math.radians(peak) >= 10.0 * 0.9
        last = odom[-1].twist.twist
        assert last.angular.z / last.linear.x == pytest.approx(4.0, rel=0.15)
        assert not graph.system_node.cmd_timed_out and graph.driver.drive("wheel_front_right").limits.watchdog_stops == 0
        # /cmd_vel stops: the wheels ramp down (10 rad/s at 10 rad/s^2 after the 0.5 s timeout)
        wait_for(lambda: all(abs(graph.driver.drive(w).snapshot().velocity_deg_s) < 0.5 for w in WHEELS), 30.0,
                 "the wheels stopped after /cmd_vel did")
        listeners += [can.Bus(interface="socketcand", channel=ch, host=graph.sim.host, port=graph.sim.port)
                      for ch in ("can0", "can1")]
        time.sleep(RAWMODE_HOLD_S + 0.05)
        for bus in listeners:
            drain(bus, 0.02)
        time.sleep(10.0)  # ten seconds of the bus, read back from each listener's queue
        frames = [m for bus in listeners for m in drain(bus, 0.5)]
        speeds = tpdo_velocities(frames, 4096 * 50 / 360.0)
        assert len(speeds) > 500 and max(speeds) < 0.5, max(speeds)  # and they stay stopped (seen on the bus)
        # angular alone beyond max_angular_rad_s: turned on the spot at 2 rad/s
        spin = Twist()
        spin.angular.z = 4.0
        turning, deadline = 0, time.monotonic() + 60.0
        while turning < 20:  # commanded until the rover turns at its limit, then one second more
            assert time.monotonic() < deadline, f"the turn reached {odom[-1].twist.twist.angular.z:.2f} rad/s only"
            cmd.publish(spin)
            turning += abs(odom[-1].twist.twist.angular.z) >= 2.0 * 0.9
            time.sleep(0.05)
        last = odom[-1].twist.twist
        assert abs(last.angular.z) == pytest.approx(2.0, rel=0.1) and abs(last.linear.x) < 0.05
        rim = max(abs(math.radians(graph.driver.drive(w).snapshot().velocity_deg_s)) * 0.1 for w in WHEELS)
        assert rim <= 1.0 * 1.05
    finally:
        for bus in listeners:
            bus.shutdown()


def test_a_wheel_that_cannot_follow_stops_the_whole_drive_system(graph: Graph) -> None:
    for wheel in WHEELS:
        assert graph.call(Trigger, f"wheels/{wheel}/enable").success
    cmd = graph.probe.create_publisher(Twist, "/cmd_vel", COMMAND_QOS)
    twist = Twist()
    twist.linear.x = 0.5
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)

    def all_faster_than(deg_s: float) -> bool:
        return all(graph.driver.drive(w).snapshot().velocity_deg_s > deg_s for w in WHEELS)

    def none_driven() -> bool:
        return all(abs(graph.driver.drive(w).snapshot().velocity_deg_s) < 1.0 for w in WHEELS)

    def said_why() -> bool:  # the real cause and what helps (issue 52: "arm the rover" was said for a wheel in FAULT)
        return any("wheel_middle_left: faulted (FAULT: EMCY 0x2310" in st.message and "/recover" in st.message
                   and stop_reason(st, "; no wheel is driven") is not None for a in diags for st in a.status)

    publish_until(lambda: cmd.publish(twist), lambda: all_faster_than(100.0), HANG_S, "all six wheels driven")
    apply_action(graph.sim, {"action": "fault", "node": 2, "code": 0x2310})  # wheel_middle_left (can0)
    # /cmd_vel still fresh, but one wheel is in FAULT: none is driven, and the diagnostics say why
    publish_until(lambda: cmd.publish(twist), lambda: none_driven() and said_why(), HANG_S,
                  "no wheel driven with one in FAULT, and why said")
    graph.driver.drive("wheel_middle_left").recover()
    graph.driver.drive("wheel_middle_left").enable()
    # recovered, but no fresh /cmd_vel: nothing moves, not even briefly. The /cmd_vel refused
    # while the wheel was in FAULT was still within its 500 ms timeout when the wheel came back,
    # and drove all six for a moment (caught only at the end of a loaded run; watched throughout
    # now, until the drive system has taken /cmd_vel for stale, and then 20 samples more of a wheel)
    fastest = 0.0

    def watched() -> bool:
        nonlocal fastest
        fastest = max([fastest, *(abs(graph.driver.drive(w).snapshot().velocity_deg_s) for w in WHEELS)])
        return bool(graph.system_node.cmd_timed_out)

    wait_for(watched, HANG_S, "the drive system to take /cmd_vel for stale")
    wheel = graph.driver.drive("wheel_middle_left")
    until = wheel.cache.position_seq + 20
    wait_for(lambda: watched() and wheel.cache.position_seq >= until, HANG_S, "20 samples of a wheel")
    assert fastest < 1.0, f"a wheel turned at {fastest:.1f} deg/s on the /cmd_vel refused before the recovery"
    # a fresh command drives all six again
    publish_until(lambda: cmd.publish(twist), lambda: all_faster_than(100.0), HANG_S, "all six wheels driven again")


def test_motor_state_is_marked_stale_when_the_pdos_stop(graph: Graph) -> None:
    states = graph.listen(MotorState, "wheels/wheel_front_left/motor_state")
    joints = graph.listen(JointState, "/joint_states")
    eventually(lambda: bool(states) and not states[-1].stale and math.isfinite(states[-1].angle), 3.0, "fresh state")
    apply_action(graph.sim, {"action": "tpdos", "node": 1, "channel": "can0", "on": False})
    eventually(lambda: states[-1].stale, 10.0, "MotorState stale")  # how soon: benchmarks, not a test
    last = states[-1]
    assert math.isnan(last.angle) and math.isnan(last.velocity) and not last.enabled and last.data_age >= 0.05
    eventually(lambda: math.isnan(joints[-1].position[0]) and math.isfinite(joints[-1].position[3]), 10.0,
               "/joint_states: NaN for the stale joint only")
    apply_action(graph.sim, {"action": "tpdos", "node": 1, "channel": "can0", "on": True})
    eventually(lambda: not states[-1].stale and math.isfinite(states[-1].angle), 10.0, "fresh again")


def test_a_slow_enable_service_never_stalls_commands_or_other_joints_topics(graph: Graph) -> None:
    apply_action(graph.sim, {"action": "slow_enable", "node": 1, "channel": "can0", "delay_s": 0.7})  # ~2 s
    diags = graph.listen(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
    eventually(lambda: bool(diags), 10.0, "a first /diagnostics")  # matched: a refusal is said once
    other: list[float] = []  # arrival times of joint B's MotorState
    graph.probe.create_subscription(MotorState, "wheels/wheel_rear_left/motor_state",
                                    lambda _msg: other.append(time.monotonic()), STATE_QOS)
    degree = graph.probe.create_publisher(Float32, "wheels/wheel_front_left/degree_cmd", COMMAND_QOS)
    client = graph.probe.create_client(Trigger, "wheels/wheel_front_left/enable")
    assert client.wait_for_service(timeout_sec=5.0)
    wait_for(lambda: degree.get_subscription_count() > 0, 10.0, "the degree topic matched")
    future = client.call_async(Trigger.Request())
    drive = graph.driver.drive("wheel_front_left")
    eventually(lambda: drive.channel.busy == "enable", 10.0, "the enable service to start")
    n0 = len(other)
    refused = 0
    while not future.done() and refused < 30:
        degree.publish(Float32(data=30.0))  # the hot executor refuses it at once
        try:
            drive.move_to(30.0)  # what the topic callback runs
        except CommandRejected as err:
            assert "busy with enable" in str(err)
            # refused at once, not after waiting: the enable it would have waited for still runs
            assert drive.channel.busy == "enable" and not future.done()
            refused += 1
        drive.cache.wait_until(future.done, 0.02)
    eventually(future.done, 15.0, "the enable service's answer")
    during = len(other) - n0
    assert future.result().success and refused >= 30, refused
    # order, not rate (the benchmarks time it): joint B's MotorState kept coming while the enable
    # service waited (about 2 s at 50 Hz); a stall behind it would have left none in that time
    assert during >= 10, during
    eventually(lambda: any("busy with enable" in kv.value for a in diags for st in a.status if "wheel_front_left" in st.name
                           for kv in st.values), 10.0, "the refusal in /diagnostics")


def test_default_qos_subscribers_receive_the_state_topics(graph: Graph) -> None:
    """What RViz, Nav2 and a plain rclpy subscriber use: reliable, volatile, keep last 10. A
    best-effort publisher was invisible to them ("offering incompatible QoS")."""
    from rclpy.qos import QoSProfile

    default = QoSProfile(depth=10)
    inboxes = {topic: graph.listen(msg_type, topic, default) for topic, msg_type in (
        ("/odom", Odometry), ("/joint_states", JointState), ("/diagnostics", DiagnosticArray),
        ("wheels/wheel_front_left/motor_state", MotorState), ("/motor_state", MotorState))}
    eventually(lambda: all(inboxes.values()), 5.0, "a message on every state topic")


def test_best_effort_and_reliable_command_publishers_both_drive_a_wheel(graph: Graph) -> None:
    """The driver takes set-points best effort: a best-effort publisher (a joystick bridge, a
    sensor-data profile) drives a wheel, where the reliable subscription it had refused it
    ("offering incompatible QoS", nothing moved); a reliable publisher still does."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    joint = "wheel_front_right"
    drive = graph.driver.drive(joint)
    assert graph.call(Trigger, f"wheels/{joint}/enable").success
    best_effort = graph.probe.create_publisher(Float32, f"wheels/{joint}/velocity_cmd",
                                               QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    reliable = graph.probe.create_publisher(Float32, f"wheels/{joint}/velocity_cmd", COMMAND_QOS)
    for pub, target in ((best_effort, 60.0), (reliable, -60.0)):
        wait_for(lambda pub=pub: pub.get_subscription_count() > 0, 10.0, "velocity_cmd matched")

        def turning(pub: Any = pub, target: float = target) -> bool:
            pub.publish(Float32(data=target))  # a stream, as a teleop sends it
            return abs(drive.snapshot().velocity_deg_s - target) < 2.0
        eventually(turning, 5.0, f"{target} deg/s from a {pub.qos_profile.reliability.name} publisher")
    assert graph.call(Trigger, f"wheels/{joint}/quick_stop").success
    # the rule on every command topic of the node, as the graph reports it
    topics = ["/cmd_vel", "/joint_commands", "/motor_degree_cmd"] + [f"wheels/{w}/{kind}_cmd" for w in WHEELS
                                                                     for kind in ("degree", "velocity")]
    for topic in topics:
        subs = graph.probe.get_subscriptions_info_by_topic(graph.probe.resolve_topic_name(topic))
        assert subs and all(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in subs), topic


def test_home_and_move_joint_actions_give_feedback_and_cancel_stops_the_joint(graph: Graph) -> None:
    from rclpy.action import ActionClient
    from rovercan_msgs.action import Home, MoveJoint

    client_node = rclpy.create_node("action_client", context=graph.context)
    executor = SingleThreadedExecutor(context=graph.context)
    executor.add_node(client_node)
    spin = SpinThread(executor, "test-action-client")
    try:
        joint = "wheel_rear_left"
        drive = graph.driver.drive(joint)
        move = ActionClient(client_node, MoveJoint, "move_joint")
        home = ActionClient(client_node, Home, "home_joint")
        assert move.wait_for_server(timeout_sec=5.0) and home.wait_for_server(timeout_sec=5.0)
        assert graph.call(Trigger, f"wheels/{joint}/enable").success

        def run(client: Any, goal: Any, cancel_when: Callable[[], bool] | None = None) -> tuple[Any, list[Any]]:
            feedback: list[Any] = []
            sent = client.send_goal_async(goal, feedback_callback=lambda f: feedback.append(f.feedback))
            eventually(sent.done, 5.0, "the goal accepted")
            handle = sent.result()
            assert handle.accepted
            if cancel_when is not None:  # the cancel's moment: a state of the move, not a span
                eventually(cancel_when, 30.0, "the moment to cancel")
                cancel = handle.cancel_goal_async()
                eventually(cancel.done, 5.0, "the cancel answered")
            result = handle.get_result_async()
            eventually(result.done, 30.0, "the result")
            return result.result(), feedback

        homed, feedback = run(home, Home.Goal(joint=joint))
        assert homed.result.success and homed.result.angle == pytest.approx(0.0, abs=0.2), homed.result.message
        assert feedback and all(f.state for f in feedback)
        moved, feedback = run(move, MoveJoint.Goal(joint=joint, target_deg=40.0, speed_deg_s=90.0))
        assert moved.result.success and moved.result.angle == pytest.approx(40.0, abs=0.3), moved.result.message
        assert len(feedback) >= 3 and feedback[0].remaining_deg > feedback[-1].remaining_deg > -0.5
        canceled, feedback = run(move, MoveJoint.Goal(joint=joint, target_deg=200.0, speed_deg_s=60.0),
                                 cancel_when=lambda: drive.snapshot().angle_deg > 70.0)  # well under way
        assert canceled.status == 5 and not canceled.result.success  # GoalStatus.STATUS_CANCELED
        assert "halted" in canceled.result.message
        state = drive.snapshot()
        assert 45.0 < state.angle_deg < 190.0 and abs(state.velocity_deg_s) < 1.0  # stopped short of 200
        assert state.state is State.OPERATION_ENABLED  # a halt, not a disable
        unknown = move.send_goal_async(MoveJoint.Goal(joint="no_such_wheel", target_deg=1.0))
        eventually(unknown.done, 5.0, "the unknown joint refused")
        assert not unknown.result().accepted
    finally:
        spin.stop(5.0)
        client_node.destroy_node()


def test_a_move_goal_is_checked_whole_before_the_drive_is_touched(graph: Graph) -> None:
    """A move_joint goal with a bad target or speed is refused naming it, and changes nothing on the
    drive (its mode, its profile speed); a goal with speed 0 moves at the configured speed, not at
    the one an earlier goal left in 0x6081."""
    from rclpy.action import ActionClient
    from rovercan_msgs.action import MoveJoint

    joint = "wheel_rear_left"
    drive = graph.driver.drive(joint)
    sim_drive = graph.sim.simulator_for(drive.node_id, "can0")

    def profile_velocity() -> int:
        return int(sim_drive.call(lambda: sim_drive.drive(drive.node_id).store.get(0x6081, 0)))

    client_node = rclpy.create_node("move_check_client", context=graph.context)
    executor = SingleThreadedExecutor(context=graph.context)
    executor.add_node(client_node)
    spin = SpinThread(executor, "test-move-check")
    try:
        move = ActionClient(client_node, MoveJoint, "move_joint")
        assert move.wait_for_server(timeout_sec=5.0)
        assert graph.call(SetMode, f"wheels/{joint}/set_mode", SetMode.Request(mode="profile_velocity")).success
        assert graph.call(Trigger, f"wheels/{joint}/enable").success

        def run(goal: Any) -> Any:
            sent = move.send_goal_async(goal)
            eventually(sent.done, 5.0, "the goal answered")
            result = sent.result().get_result_async()
            eventually(result.done, 30.0, "the result")
            return result.result().result

        mode, speed = drive.snapshot().mode, profile_velocity()
        assert mode == 3  # profile velocity: a goal that switched it to profile position would show
        for goal, says in ((MoveJoint.Goal(joint=joint, target_deg=math.nan), "angle"),
                           (MoveJoint.Goal(joint=joint, target_deg=10.0, speed_deg_s=math.nan), "profile velocity"),
                           (MoveJoint.Goal(joint=joint, target_deg=10.0, speed_deg_s=-5.0), "allowed 0 < speed"),
                           (MoveJoint.Goal(joint=joint, target_deg=10.0, speed_deg_s=1e-30), "velocity resolution")):
            result = run(goal)
            assert not result.success and says in result.message and "Nothing was sent" in result.message, result.message
            assert drive.snapshot().mode == mode and profile_velocity() == speed
        assert run(MoveJoint.Goal(joint=joint, target_deg=10.0, speed_deg_s=30.0)).success
        assert profile_velocity() == drive.cache.scale.magnitude_to_drive(30.0)
        assert run(MoveJoint.Goal(joint=joint, target_deg=0.0, speed_deg_s=0.0)).success
        assert profile_velocity() == drive.cache.scale.magnitude_to_drive(drive.config.profile_velocity_deg_s)
    finally:
        spin.stop(5.0)
        client_node.destroy_node()


def test_a_home_goal_whose_cancel_could_not_quick_stop_says_so(graph: Graph) -> None:
    """A cancelled home_joint goal says "quick-stopped" only when its quick stop was: one that
    failed is the result's message, with what helps (/disarm), and the goal ends once the homing does."""
    from rclpy.action import ActionClient
    from rovercan_msgs.action import Home

    from can_config.errors import DriveStateError

    joint = SLOW_HOMING
    drive = graph.driver.drive(joint)
    runner = graph.sim.simulators["can1"]
    runner.call(lambda: setattr(runner.drive(drive.node_id).params, "index_position_counts", 10**9))  # homes on
    client_node = rclpy.create_node("home_cancel_client", context=graph.context)
    executor = SingleThreadedExecutor(context=graph.context)
    executor.add_node(client_node)
    spin = SpinThread(executor, "test-home-cancel")
    quick_stop = drive.quick_stop
    try:
        home = ActionClient(client_node, Home, "home_joint")
        assert home.wait_for_server(timeout_sec=5.0)
        assert graph.call(Trigger, f"wheels/{joint}/enable").success
        sent = home.send_goal_async(Home.Goal(joint=joint))
        eventually(sent.done, 5.0, "the goal accepted")
        handle = sent.result()
        assert handle.accepted
        eventually(lambda: drive.channel.busy == "home", 10.0, "homing under way")

        tried = threading.Event()

        def refused() -> None:
            tried.set()
            raise DriveStateError(f"{joint}: the quick stop was not confirmed (a test's)", node_id=drive.node_id)

        drive.quick_stop = refused  # type: ignore[method-assign]
        cancel = handle.cancel_goal_async()
        eventually(cancel.done, 5.0, "the cancel answered")
        result = handle.get_result_async()
        eventually(tried.is_set, 10.0, "the cancel's quick stop tried")
        drive.quick_stop = quick_stop  # type: ignore[method-assign]
        assert not result.done()  # the homing goes on: nothing stopped it
        assert graph.call(Trigger, f"wheels/{joint}/quick_stop").success  # what the message says helps
        eventually(result.done, 30.0, "the result once the homing ended")
        message = result.result().result.message
        assert "its quick stop failed" in message and "a test's" in message and "/disarm" in message, message
    finally:
        drive.quick_stop = quick_stop  # type: ignore[method-assign]
        spin.stop(5.0)
        client_node.destroy_node()


def test_a_goals_last_wait_is_not_queued_behind_another_goals_start(graph: Graph) -> None:
    """A joint's goal starts (SDO writes, a mode switch) run one at a time in arrival order; a
    goal's last wait on its drive runs beside them: it ended behind a slow start of the next
    goal (order, not a clock: the wait ends while the start is still held)."""
    from nodes.actions.driver_actions import DriverActionsNode

    actions = next(n for n in graph.assembly.nodes if isinstance(n, DriverActionsNode))
    executor = actions.executor
    assert executor is not None
    held = threading.Event()
    started = threading.Event()

    def slow_start() -> str:
        started.set()
        held.wait(60.0)
        return "started"

    start = executor.create_task(actions._off_executor("wheel_front_left", slow_start))
    wait_for(started.is_set, 10.0, "the start under way on the joint's worker")
    last = executor.create_task(actions._off_executor("wheel_front_left", lambda: "reached", lane="wait"))
    try:
        wait_for(last.done, 10.0, "the last wait, beside the held start")
        assert last.result() == "reached" and not start.done()
    finally:
        held.set()
    wait_for(start.done, 10.0, "the start's end")
    assert start.result() == "started"


def test_a_stop_service_answers_while_a_slow_service_is_still_running(graph: Graph) -> None:
    """/home on a drive that answers SDO in 0.3 s runs for seconds on the services' thread; a
    quick stop of another joint and of the homing joint itself are answered meanwhile (order,
    not a clock: the stop's answer comes while /home has not answered). The landed code ran
    every Trigger service on one executor: /quick_stop waited behind /home."""
    runner = graph.sim.simulators["can0"]
    homing, other = "wheel_front_left", "wheel_middle_left"
    node_id = graph.driver.drive(homing).node_id
    runner.call(lambda: setattr(runner.drive(node_id).faults, "sdo_delay_s", 0.3))
    for joint in (homing, other):
        assert graph.call(Trigger, f"wheels/{joint}/enable").success
    home_client = graph.probe.create_client(Trigger, f"wheels/{homing}/home")
    assert home_client.wait_for_service(timeout_sec=5.0)
    home = home_client.call_async(Trigger.Request())
    wait_for(lambda: graph.driver.drive(homing).channel.busy == "home", 10.0, "homing under way")
    stopped = graph.call(Trigger, f"wheels/{other}/quick_stop")
    assert stopped.success, stopped.message
    assert not home.done() and graph.driver.drive(homing).channel.busy == "home"  # answered while /home runs
    stopped = graph.call(Trigger, f"wheels/{homing}/quick_stop")
    assert stopped.success, stopped.message
    wait_for(home.done, 15.0, "/home answered")
    assert not home.result().success and "interrupted by quick stop" in home.result().message
    assert graph.driver.drive(homing).cache.state.name != "OPERATION_ENABLED"


def test_one_joints_services_and_arm_answer_while_another_joint_homes(graph: Graph) -> None:
    """A joint homing slowly (until stopped) holds no other joint's services: another joint's
    /enable and the rover's /arm answer while it runs (order, not a clock: each answer arrives
    while /home has not answered and the joint is still busy homing). The landed code ran every
    service that waits on one thread: a second joint's /enable answered after a 10 s /home."""
    homing, other = SLOW_HOMING, "wheel_front_right"  # both on can1
    drive = graph.driver.drive(homing)
    runner = graph.sim.simulators["can1"]
    runner.call(lambda: setattr(runner.drive(drive.node_id).params, "index_position_counts", 10**9))
    assert graph.call(Trigger, f"wheels/{homing}/enable").success
    home_client = graph.probe.create_client(Trigger, f"wheels/{homing}/home")
    assert home_client.wait_for_service(timeout_sec=5.0)
    home = home_client.call_async(Trigger.Request())
    wait_for(lambda: drive.channel.busy == "home", 10.0, "homing under way")
    enabled = graph.call(Trigger, f"wheels/{other}/enable")
    assert enabled.success and "OPERATION_ENABLED" in enabled.message, enabled.message
    assert not home.done() and drive.channel.busy == "home"  # answered while the home runs
    armed = graph.call(Trigger, "/arm")
    assert not home.done() and drive.channel.busy == "home"
    # every other wheel enabled; the homing one refused at once, named, not waited for
    assert not armed.success and f"{homing}: enable refused: the drive is busy with home" in armed.message, armed.message
    assert all(graph.driver.drive(w).cache.state is State.OPERATION_ENABLED for w in WHEELS if w != homing)
    disarmed = graph.call(Trigger, "/disarm")  # the driver's safe stop: the homing ends too
    assert disarmed.success, disarmed.message
    wait_for(home.done, 15.0, "/home answered")
    assert not home.result().success
    # quick stop, then disable voltage (not shutdown): no drive is left with voltage
    assert all(graph.driver.drive(w).cache.state is State.SWITCH_ON_DISABLED for w in WHEELS)


def test_a_parameter_read_at_start_refuses_a_set_and_a_rate_takes_one(graph: Graph) -> None:
    """`ros2 param set /rovercan_driver config /etc/shadow` was accepted and silently ignored: now
    refused, saying why; the diagnostics rate takes effect; the state rate is refused while the
    drive system's control loop runs on its timer."""
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.srv import DescribeParameters, SetParameters
    from rclpy.parameter import Parameter as RclpyParameter

    def set_one(name: str, value: Any) -> Any:
        msg: ParameterMsg = RclpyParameter(name, value=value).to_parameter_msg()
        reply = graph.call(SetParameters, "/rovercan_driver/set_parameters", SetParameters.Request(parameters=[msg]))
        return reply.results[0]

    # config, executor and realtime_priority: the entry point's (tests/test_params_file.py)
    for name, value in (("default_joint", "wheel_rear_left"), ("arm", True), ("drive_system", False)):
        result = set_one(name, value)
        assert not result.successful and "read-only" in result.reason, (name, result)
        assert graph.driver_node.get_parameter(name).value != value
    described = graph.call(DescribeParameters, "/rovercan_driver/describe_parameters",
                           DescribeParameters.Request(names=["default_joint"])).descriptors[0]
    assert described.read_only and "restart the node" in described.additional_constraints
    result = set_one("diagnostics_rate_hz", 2.0)
    assert result.successful, result.reason
    assert graph.driver_node._diag_timer.timer_period_ns == 500_000_000
    result = set_one("state_rate_hz", 20.0)
    assert not result.successful and "control loop" in result.reason, result


def test_disarm_with_the_bus_killed_names_each_wheel_lost_not_safe(graph: Graph) -> None:
    """Both buses' server killed with the wheels armed: /disarm can send and confirm nothing, and says
    so, each wheel named lost (its last statusword no news of it); it answered success, every wheel
    "OPERATION_ENABLED" from before the loss, and deactivate said them quick-stopped."""
    from std_srvs.srv import Trigger

    armed = graph.call(Trigger, "/arm")
    assert armed.success, armed.message
    graph.sim.close()
    wait_for(lambda: all(graph.driver.drive(w).cache.lost for w in WHEELS), HANG_S, "every wheel lost")
    disarmed = graph.call(Trigger, "/disarm")
    assert not disarmed.success, disarmed.message
    for wheel in WHEELS:
        assert f"{wheel}: lost and not configured (its bus gone" in disarmed.message, disarmed.message
        assert "no stop could be sent or confirmed" in disarmed.message, disarmed.message
        assert f"{wheel} LOST (last heard" in disarmed.message, disarmed.message
    report = graph.driver.stop_report()
    assert len(report.lost) == len(WHEELS) and report.lines == report.lost
