"""One owner per piece of state: a drive that re-boots blocks no other drive's watchdog or
heartbeat check, and a command to a drive busy in a long operation is answered at once."""

from __future__ import annotations

import threading
from collections.abc import Callable

from can_config import RoverConfig
from can_config.errors import CommandRejected, DriveStateError
from motor_driver import MotorDriver, State
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import in_thread, make_config, wait_for

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
    wait_for(lambda: not a.cache.booted, 10.0, "A's boot-up seen")
    for _ in range(10):
        b.set_velocity(90.0)
    # order, not time (the benchmarks time them): B's watchdog and C's loss both act while A's
    # re-configuration is still stuck on the bus's worker
    wait_for(lambda: b.limits.watchdog_stops > 0, 10.0, "B's watchdog")
    assert not a.cache.booted
    apply_action(sim, {"action": "unplug", "node": 3})
    wait_for(lambda: c.cache.lost, 10.0, "C's heartbeat loss")
    assert not a.cache.booted  # A was still being configured all along


def test_a_command_to_a_drive_busy_enabling_is_refused_at_once(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(2))
    a, b = driver.drive("joint1"), driver.drive("joint2")
    b.enable()
    apply_action(sim, {"action": "slow_enable", "node": 1, "delay_s": 0.7})  # enable takes about 2 s
    enabling = threading.Thread(target=a.enable)
    enabling.start()
    wait_for(lambda: a.channel.busy == "enable", 10.0, "the enable under way")
    refused = 0
    while enabling.is_alive() and refused < 30:
        try:
            a.move_to(10.0)
        except CommandRejected as err:
            assert "busy with enable" in str(err)
            # refused at once: the enable it would have waited for is still running
            assert enabling.is_alive() and a.channel.busy == "enable"
            refused += 1
        b.move_to(float(refused % 20))  # the other drive is not held up at all
        a.cache.wait_until(lambda: not enabling.is_alive(), 0.01)
    enabling.join()
    assert a.cache.state is State.OPERATION_ENABLED
    assert refused >= 30, refused
    a.move_to(5.0, wait=True)  # and afterwards it takes commands


def test_a_stop_preempts_a_slow_enable(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    a = driver.drive("joint1")
    apply_action(sim, {"action": "slow_enable", "node": 1, "delay_s": 0.7})
    enabling, errors = in_thread(lambda: a.enable(timeout_s=2.0), DriveStateError)
    wait_for(lambda: a.channel.busy == "enable", 10.0, "the enable under way")
    a.disable_voltage()  # never waits for the enable: had it waited, the enable would have succeeded
    enabling.join(10.0)
    assert errors and "interrupted by" in str(errors[0])
    wait_for(lambda: a.cache.state is State.SWITCH_ON_DISABLED, 10.0, "switch on disabled")
