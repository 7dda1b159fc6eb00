"""A statusword the drive sent while this driver's receive thread was behind is not the drive's
failure to change state: a wait for what the drive says (a stop's or an enable's state, homing
attained, a target reached) looks on past its deadline while that thread has yet to hand on what
came (motor_driver.process.held.ReadBehind, as an SDO answer's wait does:
tests/test_sdo_read_behind.py), and a thread still behind at the bound is named as the cause, not
the drive.

The receive thread is held by a callback of its own (tests/test_read_behind.py's Hold), the
waiter is seen past its deadline by a hook in its own loop, and the drive's new statusword is
seen on the bus by an independent client before the thread is let go: no clock decides anything.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import can
import pytest

from can_config import GENERIC_EDS, RoverConfig
from can_config.errors import DriveTimeoutError
from motor_driver import MotorDriver
from motor_driver.drive.command import power as power_module
from motor_driver.process import held
from motor_driver.protocol.cia402 import State, decode_state
from virtual_can import SimService

from .conftest import make_config, wait_for
from .test_host_loss import statusword_tpdo
from .test_read_behind import HOLD_ID, Hold
from .test_sdo_read_behind import HeldCall, error_at_the_bound, see_behind

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

#: the stop's wait: short, so the waiter is past its deadline while the thread is held
STOP_TIMEOUT_S = 0.2


@pytest.fixture
def seen_behind(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    yield see_behind(monkeypatch, power_module)


def hold_and_stop(sim: SimService, driver: MotorDriver, listener_factory: ListenerFactory,
                  looked_on: threading.Event) -> tuple[Hold, HeldCall]:
    """joint1 armed; its bus's receive thread held, then the disable: returns once the drive's
    statusword saying it left Operation Enabled is on the bus (an independent client heard it) and
    the waiter has looked on past its deadline for the thread."""
    drive = driver.drive("joint1")
    drive.enable()
    hold = Hold(driver)
    listener, sender = listener_factory(sim), listener_factory(sim)
    cob, offset = statusword_tpdo(GENERIC_EDS, 1)
    stop = HeldCall(lambda: drive.disable(STOP_TIMEOUT_S), "held-disable")
    sender.send(can.Message(arbitration_id=HOLD_ID, data=b"\x01", is_extended_id=False))
    wait_for(hold.holding.is_set, 30.0, "the receive thread in the hold's callback")
    stop.thread.start()
    while True:  # the drive's answer: a statusword that is no longer Operation Enabled
        msg = listener.recv(30.0)
        assert msg is not None, "the drive's statusword never came on the bus"
        if msg.arbitration_id == cob and decode_state(int.from_bytes(msg.data[offset:offset + 2], "little")) in (
                State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED):
            break
    wait_for(looked_on.is_set, 30.0, "the waiter past its deadline, looking on for the receive thread")
    return hold, stop


def test_a_statusword_that_came_while_the_receive_thread_was_held_ends_the_wait(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event) -> None:
    sim, driver = driver_factory(make_config(1))
    hold, stop = hold_and_stop(sim, driver, listener_factory, seen_behind)
    assert stop.thread.is_alive() and stop.error is None  # waiting on, past its deadline
    hold.release.set()
    stop.thread.join(30.0)
    assert not stop.thread.is_alive() and stop.error is None, stop.error
    assert driver.drive("joint1").cache.state in (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED)


def test_a_receive_thread_still_behind_at_the_bound_is_named_not_the_drive(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(held, "READ_BEHIND_MAX_S", 0.3)
    sim, driver = driver_factory(make_config(1))
    said = error_at_the_bound(*hold_and_stop(sim, driver, listener_factory, seen_behind), DriveTimeoutError)
    assert "This driver was late, not the drive" in said and "receive thread was still behind" in said, said
    assert "last read OPERATION_ENABLED" in said and "still in" not in said, said
