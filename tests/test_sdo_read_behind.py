"""An SDO answer the drive sent while this driver's receive thread was behind is not the drive's
silence: the waiter, past its deadline, looks on while that thread has yet to hand on what came
(motor_driver.process.held.ReadBehind, motor_driver.bus.adapters.receive_behind), and a thread
still behind at the bound is named as the cause, not the drive.

The receive thread is held by a callback of its own (tests/test_read_behind.py's Hold), a hook
inside the critical section; the waiter is seen past its deadline by a hook in its own loop,
and the drive's answer is seen on the bus by an independent client before the thread is let go,
so no clock decides anything. The whole process is not held (that is HeldDeadline's case,
tests/test_held_waits.py): the waiter runs on time while the receive thread does not.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator
from types import ModuleType

import can
import pytest

from can_config import RoverConfig
from can_config.errors import SdoTimeoutError
from motor_driver import MotorDriver
from motor_driver.bus import adapters, sdo_client
from motor_driver.bus.adapters import receive_behind, watch_idle
from motor_driver.process import held
from motor_driver.runtime import supervisor as supervisor_module
from virtual_can import SimService

from .conftest import make_config, wait_for
from .test_read_behind import HOLD_ID, Hold

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

DEVICE_TYPE = 0x1000
SDO_TIMEOUT_MS = 200.0


class SeenBehind(held.ReadBehind):
    """held.ReadBehind that says when a waiter first looked on past its deadline for the receive thread."""

    looked_on = threading.Event()

    def wait_on(self) -> bool:
        again = super().wait_on()
        if again:
            SeenBehind.looked_on.set()
        return again


def see_behind(monkeypatch: pytest.MonkeyPatch, waiter: ModuleType) -> threading.Event:
    """The waits of ``waiter`` (the module that makes their ReadBehind) use SeenBehind, and no
    bound ends a held test early; the event it sets."""
    SeenBehind.looked_on = threading.Event()
    monkeypatch.setattr(waiter, "ReadBehind", SeenBehind)
    monkeypatch.setattr(held, "READ_BEHIND_MAX_S", 600.0)  # a test that shortens it sets it after this
    # the drive's heartbeats go unread meanwhile: the supervisor waits for the reader as long as needed
    monkeypatch.setattr(supervisor_module, "READ_BEHIND_MAX_S", 600.0)
    return SeenBehind.looked_on


@pytest.fixture
def seen_behind(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    yield see_behind(monkeypatch, sdo_client)


class HeldCall:
    """``call()`` (a wait for the drive) in a thread of its own, started once the receive thread
    is held: its value or its error."""

    def __init__(self, call: Callable[[], object], name: str) -> None:
        self.value: object = None
        self.error: Exception | None = None
        self._call = call
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        try:
            self.value = self._call()
        except Exception as err:
            self.error = err


def error_at_the_bound(hold: Hold, call: HeldCall, kind: type[Exception]) -> str:
    """The held call's end while the receive thread is still held (the bound passed): its error,
    of ``kind``, said; the thread let go after."""
    try:
        call.thread.join(30.0)
        assert not call.thread.is_alive() and hold.holding.is_set() and not hold.release.is_set()
    finally:
        hold.release.set()
    assert isinstance(call.error, kind), call.error
    return str(call.error)


def hold_and_read(sim: SimService, driver: MotorDriver, listener_factory: ListenerFactory,
                  looked_on: threading.Event) -> tuple[Hold, HeldCall]:
    """The receive thread held, then the read: returns once the drive's answer is on the bus (an
    independent client heard it) and the waiter has looked on past its deadline for the thread."""
    hold = Hold(driver)
    listener, sender = listener_factory(sim), listener_factory(sim)
    read = HeldCall(lambda: driver.drive("joint1").sdo_read(DEVICE_TYPE), "held-sdo-read")
    sender.send(can.Message(arbitration_id=HOLD_ID, data=b"\x01", is_extended_id=False))
    wait_for(hold.holding.is_set, 30.0, "the receive thread in the hold's callback")
    assert receive_behind(driver.buses["can0"].network.bus) is True
    read.thread.start()
    while True:  # the drive answered: 0x581, an upload initiate answer naming 0x1000:0
        msg = listener.recv(30.0)
        assert msg is not None, "the drive's answer never came on the bus"
        if msg.arbitration_id == 0x581 and bytes(msg.data[1:4]) == b"\x00\x10\x00":
            break
    wait_for(looked_on.is_set, 30.0, "the waiter past its deadline, looking on for the receive thread")
    return hold, read


def test_an_answer_that_came_while_the_receive_thread_was_held_is_read_not_timed_out(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event) -> None:
    sim, driver = driver_factory(make_config(1, sdo_timeout_ms=SDO_TIMEOUT_MS))
    hold, read = hold_and_read(sim, driver, listener_factory, seen_behind)
    assert read.thread.is_alive() and read.error is None  # waiting on, past its deadline
    hold.release.set()
    read.thread.join(30.0)
    assert read.error is None, read.error
    assert isinstance(read.value, bytes) and int.from_bytes(read.value, "little") == 0x00020192  # the generic EDS's device type
    assert not driver.drive("joint1").cache.lost


def test_a_receive_thread_still_behind_at_the_bound_is_named_not_the_drive(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, seen_behind: threading.Event,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(held, "READ_BEHIND_MAX_S", 0.3)
    sim, driver = driver_factory(make_config(1, sdo_timeout_ms=SDO_TIMEOUT_MS))
    said = error_at_the_bound(*hold_and_read(sim, driver, listener_factory, seen_behind), SdoTimeoutError)
    assert "This driver was late, not the drive silent" in said and "receive thread was still behind" in said, said
    assert "check power" not in said, said


def test_a_bus_that_cannot_tell_excuses_nothing_and_the_socket_count_is_the_kernels() -> None:
    """python-can's virtual bus, watched as the driver watches a bus it reads a frame at a time,
    cannot tell a frame taken from one handed on: not known, so nothing is excused. The count the
    socketcand and kernel paths read is the kernel's own (FIONREAD); the kernel tier shows a CAN
    raw socket's (tests/test_kernel_tier.py)."""
    bus = watch_idle(can.Bus(interface="virtual", channel="sdo-read-behind"), lambda began: None)
    try:
        assert receive_behind(bus) is None
        assert receive_behind(None) is None
    finally:
        bus.shutdown()
    left, right = socket.socketpair()
    with left, right:
        assert adapters._unread_bytes(right) == 0
        left.sendall(b"< frame 581 1.0 43 00 10 00 >")
        assert adapters._unread_bytes(right) == 29
        right.recv(10)
        assert adapters._unread_bytes(right) == 19
    assert adapters._unread_bytes(right) is None  # closed: cannot tell


