"""The verdict on a drive of the simulator, as the driver's consumers read it: a set-point on data
its drive stopped sending is refused with its age and cause, a drive whose host watch stopped it
is named so (by the refusal and /diagnostics' grading), a drive that re-booted and is not yet
configured again is not OK. Every wait is on a condition; none decides by the clock."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import pytest

from can_config import RoverConfig
from can_config.errors import DriveStateError
from motor_driver import MotorDriver, State
from motor_driver.diagnostics.health import ERROR, OK, WARN, drive_health
from motor_driver.drive.verdict import Condition
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import driver_node_spinning, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def test_a_set_point_on_stale_data_is_refused_with_its_age(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(10.0)
    apply_action(sim, {"action": "tpdos", "node": 1, "on": False})  # heartbeats go on: stale, not lost
    wait_for(drive.cache.data_stale, 10.0, "its data stale")
    with pytest.raises(DriveStateError, match=r"^joint1: no data for \d+ ms \(bus or drive stalled\)"):
        drive.set_velocity(5.0)
    with pytest.raises(DriveStateError, match=r"^joint1: no data for \d+ ms \(bus or drive stalled\)"):
        drive.command_velocity(5.0, at_once=True)  # a per-joint topic's way in
    drive.set_velocity(0.0)  # a stop is taken on late data all the same
    assert drive.snapshot().verdict.condition is Condition.LATE
    apply_action(sim, {"action": "tpdos", "node": 1, "on": True})
    wait_for(lambda: not drive.cache.data_stale(), 10.0, "its data fresh again")
    drive.set_velocity(5.0)  # taken again


def test_a_drive_whose_position_tpdo_alone_stops_is_late_naming_that_tpdo(driver_factory: DriverFactory) -> None:
    """Its TPDO with the position (0x281: 0x6064, 0x606C) stops while its statusword's keep coming
    (a mapping lost, a PDO dropped): its position is old however fresh the others are. The data's
    age was the newest TPDO's: the drive stayed usable, /joint_states republished the frozen
    position as measured and the odometry waited for it for ever, "trusted". Now it is late,
    naming the TPDO; set-points are refused; healed, it is usable again."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(10.0)
    apply_action(sim, {"action": "tpdo_lost", "node": 1, "cob_id": 0x281})
    wait_for(lambda: drive.snapshot().verdict.condition is Condition.LATE, 10.0, "the drive late")
    state = drive.snapshot()
    assert state.verdict.cause.startswith("TPDO 0x281 (0x6064, 0x606C) not heard for"), state.verdict
    assert "while its other PDOs are" in state.verdict.cause
    assert drive.cache.received.rx_monotonic > drive.cache.received.position_rx  # its others still heard
    with pytest.raises(DriveStateError, match=r"^joint1: TPDO 0x281 \(0x6064, 0x606C\) not heard for \d+ ms"):
        drive.set_velocity(5.0)
    drive.set_velocity(0.0)  # a stop is taken on late data all the same
    apply_action(sim, {"action": "tpdo_lost", "node": 1, "cob_id": 0x281, "on": False})
    wait_for(lambda: drive.snapshot().verdict.usable, 10.0, "usable again")
    drive.set_velocity(5.0)  # taken again


