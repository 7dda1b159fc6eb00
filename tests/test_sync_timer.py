"""The SYNC of a socketcand bus comes from the daemon's timer (socketcand's broadcast manager,
'< add >'), not from a thread of the driver: a busy driver process does not shift it. A config
can ask for the thread; a second master's SYNC is still seen (by the rate)."""

from __future__ import annotations

import time
from collections.abc import Callable

import can

from can_config import RoverConfig, parse_config
from motor_driver import MotorDriver
from motor_driver.cyclic import DaemonCyclicTask, add_command
from virtual_can.service import SimService

from .conftest import IN_PROCESS_HOST_TIMEOUT_MS, REPO, drain

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def config(**bus: object) -> RoverConfig:
    return parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                    "kwargs": {"host": "127.0.0.1", "port": 1}, **bus}],
                         "drives": [{"name": "joint1", "node_id": 1, "host_timeout_ms": IN_PROCESS_HOST_TIMEOUT_MS}]},
                        source=REPO / "tests" / "generated.yaml")


def sync_times(listener: can.BusABC, seconds: float) -> list[float]:
    return [m.timestamp for m in drain(listener, seconds) if m.arbitration_id == 0x080]


def test_add_command_is_the_socketcand_line() -> None:
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    assert add_command(sync, 0.01) == "< add 0 10000 080 0 >"
    ext = can.Message(arbitration_id=0x1234567, data=b"\x01\xff", is_extended_id=True)
    assert add_command(ext, 2.5) == "< add 2 500000 01234567 2 01 FF >"


def test_the_daemon_sends_the_sync_and_a_busy_driver_does_not_shift_it(
        driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(config())
    assert isinstance(driver.buses["can0"].sync_task, DaemonCyclicTask)
    listener = listener_factory(sim)
    drain(listener, 0.05)
    stop = time.monotonic() + 0.5
    while time.monotonic() < stop:  # the driver's process is busy: its interpreter is taken
        sum(i * i for i in range(20_000))
    syncs = sync_times(listener, 0.01)
    assert len(syncs) >= 45
    assert driver.drive("joint1").foreign_master == ""  # its own SYNC, reaching it, is not another master's


def test_a_config_can_keep_the_sync_in_a_thread(driver_factory: DriverFactory,
                                                listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(config(sync_timer="thread"))
    assert not isinstance(driver.buses["can0"].sync_task, DaemonCyclicTask)
    listener = listener_factory(sim)
    syncs = sync_times(listener, 0.3)
    assert 25 <= len(syncs) <= 35