def test_read_behind_looks_on_only_while_the_thread_is_behind_and_within_its_bound() -> None:
    now = [0.0]
    behind: list[bool | None] = [True]
    looks = held.ReadBehind(lambda: behind[0], bound_s=1.0, clock=lambda: now[0])
    assert looks.wait_on()  # behind at the deadline: look on
    now[0] = 0.6
    assert looks.wait_on() and not looks.gave_up
    now[0] = 1.0
    assert not looks.wait_on() and looks.gave_up and "still behind the bus 1.0 s" in looks.said()
    now[0], behind[0] = 1.1, False  # an answer not its own was dropped, and then the thread had caught up
    assert not looks.wait_on() and not looks.gave_up and "still behind" not in looks.said()
    behind[0] = True

    caught_up = held.ReadBehind(lambda: behind[0], bound_s=1.0, clock=lambda: now[0])
    now[0] = 5.0
    assert caught_up.wait_on()
    now[0], behind[0] = 5.4, False
    assert not caught_up.wait_on() and not caught_up.gave_up  # caught up: the drive's silence, judged now
    assert "looked 0.40 s past the deadline" in caught_up.said()

    for unknown in (None, False):  # a bus that cannot tell, or a thread that kept up: nothing excused
        behind[0] = unknown
        plain = held.ReadBehind(lambda: behind[0], bound_s=1.0, clock=lambda: now[0])
        assert not plain.wait_on() and not plain.gave_up and plain.said() == ""
