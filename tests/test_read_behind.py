"""A driver whose receive thread is behind the bus (a starved process: the frames wait in the
socket) blames itself, not the drives: a heartbeat overdue by the supervisor's clock is judged by
how far that thread has read on the bus's own time line, so drives that spoke are not declared
lost, told to stop or NMT-stopped; a drive that really fell silent meanwhile still is, once the
thread has read past its timeout.

The receive thread is held by a callback of its own (a frame only the test sends), a hook inside
the critical section, not a clock: the drives' heartbeats sent meanwhile are counted by an
independent client of the bus, and the supervisor is shown to have judged after the timeout had
passed (two round trips through its own inbox). The bound past which the clock judges alone
(READ_BEHIND_MAX_S: a receive thread that stopped reading) is set long for those two, and short
for the third, which shows that bound."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from motor_driver.bus.adapters import watch_idle
from motor_driver.diagnostics.health import drive_health, with_boot
from motor_driver.runtime import supervisor as supervisor_module
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

HOLD_ID, MARK_ID = 0x7F0, 0x7F1  # no CANopen service's, nobody else's on the test bus
TIMEOUT_MS = 300.0
#: heartbeats each talking drive sends while the thread is held: past the timeout at their 100 ms period
HELD_HEARTBEATS = 6


class Hold:
    """Holds the bus's receive thread in a callback of its own until released."""

    def __init__(self, driver: MotorDriver) -> None:
        self.holding, self.release = threading.Event(), threading.Event()
        driver.buses["can0"].network.subscribe(HOLD_ID, self._held)

    def _held(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        self.holding.set()
        self.release.wait(60.0)


def heartbeats_while_held(sim: SimService, listener_factory: ListenerFactory, hold: Hold,
                          talking: tuple[int, ...], meanwhile: Callable[[], object] = lambda: None) -> dict[int, int]:
    """Send the hold's frame; once the receive thread is held, ``meanwhile``, then a marker
    frame; count each node's heartbeats on the bus after the marker until every ``talking`` node
    has sent HELD_HEARTBEATS (the listener shown to listen)."""
    listener, sender = listener_factory(sim), listener_factory(sim)
    try:
        sender.send(can.Message(arbitration_id=HOLD_ID, data=b"\x01", is_extended_id=False))
        wait_for(hold.holding.is_set, 30.0, "the receive thread in the hold's callback")
        meanwhile()
        sender.send(can.Message(arbitration_id=MARK_ID, data=b"\x01", is_extended_id=False))
        seen: dict[int, int] = {}
        marked = False
        while not all(seen.get(node, 0) >= HELD_HEARTBEATS for node in talking):
            msg = listener.recv(10.0)
            assert msg is not None, f"the bus fell silent; heartbeats seen {seen}"
            marked = marked or msg.arbitration_id == MARK_ID
            if marked and 0x701 <= msg.arbitration_id <= 0x77F:
                seen[msg.arbitration_id - 0x700] = seen.get(msg.arbitration_id - 0x700, 0) + 1
        return seen
    finally:
        sender.shutdown()
        listener.shutdown()


@pytest.fixture
def read_behind_max(monkeypatch: pytest.MonkeyPatch) -> Callable[[float], None]:
    """Set the supervisor's READ_BEHIND_MAX_S (a long one: no starved test reaches it)."""
    return lambda seconds: monkeypatch.setattr(supervisor_module, "READ_BEHIND_MAX_S", seconds)


def health_of(driver: MotorDriver, name: str) -> dict[str, str]:
    """The drive's /diagnostics values as the driver node grades them (its boots' ledger with them)."""
    drive = driver.drive(name)
    health = drive_health(drive.snapshot(), heartbeat_period_s=drive.config.heartbeat_period_s)
    return with_boot(health, driver.supervisor.records[name]).values


def judged(driver: MotorDriver) -> None:
    """Return once the supervisor has run a whole period (its drives judged) after this call."""
    driver.supervisor.call(lambda: None)
    driver.supervisor.call(lambda: None)


def test_drives_that_spoke_while_the_receive_thread_was_held_are_not_lost(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, caplog: pytest.LogCaptureFixture,
        read_behind_max: Callable[[float], None]) -> None:
    read_behind_max(600.0)
    sim, driver = driver_factory(make_config(2, heartbeat_timeout_ms=TIMEOUT_MS))
    hold = Hold(driver)
    caplog.set_level(logging.INFO)
    try:
        heartbeats_while_held(sim, listener_factory, hold, (1, 2))
        judged(driver)
        for drive in driver:  # overdue by the clock, read by nobody: judged as the driver's lateness
            assert not drive.cache.lost, drive.name
            record = driver.supervisor.records[drive.name]
            assert record.lost_stops == 0 and record.read_behind and record.read_behind_episodes >= 1, drive.name
    finally:
        hold.release.set()
    for drive in driver:
        before = drive.cache.heartbeats
        wait_for(lambda d=drive, n=before: d.cache.heartbeats > n, 30.0, f"{drive.name}'s heartbeats read")
    judged(driver)
    for drive in driver:
        record = driver.supervisor.records[drive.name]
        assert not drive.cache.lost and record.lost_stops == 0 and not record.read_behind, drive.name
    said = caplog.text
    assert "this driver is behind" in said and "heartbeat lost" not in said
    values = {drive.name: health_of(driver, drive.name) for drive in driver}
    assert all(int(v["heartbeat_read_behind"]) >= 1 for v in values.values()), values


def test_a_drive_that_fell_silent_while_the_receive_thread_was_held_is_still_lost(
        driver_factory: DriverFactory, listener_factory: ListenerFactory,
        read_behind_max: Callable[[float], None]) -> None:
    read_behind_max(600.0)
    sim, driver = driver_factory(make_config(2, heartbeat_timeout_ms=TIMEOUT_MS))
    hold = Hold(driver)
    try:
        seen = heartbeats_while_held(sim, listener_factory, hold, (2,),
                                     lambda: apply_action(sim, {"action": "tx_dead", "node": 1}))
        assert 1 not in seen, seen  # joint1 silent on the bus itself
        judged(driver)
        assert not driver.drive("joint1").cache.lost  # not yet read that far: not judged
    finally:
        hold.release.set()
    wait_for(lambda: driver.drive("joint1").cache.lost, 30.0, "joint1 declared lost once read past its timeout")
    assert not driver.drive("joint2").cache.lost
    assert driver.supervisor.records["joint2"].lost_stops == 0


def test_a_receive_thread_held_past_the_bound_leaves_the_verdict_to_the_clock(
        driver_factory: DriverFactory, listener_factory: ListenerFactory,
        read_behind_max: Callable[[float], None]) -> None:
    """A receive thread that no longer reads cannot excuse a silence for ever: past the bound the
    drives are declared lost (and told to stop) while it is still held."""
    read_behind_max(0.1)
    sim, driver = driver_factory(make_config(1, heartbeat_timeout_ms=TIMEOUT_MS))
    hold = Hold(driver)
    try:
        heartbeats_while_held(sim, listener_factory, hold, (1,))
        wait_for(lambda: driver.drive("joint1").cache.lost, 30.0, "joint1 declared lost by the clock")
        assert hold.holding.is_set() and not hold.release.is_set()
    finally:
        hold.release.set()


def test_a_drive_silent_on_an_otherwise_silent_bus_is_lost_though_no_frame_moves_the_read_stamp(
        driver_factory: DriverFactory, read_behind_max: Callable[[float], None]) -> None:
    """One drive, the SYNC from the driver's own thread (its socket does not hear its own frames):
    once the drive's transmitter dies no frame comes at all, so nothing the bus stamps shows how
    far the receive thread has read; its waits that come back empty do (BusStats.idle_at), and
    the drive is declared lost without the bound's help (set far beyond the test's wait)."""
    read_behind_max(600.0)
    config = make_config(1, bus_keys={"sync_timer": "thread"}, heartbeat_timeout_ms=TIMEOUT_MS)
    sim, driver = driver_factory(config)
    assert driver.buses["can0"].foreign.own_sync_period_s == 0.0  # its SYNC does not come back to it
    cache = driver.drive("joint1").cache
    heard = cache.heartbeats
    wait_for(lambda: cache.heartbeats > heard, 30.0, "a heartbeat after the boot")  # judged by its stamp, not the boot's
    assert cache.heartbeat_stamp
    apply_action(sim, {"action": "tx_dead", "node": 1})
    record = driver.supervisor.records["joint1"]
    # lost, then told to stop: the supervisor marks it lost before it sends the stop (another
    # thread can read the mark in between), so the stop is waited for, not asserted at the mark
    wait_for(lambda: driver.drive("joint1").cache.lost and record.lost_stops >= 1, 30.0,
             "joint1 declared lost on a silent bus and told to stop")


def test_a_bus_read_a_frame_at_a_time_tells_each_wait_that_came_back_empty() -> None:
    """The kernel path's evidence (python-can's own receive, here its virtual interface): a wait
    with nothing is told, one that brought a frame is not."""
    told: list[float] = []
    reader = watch_idle(can.Bus(interface="virtual", channel="read-behind", receive_own_messages=False),
                        told.append)
    writer = can.Bus(interface="virtual", channel="read-behind")
    try:
        assert reader.recv(0.01) is None and len(told) == 1
        writer.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        msg = reader.recv(10.0)
        assert msg is not None and msg.arbitration_id == 0x701 and len(told) == 1
    finally:
        reader.shutdown()
        writer.shutdown()


def test_an_empty_wait_is_told_with_when_it_began_and_a_second_watch_replaces_the_first() -> None:
    """The evidence is the wait's start, taken before the bus's own receive is entered (a hold of
    the thread after the wait came back proves nothing of what came meanwhile), and a bus watched
    again (handed to a second driver) tells only its newest watcher, once a wait."""
    bus = can.Bus(interface="virtual", channel="read-behind-start", receive_own_messages=False)
    entered: list[float] = []
    own = bus._recv_internal

    def recv_internal(timeout: float | None) -> tuple[can.Message | None, bool]:
        entered.append(time.monotonic())
        got: tuple[can.Message | None, bool] = own(timeout)
        return got

    bus._recv_internal = recv_internal  # the bus's own receive, seen from inside the watch
    first: list[float] = []
    second: list[float] = []
    try:
        watch_idle(bus, first.append)
        assert bus.recv(0.02) is None and len(first) == 1 and first[0] <= entered[-1]
        watch_idle(bus, second.append)
        assert bus.recv(0.02) is None
        assert len(first) == 1 and len(second) == 1 and len(entered) == 2 and second[0] <= entered[-1]
    finally:
        bus.shutdown()


def test_a_drive_silent_on_a_bus_read_a_frame_at_a_time_is_lost_by_its_empty_waits(
        read_behind_max: Callable[[float], None]) -> None:
    """The kernel buses' path in a running driver (python-can's receive, a frame at a time, here
    its virtual interface; the simulated drive on another handle of that channel): with the bound
    out of reach, only the receive thread's empty waits can prove the silence of a drive that was
    heard, once its transmitter dies on a bus with no other frame for the driver."""
    from can_config import load_drive_od, parse_config
    from virtual_can.sim import MotorParams, SimulatedDrive
    from virtual_can.sim.runner import DriveSimulator

    read_behind_max(600.0)
    channel = f"read-behind-frames-{id(read_behind_max)}"
    config = parse_config({"buses": [{"name": "can0", "interface": "virtual", "channel": channel}],
                           "drives": [{"name": "joint1", "node_id": 1, "heartbeat_timeout_ms": TIMEOUT_MS,
                                       "host_timeout_ms": 2000}]})
    spec = config.drives[0]
    drive = SimulatedDrive(1, load_drive_od(spec.eds, 1), MotorParams.from_model(spec.sim, spec.counts_per_rev),
                           name="joint1")
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as sim_bus, \
            DriveSimulator(sim_bus, [drive], realtime=False) as runner:
        runner.start()
        with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as bus, \
                MotorDriver(config, {"can0": bus}) as driver:
            driver.start()
            cache = driver.drive("joint1").cache
            heard = cache.heartbeats
            wait_for(lambda: cache.heartbeats > heard, 30.0, "a heartbeat after the boot")
            assert cache.heartbeat_stamp and not cache.lost
            drive.faults.tx_dead = True
            wait_for(lambda: cache.lost, 30.0, "joint1 declared lost on a bus read a frame at a time")
            assert driver.buses["can0"].stats.idle_at > 0.0
