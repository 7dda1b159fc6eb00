"""One owner per piece of state: a drive that re-boots blocks no other drive's watchdog or
heartbeat check, and a command to a drive busy in a long operation is answered at once."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from can_config import RoverConfig
from can_config.errors import CommandRejected, DriveStateError
from motor_driver import MotorDriver, State
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def test_a_rebooting_drive_blocks_neither_the_watchdog_nor_heartbeat_checks_of_another(
        driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(3, watchdog_ms=300, heartbeat_timeout_ms=350))
    a, b, c = driver.drive("joint1"), driver.drive("joint2"), driver.drive("joint3")
    b.enable()
    # A power-cycles and then answers every SDO 3 s late: its re-configuration on the bus's
    # worker is stuck in SDO timeouts and retries for seconds
    apply_action(sim, {"action": "sdo", "node": 1, "delay_s": 3.0})
    apply_action(sim, {"action": "power_cycle", "node": 1, "off_s": 0.1})
    wait_for(lambda: a.rebooted.is_set() or not a.booted, 2.0, "A's boot-up seen")
    time.sleep(0.3)  # A's re-configuration is under way
    for _ in range(10):
        b.set_velocity(90.0)
        time.sleep(0.02)
    t_last = time.monotonic()
    wait_for(lambda: b.watchdog_stops > 0, 2.0, "B's watchdog")
    assert time.monotonic() - t_last == pytest.approx(0.3, abs=0.05 + 0.02)  # its configured time +-50 ms
    apply_action(sim, {"action": "unplug", "node": 3})
    t_unplug = time.monotonic()
    wait_for(lambda: c.lost, 2.0, "C's heartbeat loss")
    # the last heartbeat came up to one period (100 ms) before the unplug
    assert 0.35 - 0.1 - 0.05 <= time.monotonic() - t_unplug <= 0.35 + 0.05
    assert not a.booted  # A was still being configured all along


def test_a_command_to_a_drive_busy_enabling_is_refused_at_once(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(2))
    a, b = driver.drive("joint1"), driver.drive("joint2")
    b.enable()
    apply_action(sim, {"action": "slow_enable", "node": 1, "delay_s": 0.7})  # enable takes about 2 s
    enabling = threading.Thread(target=a.enable)
    t0 = time.monotonic()
    enabling.start()
    time.sleep(0.2)
    worst = 0.0
    refused = 0
    while enabling.is_alive() and time.monotonic() - t0 < 5:
        start = time.perf_counter()
        try:
            a.move_to(10.0)
        except CommandRejected as err:
            assert "busy with enable" in str(err)
            refused += 1
        worst = max(worst, time.perf_counter() - start)
        b.move_to(float(refused % 20))  # the other drive is not held up at all
        time.sleep(0.01)
    enabling.join()
    assert time.monotonic() - t0 >= 1.8 and a.state is State.OPERATION_ENABLED
    assert refused > 50 and worst < 0.005, (refused, worst)
    a.move_to(5.0, wait=True)  # and afterwards it takes commands


def test_a_stop_preempts_a_slow_enable(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    a = driver.drive("joint1")
    apply_action(sim, {"action": "slow_enable", "node": 1, "delay_s": 0.7})
    errors: list[BaseException] = []

    def enable() -> None:
        try:
            a.enable(timeout_s=2.0)
        except DriveStateError as err:
            errors.append(err)

    enabling = threading.Thread(target=enable)
    enabling.start()
    time.sleep(0.3)
    t0 = time.monotonic()
    a.disable_voltage()  # never waits for the enable
    assert time.monotonic() - t0 < 0.2
    enabling.join(3.0)
    assert errors and "interrupted by" in str(errors[0])
    time.sleep(1.0)
    assert a.state is State.SWITCH_ON_DISABLED
