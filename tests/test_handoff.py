"""A command that must wait for its drive holds no other joint's commands (nodes/joints/handoff.py).

The hot executor's one thread carries every joint's commands. A joint's first streamed
set-point switches its drive's mode by SDO; done on that thread, it held a 500 Hz arm's stream
(the twelve-drive run, docs/performance.md). Here the switch is held inside the driver (a hook
at its critical point, released by the test), and the other joint's stream must reach its
drive meanwhile: a verdict on what arrived, with no clock (hang bounds only)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import canopen
import pytest

from can_config import RoverConfig, parse_config
from can_config.config import GENERIC_EDS
from can_config.errors import CommandRejected, CommandWouldWait, DriveTimeoutError
from can_config.objects import OD, OperationMode
from motor_driver import MotorDriver
from nodes.joints.handoff import Handoff
from virtual_can import SimService

from .conftest import (
    HAVE_ROS,
    IN_PROCESS_HEARTBEAT_TIMEOUT_MS,
    IN_PROCESS_HOST_TIMEOUT_MS,
    REPO,
    in_process_stale_after_syncs,
    make_config,
    requires_ros,
    stop_reason,
    wait_for,
)

if HAVE_ROS:
    import rclpy
    from rclpy.parameter import Parameter
    from std_msgs.msg import Float32

    from nodes.assembly import Assembly
    from nodes.process.qos import COMMAND_QOS
    from nodes.process.spinning import SpinThread, make_executor

SWITCH_POINT = "mode switch: 0x6060 written"
JOINTS = ("joint1", "joint2")


class Arm:
    """Two joints streaming positions (``position_mode: cyclic``) on a 2 ms SYNC (500 Hz), the
    driver assembled as rover_driver assembles it (armed), a probe publishing their degree_cmd."""

    def __init__(self, sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> None:
        drives = [{"name": j, "node_id": i, "position_mode": "cyclic", "max_velocity_deg_s": 720, "gear_ratio": 50.0,
                   "host_timeout_ms": IN_PROCESS_HOST_TIMEOUT_MS, "heartbeat_timeout_ms": IN_PROCESS_HEARTBEAT_TIMEOUT_MS,
                   "stale_after_syncs": in_process_stale_after_syncs(0.002)}
                  for i, j in enumerate(JOINTS, start=1)]
        config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                          "kwargs": {"host": "127.0.0.1", "port": 1}, "sync_period_ms": 2}],
                               "drives": drives}, source=REPO / "tests" / "generated.yaml")
        self.sim, config = sim_factory(config)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.hot = make_executor("events", self.context)
        self.assembly = Assembly(MotorDriver(config), self.hot, context=self.context,
                                 overrides=[Parameter("arm", value=True)])
        self.node = self.assembly.build()
        self.probe = rclpy.create_node("probe", context=self.context)
        self.pubs = {j: self.probe.create_publisher(Float32, f"{j}/degree_cmd", COMMAND_QOS) for j in JOINTS}
        self.hot.add_node(self.probe)
        self.assembly.start()
        self.spin = SpinThread(self.hot, "test-hot")
        self.driver = self.assembly.driver
        for j in JOINTS:
            wait_for(self._ready(j), 30.0, f"{j} armed and its degree_cmd matched")

    def _ready(self, joint: str) -> Callable[[], bool]:
        drive, pub = self.driver.drive(joint), self.pubs[joint]
        return lambda: drive.snapshot().verdict.usable and pub.get_subscription_count() > 0

    def close(self) -> None:
        self.spin.stop(5.0)
        self.assembly.close()
        self.probe.destroy_node()
        rclpy.shutdown(context=self.context)

    def publish(self, joint: str, deg: float) -> None:
        self.pubs[joint].publish(Float32(data=deg))

    def on_the_drive(self, joint: str) -> tuple[int, float]:
        """The simulated drive's mode and its position target in degrees: what reached it."""
        node_id = self.driver.drive(joint).node_id
        runner = self.sim.simulator_for(node_id)
        sim_drive = runner.drive(node_id)
        mode = int(runner.call(lambda: sim_drive.mode))  # type: ignore[call-overload]
        target = float(runner.call(lambda: sim_drive.store.get(OD.TARGET_POSITION, 0)))  # type: ignore[arg-type]
        return mode, self.driver.drive(joint).cache.scale.counts_to_deg(target)

    def holds(self, joint: str, deg: float) -> bool:
        mode, target = self.on_the_drive(joint)
        return mode == OperationMode.CYCLIC_SYNC_POSITION and abs(target - deg) < 0.005


