"""Cyclic synchronous velocity (CSV) and torque (CST): streamed one value per SYNC by the
driver, followed by the simulated drive, refused on a drive whose 0x6502 lacks them, stopped by
the watchdog when the stream stops, and used by /joint_commands where the config says so."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from can_config import RoverConfig, parse_config
from can_config.config import GENERIC_EDS
from can_config.errors import CommandRejected
from can_config.objects import OperationMode
from motor_driver import MotorDriver
from motor_driver.drive import Drive
from virtual_can.service import SimService

from .conftest import (
    HAVE_ROS,
    IN_PROCESS_HOST_TIMEOUT_MS,
    REPO,
    TORQUE_LIMIT_NM,
    TORQUE_REFUSAL,
    drain,
    driver_node_spinning,
    make_config,
    requires_ros,
    wait_for,
)

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
CYCLIC = {"velocity_mode": "cyclic", "torque_mode": "cyclic", "position_mode": "cyclic"}


def stream(fn: Callable[[float], None], values: list[float], period_s: float) -> None:
    for value in values:
        fn(value)
        time.sleep(period_s)


def stream_until(fn: Callable[[float], None], value: float, period_s: float, done: Callable[[], bool], what: str,
                 most: int = 500) -> None:
    """``value`` streamed once per period until ``done()``: a sample read once after a fixed count
    may predate the stream on a starved machine (a torque of NaN: no torque TPDO applied yet)."""
    for _ in range(most):
        fn(value)
        time.sleep(period_s)
        if done():
            return
    raise AssertionError(f"{what} not seen after {most} set-points of {value}")


def test_csv_follows_the_stream_then_the_watchdog_stops_it(
        driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(make_config(1, gear_ratio=10.0, counts_per_rev=4096, watchdog_ms=1000))
    drive = driver.drive("joint1")
    drive.enable()
    period = drive.cache.sync_period_s
    drive.stream_velocity(5.0)  # switches to CSV (SDO) once
    listener = listener_factory(sim)
    drain(listener, 0.02)
    ramp = [10.0 * i for i in range(1, 19)]  # 10 deg/s per SYNC: 1000 deg/s^2 up to 180 deg/s
    stream(drive.stream_velocity, ramp, period)
    stream_until(drive.stream_velocity, 180.0, period, lambda: drive.snapshot().velocity_deg_s == pytest.approx(180.0, rel=0.03),
                 "180 deg/s")
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_VELOCITY
    frames = drain(listener, 0.05)
    assert not [m for m in frames if m.arbitration_id == 0x601]  # set-points by RPDO, no SDO
    # the stream stops: the watchdog (1 s: a loaded machine held this test's thread for 300 ms
    # mid-stream, and a 300 ms watchdog stopped it there too, rightly) sends zero velocity, once
    stops = drive.limits.watchdog_stops
    wait_for(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, 10.0, "the watchdog's stop")  # how soon: benchmarks
    # once: the supervisor (the watchdog's looker) shown to have looked again and again since,
    # six host heartbeats of its own, not a span of the clock in which a held one looks at nothing
    handle = driver.buses["can0"]
    beats = handle.beats_sent()
    wait_for(lambda: handle.beats_sent() >= beats + 6, 30.0, "six supervisor periods after the stop")
    assert drive.limits.watchdog_stops == stops + 1


def test_csv_refuses_a_jump_up_and_a_speed_beyond_the_limit(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(make_config(1, max_velocity_deg_s=360.0))
    drive = driver.drive("joint1")
    drive.enable()
    drive.stream_velocity(10.0)
    # quick-stop deceleration 4 x 360 deg/s^2 over two 10 ms SYNC periods: 28.8 deg/s per step
    with pytest.raises(CommandRejected, match=r"jumps 190\.0 deg/s .* at most 28\.8 deg/s per step"):
        drive.stream_velocity(200.0)
    with pytest.raises(CommandRejected, match=r"max_velocity_deg_s=360"):
        drive.stream_velocity(400.0)
    drive.stream_velocity(0.0)  # slowing down is never refused


def test_cst_drives_the_commanded_torque(torque_limited_drive: Drive) -> None:
    drive = torque_limited_drive
    with pytest.raises(CommandRejected, match=TORQUE_REFUSAL):
        drive.stream_torque(TORQUE_LIMIT_NM + 0.1)
    # 0.2 Nm against 0.03 Nm of friction speeds the joint up
    stream_until(drive.stream_torque, 0.2, drive.cache.sync_period_s,
                 lambda: abs(drive.snapshot().torque_nm - 0.2) <= 0.01 and drive.snapshot().velocity_deg_s > 50.0,
                 "0.2 Nm and the joint speeding up")
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_TORQUE
    stream_until(drive.stream_torque, 0.0, drive.cache.sync_period_s, lambda: abs(drive.snapshot().torque_nm) <= 0.03,
                 "no torque")  # friction brakes it


def test_cyclic_modes_are_refused_on_a_drive_without_them(tmp_path: Path, driver_factory: DriverFactory) -> None:
    eds = tmp_path / "no_cyclic.eds"  # 0x6502 = 0xAD: PP, PV, PT, homing, CSP; no CSV, no CST
    eds.write_text(GENERIC_EDS.read_text().replace("DefaultValue=941", "DefaultValue=173"))
    _, driver = driver_factory(make_config(1, eds=str(eds)))
    drive = driver.drive("joint1")
    drive.enable()
    with pytest.raises(CommandRejected, match=r"CYCLIC_SYNC_VELOCITY is not supported by node 1 \(0x6502 = 0x000000AD\)"):
        drive.stream_velocity(5.0)
    with pytest.raises(CommandRejected, match=r"CYCLIC_SYNC_TORQUE is not supported"):
        drive.stream_torque(0.1)
    assert drive.snapshot().mode == OperationMode.PROFILE_POSITION  # nothing changed on the drive


def test_command_velocity_and_torque_take_the_configured_mode(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(make_config(1, **CYCLIC))
    drive = driver.drive("joint1")
    drive.enable()
    drive.command_velocity(10.0)
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_VELOCITY
    drive.command_torque(0.0)
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_TORQUE
    _, profile = driver_factory(make_config(1))
    other = profile.drive("joint1")
    other.enable()
    other.command_velocity(10.0)
    assert other.snapshot().mode == OperationMode.PROFILE_VELOCITY


def test_command_position_streams_where_the_config_says_cyclic_and_moves_by_profile_elsewhere(
        driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(make_config(1, position_mode="cyclic", max_velocity_deg_s=360.0))
    drive = driver.drive("joint1")
    drive.enable()
    drive.command_position(0.2)  # switches to CSP (SDO) once
    listener = listener_factory(sim)
    for i in range(1, 6):
        drive.command_position(0.2 + 0.5 * i)
    wait_for(lambda: abs(drive.snapshot().angle_deg - 2.7) < 0.05, 2.0, "the shaft at the stream's last set-point")
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_POSITION
    sent = [m for m in drain(listener, 0.05) if m.arbitration_id in (0x201, 0x301)]
    # one RPDO per set-point, controlword Enable Operation without bit 4: no handshake, no reply
    assert [(m.arbitration_id, bytes(m.data[:2])) for m in sent] == [(0x301, b"\x0f\x00")] * 5
    # a stream jumps no further than max velocity over two SYNC periods (360 deg/s x 20 ms)
    with pytest.raises(CommandRejected, match=r"jumps 87\.\d+ deg .* at most 7\.200 deg per step"):
        drive.command_position(90.0)
    _, profile = driver_factory(make_config(1))
    other = profile.drive("joint1")
    other.enable()
    other.command_position(90.0)  # a profile-position move takes any target within the limits
    assert other.snapshot().mode == OperationMode.PROFILE_POSITION


def test_the_first_streamed_set_point_after_a_switch_is_judged_from_where_the_drive_holds(
        driver_factory: DriverFactory) -> None:
    """The shaft turns on while the switch to CSP is under way (a drive answering SDO in 200 ms,
    a velocity profile still running; in the kernel tier's VM: a shaft coasting after a torque
    command). The drive holds where its shaft was when the switch reached it: a set-point at the
    position read before the switch is a jump back, refused; one where the drive holds is taken."""
    # a limited joint: no "short way round" to hide a jump of more than half a turn on a starved machine
    sim, driver = driver_factory(make_config(1, max_velocity_deg_s=360.0, watchdog_ms=10_000, joint="limited",
                                             min_deg=-100_000.0, max_deg=100_000.0))
    drive = driver.drive("joint1")
    drive.enable()
    stream_until(drive.set_velocity, 180.0, drive.cache.sync_period_s, lambda: drive.snapshot().velocity_deg_s > 150.0,
                 "the shaft turning at 180 deg/s")
    runner = sim.simulators["can0"]
    runner.call(lambda: setattr(runner.drive(1).faults, "sdo_delay_s", 0.2))  # ~36 deg before the drive switches
    before = drive.snapshot().angle_deg
    with pytest.raises(CommandRejected, match=r"CSP setpoint jumps .* at most 7\.200 deg per step"):
        drive.stream_position(before)
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_POSITION  # switched; nothing streamed
    runner.call(lambda: setattr(runner.drive(1).faults, "sdo_delay_s", 0.0))
    held = drive.snapshot().angle_deg
    assert held - before > 7.2, (before, held)  # where it holds: past one step from where it was
    stream_until(drive.stream_position, held, drive.cache.sync_period_s, lambda: abs(drive.snapshot().angle_deg - held) < 0.5,
                 f"the shaft at {held:.2f} deg")


if HAVE_ROS:
    from sensor_msgs.msg import JointState

    from nodes.process.qos import COMMAND_QOS


@pytest.fixture
def ros_driver() -> Iterator[tuple[MotorDriver, object]]:
    config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                      "kwargs": {"host": "127.0.0.1", "port": 1}}],
                           "drives": [{"name": "wheel", "node_id": 1, "host_timeout_ms": IN_PROCESS_HOST_TIMEOUT_MS,
                                       **CYCLIC}]}, source=REPO / "tests" / "generated.yaml")
    with SimService.from_config(config, port=0) as sim:
        from can_config import with_bus_overrides
        driver = MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)).start()
        try:
            with driver_node_spinning(driver) as probe:
                yield driver, probe
        finally:
            driver.close()


@requires_ros
def test_joint_commands_velocity_and_effort_stream_csv_and_cst(ros_driver: tuple[MotorDriver, object]) -> None:
    driver, probe = ros_driver
    drive = driver.drive("wheel")
    drive.enable()
    pub = probe.create_publisher(JointState, "/joint_commands", COMMAND_QOS)  # type: ignore[attr-defined]
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, "the driver node subscribed to /joint_commands")
    for i in range(1, 30):  # rad/s, ramped: 0.1 rad/s (5.7 deg/s) per SYNC
        pub.publish(JointState(name=["wheel"], velocity=[min(0.1 * i, 1.0)]))
        time.sleep(0.01)
    wait_for(lambda: drive.snapshot().mode == OperationMode.CYCLIC_SYNC_VELOCITY, 1.0, "CSV")
    wait_for(lambda: abs(drive.snapshot().velocity_deg_s - 57.3) < 3.0, 1.0, "1 rad/s")
    for _ in range(20):
        pub.publish(JointState(name=["wheel"], effort=[0.1]))
        time.sleep(0.01)
    wait_for(lambda: drive.snapshot().mode == OperationMode.CYCLIC_SYNC_TORQUE, 1.0, "CST")
    wait_for(lambda: abs(drive.snapshot().torque_nm - 0.1) < 0.01, 1.0, "0.1 Nm")


@requires_ros
def test_degree_cmd_of_a_cyclic_joint_is_a_stream_and_a_jump_is_refused_not_moved(
        ros_driver: tuple[MotorDriver, object]) -> None:
    from std_msgs.msg import Float32

    driver, probe = ros_driver
    drive = driver.drive("wheel")
    drive.enable()
    pub = probe.create_publisher(Float32, "wheel/degree_cmd", COMMAND_QOS)  # type: ignore[attr-defined]
    wait_for(lambda: pub.get_subscription_count() > 0, 5.0, "the node's degree_cmd subscription")
    for i in range(1, 11):  # each set-point taken before the next (the topic keeps the newest only)
        pub.publish(Float32(data=0.5 * i))
        wait_for(lambda i=i: abs(drive.snapshot().angle_deg - 0.5 * i) < 0.05, 2.0, f"set-point {0.5 * i}")
    assert drive.snapshot().mode == OperationMode.CYCLIC_SYNC_POSITION
    pub.publish(Float32(data=180.0))  # beyond one step of the stream: refused, the shaft stays
    pub.publish(Float32(data=5.5))  # and the stream goes on
    wait_for(lambda: abs(drive.snapshot().angle_deg - 5.5) < 0.05, 2.0, "the set-point after the refused one")
    assert drive.snapshot().angle_deg < 6.0
