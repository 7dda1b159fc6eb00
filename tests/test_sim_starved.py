"""A simulated drive judges its watch on the host by the bus's time line, not by when its runner
thread got to look (issue 64): a runner held for longer than the consumer time while the host's
heartbeats keep reaching the bus finds them, stamped in time, and does not trip; a host that
really stops its heartbeats is still caught, on a bus where nothing else is sent, by the wall clock.

The runner is held by its hook right after a wait on the bus, before it reads its clocks: where a
starved thread stands when the frames it has not looked at pile up behind it. The hold lasts
until a listener of the test's own has seen the host's heartbeats reach the bus for twice the
consumer time past the hold's start (an order, not a duration).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can

from can_config import RoverConfig
from motor_driver import MotorDriver, State
from virtual_can import SimService
from virtual_can.bus import VirtualBus
from virtual_can.service import specs_for_count
from virtual_can.sim import DriveSimulator
from virtual_can.sim.runner import LOOK_GAP_S, SETTLE_LOOKS, BusClock

from .conftest import make_config, wait_for

HOST_NODE = 127
HOST_TIMEOUT_S = 0.5  # the in-process rigs' consumer time: the host is this test's own process
EMCY_HOST_LOST = b"\x30\x81"  # EMCY 0x8130, little-endian
HANG_S = 30.0


class Listener:
    """Every frame of the channel with its bus stamp, collected by a thread of the test's own."""

    def __init__(self, sim: SimService) -> None:
        self.bus = VirtualBus("can0", engine=sim.engine)
        self.frames: list[can.Message] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="test-listener")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append(msg)

    def host_beats_after(self, stamp: float) -> list[float]:
        return [m.timestamp for m in list(self.frames) if m.arbitration_id == 0x700 + HOST_NODE and m.timestamp > stamp]

    def host_lost_emcy(self, node_id: int) -> list[can.Message]:
        return [m for m in list(self.frames) if m.arbitration_id == 0x80 + node_id and bytes(m.data[:2]) == EMCY_HOST_LOST]

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()


@contextmanager
def listening(sim: SimService) -> Iterator[Listener]:
    listener = Listener(sim)
    try:
        yield listener
    finally:
        listener.close()


class Hold:
    """The runner's hook: held at its next look once armed, until released; counts the looks after."""

    def __init__(self) -> None:
        self.armed = threading.Event()
        self.holding = threading.Event()
        self.release = threading.Event()
        self.held_at = 0.0  # wall clock (the bus stamps' clock) when the hold began
        self.looks_after = 0

    def __call__(self, point: str) -> None:
        if point != "looked":
            return
        if self.release.is_set():
            self.looks_after += 1
        elif self.armed.is_set():
            self.held_at = time.time()
            self.holding.set()
            self.release.wait(HANG_S)


def enabled_drive(driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]
                  ) -> tuple[SimService, MotorDriver, DriveSimulator]:
    # the driver's own watch on the drive is long: the held runner sends no drive heartbeat either
    sim, driver = driver_factory(make_config(1, host_timeout_ms=HOST_TIMEOUT_S * 1000, heartbeat_timeout_ms=30_000))
    runner = sim.simulators["can0"]
    driver.drive("joint1").enable()
    wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), HANG_S, "the drive to watch the host")
    return sim, driver, runner