@pytest.fixture
def arm(sim_factory: Callable[[RoverConfig], tuple[SimService, RoverConfig]]) -> Iterator[Arm]:
    rig = Arm(sim_factory)
    yield rig
    rig.close()


@requires_ros
def test_a_joints_mode_switch_holds_no_other_joints_stream(arm: Arm) -> None:
    """joint1 streams at 500 Hz; joint2's first set-point switches its drive to CSP, held at the
    switch's critical point: joint1's set-points reach its drive all the while; joint2's switch
    ran on a worker, and once let go joint2 takes its newest command."""
    for k in range(1, 6):
        arm.publish("joint1", 0.02 * k)
    wait_for(lambda: arm.holds("joint1", 0.10), 30.0, "joint1 streaming (CSP, at 0.10 deg)", lambda: str(arm.on_the_drive("joint1")))
    entered, release = threading.Event(), threading.Event()
    switched_on: list[str] = []

    def hold(point: str) -> None:
        if point == SWITCH_POINT:
            switched_on.append(threading.current_thread().name)
            entered.set()
            release.wait(60.0)  # a bound for a hang: the test releases it

    joint2 = arm.driver.drive("joint2")
    joint2.channel.set_hook(hold)
    try:
        arm.publish("joint2", 0.05)
        wait_for(entered.is_set, 30.0, "joint2's switch to CSP under way")
        last = 0.10
        for k in range(6, 56):  # 50 set-points, 2 ms apart on the wire's time
            last = 0.02 * k
            arm.publish("joint1", last)
            time.sleep(0.002)  # paces the stream (500 Hz); no verdict on it
        wait_for(lambda: arm.holds("joint1", last), 30.0, f"joint1's stream at {last:.2f} deg while joint2's switch waits",
                 lambda: str(arm.on_the_drive("joint1")))
        arm.publish("joint2", 0.1)  # newer than the one with the worker: sent after it
        wait_for(lambda: arm.node.handoff.waiting("joint2") == pytest.approx(0.1), 30.0, "joint2's newer command waiting")
        assert abs(arm.on_the_drive("joint2")[1] - 0.05) > 0.005, "joint2's set-point went out before its switch ended"
    finally:
        release.set()
        joint2.channel.set_hook(None)
    wait_for(lambda: arm.holds("joint2", 0.1), 30.0, "joint2 at its newest command, 0.1 deg, after the switch",
             lambda: str(arm.on_the_drive("joint2")))
    assert switched_on and all(name.startswith("rovercan-handoff") for name in switched_on), switched_on
    for joint in JOINTS:
        assert arm.node.refusals.take(joint) == (0, ""), joint
    wait_for(lambda: not arm.node.handoff.busy("joint2"), 30.0, "the worker done with joint2")


@requires_ros
def test_a_refusal_on_the_worker_is_said_like_one_on_the_hot_thread(arm: Arm) -> None:
    """joint2's switch fails on the worker (0x6061 never shows CSP): the refusal is counted and
    said for joint2, nothing moved it, and its next command is taken again."""
    joint2 = arm.driver.drive("joint2")

    def fail(point: str) -> None:
        if point == SWITCH_POINT:
            raise DriveTimeoutError("0x6061 never showed the mode (the test's)", node_id=2)

    joint2.channel.set_hook(fail)
    try:
        arm.publish("joint2", 0.05)
        wait_for(lambda: arm.node.refusals.count.get("joint2", 0) >= 1, 30.0, "joint2's refusal counted")
    finally:
        joint2.channel.set_hook(None)
    count, why = arm.node.refusals.take("joint2")
    assert count == 1 and why.startswith("degree command 0.05") and "0x6061 never showed the mode" in why, why
    wait_for(lambda: not arm.node.handoff.busy("joint2"), 30.0, "the worker done with joint2")
    arm.publish("joint2", 0.05)  # the drive shows CSP by now (0x6060 was written): at once
    wait_for(lambda: arm.holds("joint2", 0.05), 30.0, "joint2 at 0.05 deg", lambda: str(arm.on_the_drive("joint2")))


