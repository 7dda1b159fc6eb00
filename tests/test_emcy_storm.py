"""A babbling node: EMCY frames on a live drive's COB-ID, from another client of the virtual bus,
as fast as it can send them. The driver's log stays short (a drive's EMCY lines are rate-limited,
with the count held back), its receive thread keeps up, so that every heartbeat the drives sent
between the EMCYs is seen in its place and no drive is declared lost; and an EMCY 0x0000 (error
reset) that is not the driver's own reset leaves the cause of a fault standing. Verdicts are
orders and outcomes (a second independent client records the bus's order); no clock decides."""

from __future__ import annotations

import itertools
import logging
import threading
from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from motor_driver.diagnostics.health import ERROR, drive_health
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import in_thread, make_config, wait_for
from .drive_states import fault

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

BURST = 10_000
EMCY = bytes([0x10, 0x23, 0x01, 0, 0, 0, 0, 0])  # 0x2310 (current, output side) from node 1
LAST = bytes([0x10, 0x23, 0x01, 0xEE, 0, 0, 0, 0])  # the burst's last frame, told apart by its data
HEARTBEATS = (0x701, 0x702)


class Order:
    """What one side saw, in order: 'E' for an EMCY of node 1, the COB-ID of a heartbeat; ``done``
    once the burst's last EMCY came."""

    def __init__(self) -> None:
        self.seen: list[int | str] = []
        self.done = threading.Event()

    def frame(self, cob_id: int, data: bytes | bytearray) -> None:
        if cob_id == 0x081:
            self.seen.append("E")
            if bytes(data) == LAST:
                self.done.set()
        elif cob_id in HEARTBEATS:
            self.seen.append(cob_id)

    def within_burst(self, cob_id: int) -> int:
        """Heartbeats of ``cob_id`` between the burst's first and last EMCY."""
        first, last = self.seen.index("E"), len(self.seen) - 1 - self.seen[::-1].index("E")
        return sum(1 for item in self.seen[first:last] if item == cob_id)


def test_ten_thousand_emcys_leave_the_log_short_and_every_heartbeat_between_them_seen(
        driver_factory: DriverFactory, listener_factory: ListenerFactory,
        caplog: pytest.LogCaptureFixture) -> None:
    sim, driver = driver_factory(make_config(2))
    network = driver.buses["can0"].network
    by_driver = Order()  # on the driver's receive thread, beside its own callbacks
    for cob in (0x081, *HEARTBEATS):
        network.subscribe(cob, lambda cob_id, data, timestamp: by_driver.frame(cob_id, data))
    on_bus = Order()
    watcher = listener_factory(sim)
    beats: dict[int, list[float]] = {cob: [] for cob in HEARTBEATS}  # the bus's stamps of each drive's heartbeats
    listening = threading.Event()  # set by the test once the bus's record covers its verdicts

    def watch() -> None:
        while not listening.is_set():
            msg = watcher.recv(0.5)
            if msg is not None:
                on_bus.frame(msg.arbitration_id, msg.data)
                if msg.arbitration_id in beats:
                    beats[msg.arbitration_id].append(msg.timestamp)

    watching, failed = in_thread(watch, name="test-bus-order")
    sender = listener_factory(sim)
    caplog.set_level(logging.INFO)
    caplog.clear()
    for _ in range(BURST - 1):
        sender.send(can.Message(arbitration_id=0x081, data=EMCY, is_extended_id=False))
    sender.send(can.Message(arbitration_id=0x081, data=LAST, is_extended_id=False))
    wait_for(by_driver.done.is_set, 120.0, "the burst's last EMCY at the driver")
    wait_for(on_bus.done.is_set, 120.0, "the burst's last EMCY on the bus")
    lost = {drive.name: drive.cache.lost or driver.supervisor.records[drive.name].lost_stops > 0 for drive in driver}
    lost_lines = [r.getMessage() for r in caplog.records if "heartbeat lost" in r.getMessage()]
    # the bus's record up to past that verdict: one more heartbeat of each drive on the bus
    heard = {cob: len(stamps) for cob, stamps in beats.items()}
    wait_for(lambda: all(len(beats[cob]) > n for cob, n in heard.items()), 30.0, "a heartbeat of each drive after the verdict")
    listening.set()
    watching.join(10.0)
    assert not failed
    assert by_driver.seen.count("E") == on_bus.seen.count("E") == BURST  # nothing dropped on the way
    for cob in HEARTBEATS:  # each heartbeat sent meanwhile, seen by the driver in its place
        assert by_driver.within_burst(cob) == on_bus.within_burst(cob) > 0, cob
    lines = [r for r in caplog.records if r.levelno >= logging.INFO]
    assert len(lines) < 100, len(lines)
    assert driver.drive("joint1").cache.emcy_count == BURST  # each counted, logged or not
    # No drive whose heartbeats were on the bus is declared lost: the driver judges by the bus's
    # record, however far behind the storm leaves its receive thread. A drive the bus itself carried
    # no heartbeat of for its timeout (a simulated drive starved beside the storm in this process:
    # its lateness, not the driver's) may be, and only then (the verdict read above, the record
    # taken to past it).
    for drive in driver:
        stamps = beats[0x700 + drive.node_id]
        silent = max((b - a for a, b in itertools.pairwise(stamps)), default=0.0)
        if silent <= drive.config.heartbeat_timeout_s:
            assert not lost[drive.name], (drive.name, f"its heartbeats were on the bus at most {silent:.3f} s apart",
                                          lost_lines)
            assert not any(f"({drive.name}): heartbeat lost" in line for line in lost_lines), lost_lines


def test_an_emcy_error_reset_that_is_not_the_drivers_keeps_the_cause_of_the_fault(
        driver_factory: DriverFactory, listener_factory: ListenerFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    apply_action(sim, {"action": "fault", "node": 1, "code": 0x2310})
    wait_for(lambda: fault(drive.snapshot()) and drive.snapshot().error_code == 0x2310, 10.0, "the fault and its EMCY")
    heard = threading.Event()
    driver.buses["can0"].network.subscribe(0x081, lambda cob_id, data, timestamp: heard.set()
                                           if data[:2] == b"\0\0" else None)
    listener_factory(sim).send(can.Message(arbitration_id=0x081, data=bytes(8), is_extended_id=False))
    wait_for(heard.is_set, 10.0, "the spoofed error reset at the driver")
    state = drive.snapshot()
    health = drive_health(state, heartbeat_period_s=drive.config.heartbeat_period_s)
    assert state.error_code == 0x2310 and health.level == ERROR and health.message.startswith("faulted (FAULT: EMCY 0x2310")
    drive.recover()  # the driver's own reset clears it
    wait_for(lambda: not fault(drive.snapshot()), 10.0, "the fault reset")
    assert drive.snapshot().error_code == 0
