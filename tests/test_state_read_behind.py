"""A statusword the drive sent while this driver's receive thread was behind is not the drive's
failure: a wait for what the drive says of itself (an enable's states, homing attained, a target
reached) looks on past its deadline while that thread has yet to hand on what came
(motor_driver.process.held.ReadBehind, as an SDO answer's wait does: tests/test_sdo_read_behind.py).
A stop's confirmation looks on only briefly (power.STOP_READ_BEHIND_S: the next drive's stop waits
behind it in safe_stop and the drive system's stopper), then names this driver, not the drive.

The receive thread is held by a callback of its own (tests/test_read_behind.py's Hold), the
waiter is seen past its deadline by a hook in its own loop, and the drive's statusword is seen on
the bus by an independent client before the thread is let go: no clock decides anything.
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
from motor_driver.protocol.cia402 import SW, State, decode_state
from virtual_can import SimService

from .conftest import make_config, wait_for
from .test_host_loss import statusword_tpdo
from .test_read_behind import HOLD_ID, Hold
from .test_sdo_read_behind import HeldCall, error_at_the_bound, see_behind

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

#: the waits' timeouts: short, so the waiter is past its deadline while the thread is held
WAIT_S = 0.2
#: the move: at the default 90 deg/s it takes longer than the wait
MOVE_DEG = 60.0


@pytest.fixture
def seen_behind(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    yield see_behind(monkeypatch, power_module)


def held_with(sim: SimService, driver: MotorDriver, listener_factory: ListenerFactory, call: HeldCall,
              heard: Callable[[int], bool]) -> Hold:
    """joint1's bus's receive thread held, then ``call`` started; returns once a statusword for
    which ``heard`` holds is on the bus (an independent client heard it)."""
    hold = Hold(driver)
    listener, sender = listener_factory(sim), listener_factory(sim)
    cob, offset = statusword_tpdo(GENERIC_EDS, 1)
    sender.send(can.Message(arbitration_id=HOLD_ID, data=b"\x01", is_extended_id=False))
    wait_for(hold.holding.is_set, 30.0, "the receive thread in the hold's callback")
    call.thread.start()
    while True:
        msg = listener.recv(30.0)
        assert msg is not None, "the drive's statusword never came on the bus"
        if msg.arbitration_id == cob and heard(int.from_bytes(msg.data[offset:offset + 2], "little")):
            return hold


def test_a_target_reached_while_the_receive_thread_was_held_ends_the_wait(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(MOVE_DEG)
    wait_for(lambda: drive.channel.handshake_idle and not drive.cache.received.statusword & SW.TARGET_REACHED,
             30.0, "the move taken (its handshake done), not yet reached")
    move = HeldCall(lambda: drive.wait_target_reached(WAIT_S), "held-move")
    hold = held_with(sim, driver, listener_factory, move, lambda sw: bool(sw & SW.TARGET_REACHED))
    wait_for(seen_behind.is_set, 30.0, "the waiter past its deadline, looking on for the receive thread")
    assert move.thread.is_alive() and move.error is None  # waiting on, past its deadline
    hold.release.set()
    move.thread.join(30.0)
    assert not move.thread.is_alive() and move.error is None, move.error
    assert abs(drive.snapshot().angle_deg - MOVE_DEG) < 1.0


def test_a_stop_does_not_wait_for_a_receive_thread_behind_and_names_it_not_the_drive(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    stop = HeldCall(lambda: drive.disable(WAIT_S), "held-disable")
    hold = held_with(sim, driver, listener_factory, stop, lambda sw: decode_state(sw) in (
        State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED))  # the drive did stop
    # ended while the thread is still held: it looked on only its short bound, not the 600 s set here
    said = error_at_the_bound(hold, stop, DriveTimeoutError)
    assert "This driver was late, not the drive" in said and "receive thread was still behind" in said, said
    assert "last read OPERATION_ENABLED" in said and "still in" not in said, said