# ---------------------------------------------------------------------- the core's at_once
AT_ONCE: dict[str, tuple[Callable[[Any, bool], object], OperationMode]] = {
    "set_velocity": (lambda d, at_once: d.set_velocity(10.0, at_once=at_once), OperationMode.PROFILE_VELOCITY),
    "command_velocity (profile)": (lambda d, at_once: d.command_velocity(10.0, at_once=at_once),
                                   OperationMode.PROFILE_VELOCITY),
    "set_torque": (lambda d, at_once: d.set_torque(0.05, at_once=at_once), OperationMode.PROFILE_TORQUE),
    "command_torque (profile)": (lambda d, at_once: d.command_torque(0.05, at_once=at_once), OperationMode.PROFILE_TORQUE),
    "stream_velocity": (lambda d, at_once: d.stream_velocity(1.0, at_once=at_once), OperationMode.CYCLIC_SYNC_VELOCITY),
    "stream_torque": (lambda d, at_once: d.stream_torque(0.05, at_once=at_once), OperationMode.CYCLIC_SYNC_TORQUE),
    "stream_position": (lambda d, at_once: d.stream_position(0.5, at_once=at_once), OperationMode.CYCLIC_SYNC_POSITION),
    "command_position (profile)": (lambda d, at_once: d.command_position(5.0, at_once=at_once),
                                   OperationMode.PROFILE_POSITION),
}
#: what reached the simulated drive: its mode, 0x6060 and every target
ON_THE_DRIVE = (OD.MODES_OF_OPERATION, OD.TARGET_POSITION, OD.TARGET_VELOCITY, OD.TARGET_TORQUE)