def test_a_zero_on_late_data_is_refused_once_the_drive_stopped_itself(driver_factory: DriverFactory) -> None:
    """A zero is taken on late data only while that data said Operation Enabled: a drive that
    stopped itself (its host watch: Quick Stop Active) and then fell silent is sent no Enable
    Operation (on a quick-stop option code 5-7 that is transition 16, back to Operation Enabled,
    and the next /cmd_vel would drive a wheel that stopped itself, without /arm)."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(10.0)
    runner = sim.simulator_for(1)
    wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), 30.0, "its host watch armed")
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})  # its consumer trips: it stops itself
    wait_for(lambda: drive.cache.state.name != "OPERATION_ENABLED", 30.0, "the drive stopped by itself")
    apply_action(sim, {"action": "tpdos", "node": 1, "on": False})  # then its data goes late
    wait_for(drive.cache.data_stale, 10.0, "its data stale")
    assert drive.snapshot().verdict.condition is Condition.LATE
    with pytest.raises(DriveStateError, match=r"^joint1: no data for \d+ ms .*a zero is taken only while the drive"
                                              r" last said OPERATION_ENABLED"):
        drive.set_velocity(0.0)


def test_a_host_watch_stop_is_named_by_the_refusal_and_diagnostics(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    runner = sim.simulator_for(1)
    wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), 30.0, "its host watch armed")
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})  # its consumer trips: it stops itself, EMCY 0x8130
    wait_for(lambda: drive.cache.state.name != "OPERATION_ENABLED" and drive.cache.last_emcy is not None, 30.0,
             "the drive stopped by itself")
    with pytest.raises(DriveStateError, match=r"^joint1: stopped itself: host heartbeat lost at [0-9:.]+ .*; /arm"
                                              r" enables it again"):
        drive.set_velocity(5.0)
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s)
    assert health.level == ERROR and health.message.startswith("stopped itself: host heartbeat lost at"), health


def test_a_held_drive_still_enabled_is_not_ok(driver_factory: DriverFactory) -> None:
    """Motion held with the drive still Operation Enabled (a deactivate whose stop was not confirmed
    holds motion and fails): WARN naming it, where it said OK "ready: motion held"; once stopped, OK."""
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    driver.hold_motion("a test's hold: deactivate did not confirm every stop")
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s)
    assert health.level == WARN, health
    assert health.message.startswith("motion held, yet still OPERATION_ENABLED (its stop not confirmed)"), health
    assert "deactivate did not confirm every stop" in health.message, health
    assert driver.safe_stop() == []
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s)
    assert health.level == OK and health.message.startswith("ready: motion held"), health


@pytest.mark.parametrize(("state", "level"), [(State.OPERATION_ENABLED, WARN), (State.QUICK_STOP_ACTIVE, WARN),
                                               (State.SWITCH_ON_DISABLED, OK), (State.READY_TO_SWITCH_ON, OK)])
def test_a_held_drive_is_graded_by_whether_it_still_holds_its_motor(state: State, level: int) -> None:
    """Under a hold, a drive whose drive function is still on (Operation Enabled, or Quick Stop Active
    after a quick stop whose disable failed) is WARN; one whose voltage is off, OK."""
    import dataclasses

    from motor_driver.drive.verdict import judge

    from .drive_states import drive_state

    made = drive_state(name="joint1", node_id=1, angle_deg=0.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0x0007,
                       state=state, mode=8, nmt="OPERATIONAL", error_code=0, error_text="", stamp=0.0,
                       heartbeat_age_s=0.0, target_reached=False, data_age_s=0.0, enabled=True)
    facts = made.facts._replace(held="a test's hold")
    held = dataclasses.replace(made, judged=(facts, judge(facts)))
    assert held.verdict.condition is Condition.HELD
    health = drive_health(held, heartbeat_period_s=0.1)
    assert health.level == level, health
    assert (f"still {state.name}" in health.message) == (level == WARN), health


def test_a_drive_that_went_pre_operational_on_losing_the_host_is_not_blamed_on_another_master(
        driver_factory: DriverFactory) -> None:
    """A drive whose 0x1029:1 is 0 (the Faulhaber's and ros2_canopen's default) goes PRE-OPERATIONAL
    on its heartbeat consumer's timeout, with EMCY 0x8130: its own doing on this host's silence,
    not another master's NMT command. It is configured again, left disabled, and enabled again
    once the host is heard; never marked "another master is on the bus" (which told the user to
    stop a bench tool that does not exist)."""
    from can_config.objects import NmtState

    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    runner = sim.simulator_for(1)
    runner.call(lambda: runner.drive(1).store.values.__setitem__((0x1029, 1), 0))
    drive.enable()
    wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), 30.0, "its host watch armed")
    boots = drive.boot.boot_count
    seen: list[Condition] = []
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})  # it hears this host no more
    wait_for(lambda: seen.append(drive.snapshot().verdict.condition) or
             runner.call(lambda: runner.drive(1).nmt) == NmtState.PRE_OPERATIONAL, 30.0, "the drive PRE-OPERATIONAL")
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1, "on": False})
    wait_for(lambda: seen.append(drive.snapshot().verdict.condition) or
             (drive.boot.boot_count > boots and drive.cache.booted), 30.0, "configured again")
    assert Condition.ANOTHER_MASTER not in seen, seen
    assert driver.supervisor.records["joint1"].foreign_master == ""
    drive.enable()
    assert drive.cache.state is State.OPERATION_ENABLED


def test_a_rebooted_drive_not_yet_configured_is_not_ok(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    apply_action(sim, {"action": "sdo", "node": 1, "abort": 0x08000000})  # its re-configuration fails
    apply_action(sim, {"action": "power_cycle", "node": 1, "off_s": 0.2})
    wait_for(lambda: drive.cache.reset_since_operational() and not drive.cache.booted, 30.0, "its boot-up heard")
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s)
    assert health.level != OK, health  # it said OK "ready (OPERATION_ENABLED)": its last TPDO's word
    assert drive.snapshot().verdict.condition in (Condition.REBOOTING, Condition.NOT_CONFIGURED)
    assert "re-booting" in health.message or "not configured" in health.message, health


@pytest.mark.ros
def test_a_per_joint_command_on_stale_data_is_refused_and_said(driver_factory: DriverFactory) -> None:
    """The per-joint velocity topic, the driver node between: the refusal reaches /diagnostics with
    its cause, and MotorState carries no old values as news."""
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from rovercan_msgs.msg import MotorState
    from std_msgs.msg import Float32

    from nodes.process.qos import COMMAND_QOS, DIAGNOSTICS_QOS, STATE_QOS

    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(0.0)
    with driver_node_spinning(driver) as probe:
        diags: list[DiagnosticArray] = []
        states: list[MotorState] = []
        probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, DIAGNOSTICS_QOS)
        probe.create_subscription(MotorState, f"{drive.config.ros_prefix}/motor_state", states.append, STATE_QOS)
        pub = probe.create_publisher(Float32, f"{drive.config.ros_prefix}/velocity_cmd", COMMAND_QOS)
        apply_action(sim, {"action": "tpdos", "node": 1, "on": False})
        wait_for(drive.cache.data_stale, 10.0, "its data stale")

        def refusal() -> str:
            pub.publish(Float32(data=5.0))
            for array in list(diags):
                for st in array.status:
                    values = {kv.key: kv.value for kv in st.values}
                    if st.name == "rovercan: joint1" and "no data for" in values.get("last_refusal", ""):
                        return values["last_refusal"]
            return ""

        wait_for(lambda: bool(refusal()), 30.0, "the refusal on /diagnostics")
        assert re.search(r"joint1: no data for \d+ ms \(bus or drive stalled\)", refusal())
        wait_for(lambda: bool(states) and states[-1].stale, 30.0, "a stale MotorState")
        assert math.isnan(states[-1].velocity) and not states[-1].enabled
        apply_action(sim, {"action": "tpdos", "node": 1, "on": True})


def test_an_old_or_used_host_loss_emcy_explains_no_later_nmt_change() -> None:
    """The drive's EMCY 0x8130 explains one NMT change that comes with it, not one hours later (a
    drive that stopped itself and stayed OPERATIONAL, re-armed; then another master's NMT command),
    nor a second one: each of those stays another master's evidence."""
    from types import SimpleNamespace

    from motor_driver.drive.ledger import DriveRecord
    from motor_driver.runtime.supervisor import HOST_LOSS_NMT_S, Supervisor

    record = DriveRecord()
    cache = SimpleNamespace(host_loss_emcys=1, host_loss_at=100.0)
    drive = SimpleNamespace(cache=cache, config=SimpleNamespace(heartbeat_period_s=0.1))
    assert not Supervisor._own_comm_error(drive, record, 100.0 + HOST_LOSS_NMT_S + 0.01)  # type: ignore[arg-type]
    assert Supervisor._own_comm_error(drive, record, 100.2)  # type: ignore[arg-type]
    assert not Supervisor._own_comm_error(drive, record, 100.3)  # type: ignore[arg-type]  # used
    record.host_loss_emcys_spent = 0
    cache.host_loss_emcys = 0  # none since the boot
    assert not Supervisor._own_comm_error(drive, record, 100.2)  # type: ignore[arg-type]
