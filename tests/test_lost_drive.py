"""A drive the driver stops hearing may still be turning (a broken transmit line, a hung CAN
task): the driver tells it to stop by every means that needs no answer (the quick-stop
controlword on its RPDO, NMT stop, the controlword by SDO) and keeps telling it until it is
heard again; on shutdown too. The simulated drive's transmitter is cut (``tx_dead``): it still
hears and obeys, and sends nothing. What it does is read from the simulator, not the driver.
The guarding causes (no answer, a stuck toggle) need remote frames: the kernel tier has them."""

from __future__ import annotations

from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import drain, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]


def sim_motion(sim: SimService, node: int = 1) -> tuple[str, float]:
    runner = sim.simulators["can0"]
    return runner.call(lambda: (runner.drive(node).state.name, abs(runner.drive(node).omega)))  # type: ignore[return-value]


def turning_then_deaf(sim: SimService, driver: MotorDriver, node: int = 1) -> None:
    drive = driver.drive(f"joint{node}")
    drive.enable()
    drive.move_to(350.0)  # a long profile move at 90 deg/s: no watchdog stops this one
    wait_for(lambda: sim_motion(sim, node)[1] > 0.5, 5.0, "the shaft turning")
    apply_action(sim, {"action": "tx_dead", "node": node})


def test_a_drive_whose_transmitter_dies_while_turning_is_stopped(driver_factory: DriverFactory,
                                                                 listener_factory: ListenerFactory) -> None:
    sim, driver = driver_factory(make_config(2, joint="continuous", heartbeat_timeout_ms=300.0))
    listener = listener_factory(sim)
    turning_then_deaf(sim, driver)
    drive = driver.drive("joint1")
    wait_for(lambda: drive.cache.lost, 5.0, "the driver declares it lost")
    wait_for(lambda: sim_motion(sim)[0] != "OPERATION_ENABLED" and sim_motion(sim)[1] < 1e-3, 10.0,
             "the deaf drive stopped")
    frames = drain(listener, 0.3)
    assert any(m.arbitration_id == 0x201 and m.data[0] == 0x02 for m in frames), "the quick-stop RPDO"
    assert any(m.arbitration_id == 0x000 and bytes(m.data) == b"\x02\x01" for m in frames), "NMT stop of node 1"
    assert not any(m.arbitration_id == 0x000 and m.data[1] == 2 for m in frames), "the other drive left alone"
    assert driver.drive("joint2").cache.state.name != "FAULT" and not driver.drive("joint2").cache.lost
    assert driver.supervisor.records["joint1"].lost_stops >= 2  # told again while it stays unheard


def test_a_lost_drive_is_told_to_stop_when_the_driver_shuts_down(driver_factory: DriverFactory,
                                                                 listener_factory: ListenerFactory) -> None:
    sim, driver = driver_factory(make_config(1, joint="continuous", heartbeat_timeout_ms=300.0))
    turning_then_deaf(sim, driver)
    wait_for(lambda: driver.drive("joint1").cache.lost, 5.0, "the driver declares it lost")
    listener = listener_factory(sim)
    driver.close()
    frames = drain(listener, 0.3)
    assert any(m.arbitration_id == 0x000 and bytes(m.data) == b"\x02\x01" for m in frames), "NMT stop at shutdown"
    wait_for(lambda: sim_motion(sim)[0] != "OPERATION_ENABLED", 5.0, "stopped")


def test_a_lost_drive_heard_again_in_the_stop_it_was_told_is_configured_again_not_called_another_master(
        driver_factory: DriverFactory, caplog: pytest.LogCaptureFixture) -> None:
    """The driver's own NMT stop of a lost drive (what a driver starved past READ_BEHIND_MAX_S
    does to every drive whose heartbeat it read late, tests/test_read_behind.py) is no other
    master's: when the drive is heard again, STOPPED, it is configured again (NMT start, left
    disabled) and can be enabled; nothing says "another master" and no command is refused for one."""
    sim, driver = driver_factory(make_config(1, joint="continuous", heartbeat_timeout_ms=300.0))
    turning_then_deaf(sim, driver)
    drive = driver.drive("joint1")
    boots = drive.boot.boot_count
    runner = sim.simulators["can0"]
    wait_for(lambda: drive.cache.lost, 5.0, "the driver declares it lost")
    wait_for(lambda: runner.call(lambda: runner.drive(1).nmt.name) == "STOPPED", 5.0, "the drive NMT-stopped")
    apply_action(sim, {"action": "tx_dead", "node": 1, "on": False})
    wait_for(lambda: drive.boot.boot_count > boots and drive.cache.booted and not drive.cache.lost, 10.0, "configured again")
    assert runner.call(lambda: runner.drive(1).nmt.name) == "OPERATIONAL"
    assert sim_motion(sim)[0] != "OPERATION_ENABLED"  # configured again, left disabled
    drive.enable()
    assert sim_motion(sim)[0] == "OPERATION_ENABLED"
    said = [r.getMessage() for r in caplog.records if "another master" in r.getMessage()]
    assert not said and drive.watch.foreign_master == "", said