@pytest.mark.parametrize("kind", sorted(AT_ONCE))
def test_at_once_a_command_that_needs_a_mode_switch_is_refused_with_nothing_sent(
        kind: str, driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    """``at_once=True``: a command whose mode the drive is not in raises CommandWouldWait, and
    neither a mode nor a target reached the drive; the same command without it switches and
    goes, and then goes at once too."""
    sim, driver = driver_factory(make_config(1, gear_ratio=50.0, counts_per_rev=4096))
    drive = driver.drive("joint1")
    drive.enable()
    command, mode = AT_ONCE[kind]
    if mode == OperationMode.PROFILE_POSITION:
        drive.set_velocity(0.0)  # in profile velocity: a position move would switch back
    runner = sim.simulator_for(1)
    sim_drive = runner.drive(1)

    def on_the_drive() -> object:
        drive.sdo_read(OD.STATUSWORD)  # a round trip: whatever the driver sent before has reached the drive
        return runner.call(lambda: (sim_drive.mode, *(sim_drive.store.get(i, 0) for i in ON_THE_DRIVE)))

    before = on_the_drive()
    needs = "a streamed position mode" if kind == "stream_position" else mode.name
    drive.power.forget_modes()  # 0x6502 unknown (as after a boot that failed): at once, not asked either
    with pytest.raises(CommandWouldWait, match=rf"joint1: .* needs a switch to {needs} first, which waits for the drive"):
        command(drive, True)
    assert drive.power._supported_modes is None, "0x6502 was read by SDO on the caller's thread"
    assert on_the_drive() == before and drive.cache.received.mode != mode
    command(drive, False)
    assert drive.cache.received.mode == mode
    command(drive, True)  # in its mode now: at once


def test_at_once_a_target_the_drive_takes_only_by_sdo_is_refused_with_nothing_sent(
        tmp_path: Path, driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    """A drive whose 0x60FF (target velocity) cannot be PDO-mapped: in profile velocity already,
    a velocity command at once still waits (its SDO write) and is refused, nothing sent; without
    ``at_once`` it goes by SDO."""
    od = canopen.import_od(str(GENERIC_EDS), 1)
    od[OD.TARGET_VELOCITY].pdo_mappable = False
    eds = tmp_path / "velocity_by_sdo.eds"
    canopen.export_od(od, str(eds), doc_type="eds")
    sim, driver = driver_factory(make_config(1, eds=str(eds), gear_ratio=50.0, counts_per_rev=4096))
    drive = driver.drive("joint1")
    assert OD.TARGET_VELOCITY in drive.plan.sdo_only
    drive.enable()
    drive.set_velocity(0.0)  # in profile velocity now
    runner, node_id = sim.simulator_for(1), 1
    sim_drive = runner.drive(node_id)

    def target() -> object:
        drive.sdo_read(OD.STATUSWORD)  # a round trip: whatever the driver sent before has reached the drive
        return runner.call(lambda: sim_drive.store.get(OD.TARGET_VELOCITY, 0))

    before = target()
    with pytest.raises(CommandWouldWait, match=r"joint1: velocity command needs its target written by SDO"):
        drive.set_velocity(20.0, at_once=True)
    assert target() == before
    drive.set_velocity(20.0)
    assert target() != before


# ---------------------------------------------------------------------- the handoff alone
class Drive:
    """Stands in for a drive's command: it would wait until ``ready``; records what it sent, where."""

    def __init__(self) -> None:
        self.ready = False
        self.sent: list[tuple[float, bool]] = []
        self.gate = threading.Event()

    def command(self, value: float, at_once: bool = False) -> None:
        if value < 0:
            raise CommandRejected(f"{value} is below 0")
        if not self.ready:
            if at_once:
                raise CommandWouldWait("a switch first")
            self.gate.wait(30.0)
            self.ready = True
        self.sent.append((value, at_once))


def test_the_handoff_keeps_a_joints_order_and_only_its_newest_command() -> None:
    failures: list[str] = []
    handoff = Handoff(["a", "b"])
    a, b = Drive(), Drive()
    b.ready = True

    def failed(joint: str, what: str, value: float, err: Exception) -> None:
        failures.append(f"{joint} {what.format(value)}: {err}")

    try:
        assert not handoff.send("a", a.command, 1.0, "{!r}", failed)  # would wait: to the worker (False)
        for value in (2.0, 3.0, 4.0):
            assert not handoff.send("a", a.command, value, "{!r}", failed)  # behind it: only the newest kept
        assert handoff.busy("a") and handoff.waiting("a") == 4.0
        assert handoff.send("b", b.command, 5.0, "{!r}", failed)  # another joint: at once (True), not behind a
        assert b.sent == [(5.0, True)] and a.sent == []
        with pytest.raises(CommandRejected, match="below 0"):
            handoff.send("b", b.command, -1.0, "{!r}", failed)  # a refusal at once raises here
        a.gate.set()
        wait_for(lambda: not handoff.busy("a"), 30.0, "a's worker done")
        assert a.sent == [(1.0, False), (4.0, False)]
        assert handoff.send("a", a.command, 6.0, "{!r}", failed)  # ready now: at once again
        assert a.sent[-1] == (6.0, True)
        a.ready = False
        a.gate.clear()
        handoff.send("a", a.command, 7.0, "{!r}", failed)
        handoff.send("a", a.command, -2.0, "{!r}", failed)  # refused behind it, on the worker
        a.gate.set()
        wait_for(lambda: not handoff.busy("a"), 30.0, "a's worker done")
        assert failures == ["a -2.0: -2.0 is below 0"]
    finally:
        handoff.close()
    a.ready = False
    with pytest.raises(CommandRejected, match="shutting down"):
        handoff.send("a", a.command, 9.0, "{!r}", failed)  # closed: refused, not handed to a worker
    assert not handoff.busy("a") and 9.0 not in [value for value, _ in a.sent]


@requires_ros
def test_a_wheels_velocity_refused_on_the_worker_stops_every_wheel() -> None:
    """The drive system's first /cmd_vel switches every wheel to profile velocity on the
    handoff's workers; one wheel's switch fails there: the next tick stops every wheel and says
    which wheel refused, as a refusal on the hot thread did (a turn by some wheels is worse than none)."""
    from .test_odom_truth import LEFT, RIGHT, Rover

    rover = Rover("stop")
    try:
        rover.arm()
        wheel = rover.driver.drive("wheel_rear_right")

        def fail(point: str) -> None:
            if point == SWITCH_POINT:
                raise DriveTimeoutError("0x6061 never showed the mode (the test's)", node_id=wheel.node_id)

        wheel.channel.set_hook(fail)
        try:
            rover.drive_until(0.3, 0.0, lambda: rover.said("wheel wheel_rear_right refused"),
                              "the drive system stopped, naming the wheel refused on the worker")
        finally:
            wheel.channel.set_hook(None)
        # every wheel stops on the simulated drives (no /cmd_vel is sent after the halt)
        wait_for(lambda: rover.sim_stopped(LEFT + RIGHT), 30.0, "every simulated wheel stopped",
                 lambda: str({n: rover.sim_speed_rad_s(n) for n in LEFT + RIGHT}))
        said = [st for array in rover.diags for st in array.status if st.name == "rovercan: drive_system"
                and "wheel wheel_rear_right refused" in st.message]
        reason = stop_reason(said[0], "; every wheel stopped")
        assert reason is not None and reason.startswith("stopped: /cmd_vel not applied: wheel wheel_rear_right refused") \
            and "0x6061 never showed the mode (the test's)" in reason, [st.message for st in said]
    finally:
        rover.close()