def test_a_runner_held_past_the_consumer_time_while_the_host_beats_does_not_trip(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    sim, driver, runner = enabled_drive(driver_factory)
    hold = Hold()
    with listening(sim) as bus:
        runner.set_hook(hold)
        try:
            hold.armed.set()
            wait_for(hold.holding.is_set, HANG_S, "the runner to be held")
            # the host's heartbeats reach the bus for twice the consumer time while the runner looks at none
            wait_for(lambda: any(t > hold.held_at + 2 * HOST_TIMEOUT_S for t in bus.host_beats_after(hold.held_at)),
                     HANG_S, "host heartbeats on the bus past twice the consumer time")
            beats = bus.host_beats_after(hold.held_at)
            hold.release.set()
            wait_for(lambda: hold.looks_after >= 5, HANG_S, "the runner to look and tick again")
        finally:
            runner.set_hook(None)
            hold.release.set()
        gaps = [b - a for a, b in zip([hold.held_at, *beats], beats, strict=False)]
        assert max(gaps) < HOST_TIMEOUT_S, f"the host itself was late ({max(gaps):.3f} s): not this test's case"
        assert bus.host_lost_emcy(1) == [], "the drive took its own hold for a silent host"
    assert runner.call(lambda: runner.drive(1).state) is State.OPERATION_ENABLED
    assert driver.drive("joint1").cache.state is State.OPERATION_ENABLED


class Host:
    """The host as a bare python-can node on the bus: SDO writes and its heartbeat, nothing else."""

    def __init__(self, sim: SimService) -> None:
        self.bus = VirtualBus("can0", engine=sim.engine)
        self.beating = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True, name="test-host-heartbeat")
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.is_set():
            if self.beating.is_set():
                self.bus.send(can.Message(arbitration_id=0x700 + HOST_NODE, data=b"\x05", is_extended_id=False))
            self._stop.wait(0.05)

    def sdo_write(self, index: int, sub: int, value: int, size: int) -> None:
        command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        data = bytes([command]) + index.to_bytes(2, "little") + bytes([sub]) + value.to_bytes(4, "little")
        self.bus.send(can.Message(arbitration_id=0x601, data=data, is_extended_id=False))
        deadline = time.monotonic() + HANG_S
        while time.monotonic() < deadline:
            answer = self.bus.recv(0.1)
            if answer is not None and answer.arbitration_id == 0x581 and bytes(answer.data[1:4]) == data[1:4]:
                assert answer.data[0] == 0x60, f"SDO write 0x{index:04X}:{sub} refused: {bytes(answer.data).hex()}"
                return
        raise AssertionError(f"no SDO answer to the write of 0x{index:04X}:{sub}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()


def test_a_host_that_stops_its_heartbeats_on_a_silent_bus_is_caught() -> None:
    """No driver, no SYNC, no other node: nothing on the bus moves its time line on once the host is
    silent; the wall clock does, at the runner's steady looks at an empty queue."""
    with SimService(specs_for_count(1), port=0) as sim, listening(sim) as watch:
        runner, host = sim.simulators["can0"], Host(sim)
        try:
            host.bus.send(can.Message(arbitration_id=0x000, data=b"\x01\x01", is_extended_id=False))  # NMT start
            host.sdo_write(0x1016, 1, HOST_NODE << 16 | int(HOST_TIMEOUT_S * 1000), 4)
            host.sdo_write(0x6007, 0, 3, 2)  # abort connection option: quick stop (as the driver sets it)
            host.beating.set()
            wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), HANG_S,
                     "the drive to watch the host")
            for controlword in (0x06, 0x07, 0x0F):
                host.sdo_write(0x6040, 0, controlword, 2)
            assert runner.call(lambda: runner.drive(1).state) is State.OPERATION_ENABLED
            host.beating.clear()
            wait_for(lambda: bool(watch.host_lost_emcy(1)), HANG_S, "EMCY 0x8130 from the drive")
            assert runner.call(lambda: runner.drive(1).state) is not State.OPERATION_ENABLED
            assert not runner.call(lambda: dict(runner.drive(1)._consumer_seen))  # tripped, and disarmed
        finally:
            host.close()


def test_the_bus_clock_stands_still_after_a_hold_and_then_takes_the_stamps_and_the_wall() -> None:
    """Pure: a look long after the one before (the runner was held) does not move the bus time the
    drives are judged on for SETTLE_LOOKS looks, whatever was stamped meanwhile (the server's
    threads, held with it, may not have delivered a heartbeat stamped before that SYNC); then the
    newest stamp counts, and the wall clock at steady looks that emptied the queue."""
    clock, t = BusClock(), time.time()  # frames are stamped on the wall clock
    for _ in range(SETTLE_LOOKS + 1):  # the first look follows none: a hold
        t += 0.002
        clock.look(t, emptied=True)
    assert clock.look(t + 0.002, emptied=True) == t + 0.002  # steady: the wall clock
    assert clock.holds == 0  # the first look follows none: no hold counted
    t += 0.002
    judged = t
    t += 10 * LOOK_GAP_S  # held
    clock.stamp(can.Message(arbitration_id=0x80, timestamp=t - 0.001))  # a SYNC stamped late in the hold
    settling = [clock.look(t + i * 0.002, emptied=False) for i in range(SETTLE_LOOKS)]  # a queue never emptied
    assert settling == [judged] * SETTLE_LOOKS
    assert clock.holds == 1  # counted once (tests that judge the drives' motion read it)
    assert clock.look(t + SETTLE_LOOKS * 0.002, emptied=False) == t - 0.001  # then the newest stamp
    assert clock.look(t + (SETTLE_LOOKS + 1) * 0.002, emptied=True) == t + (SETTLE_LOOKS + 1) * 0.002
