"""A statusword latched at a SYNC never replaces a newer one the drive sent on a change.

A CiA 402 drive latches its synchronous TPDOs at the SYNC and queues them; a change right after
(a fault, a transition) sends the statusword's event TPDO1, whose lower identifier wins the bus
before the TPDO3 latched earlier. Received in that order, the TPDO3 would show the state before
the change for a SYNC period: a fault shown as Operation Enabled again, an old set-point
acknowledge handed to the handshake. The cache keeps the newer one
(``DriveCache._keeps_newer_statusword``).

The first tests feed a cache on a canopen network of its own (no bus) frames with their bus
stamps, as tests/test_sync_stamps.py does. The last drives the simulator's latched fault (the
scenario step ``{action: fault, latched: true}``: its frames leave by identifier) and records,
on the driver's own receive thread, the state the cache held after each TPDO; an independent
client shows that the stale TPDO3 was on the wire.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import can
import canopen
import pytest

from can_config import GENERIC_EDS, RoverConfig, load_config
from can_config.eds import load_drive_od
from can_config.objects import OD
from motor_driver import MotorDriver
from motor_driver.drive.ledger import DriveRecord, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.protocol.cia402 import FAULT_STATES, State, decode_state
from motor_driver.protocol.pdo import TT_SYNC, plan_pdos
from motor_driver.protocol.units import Scale
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import REPO, make_config, wait_for
from .test_cache_writers import STATUS_MODE, ignore

SYNC = 0x080
PERIOD_S = 0.01
OPERATION_ENABLED_SW = 0x0637
FAULT_SW = 0x0218
EMCY_OVER_CURRENT = 0x2310


def sync_statusword_tpdo(eds: object, node: int) -> tuple[int, struct.Struct, int]:
    """The synchronous TPDO carrying the statusword, as the driver maps it: its COB-ID, its
    layout and the statusword's place in it."""
    for pdo in plan_pdos(load_drive_od(eds, node), node).tpdos:  # type: ignore[arg-type]
        if pdo.trans_type == TT_SYNC and OD.STATUSWORD in pdo.indexes:
            return pdo.cob_id, pdo.codec, pdo.indexes.index(OD.STATUSWORD)
    raise AssertionError("no synchronous TPDO carries the statusword")


@pytest.fixture
def cache() -> DriveCache:
    d = load_config(REPO / "config" / "rover.yaml").drives[0]
    plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
    scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
    c = DriveCache(d, canopen.Network(), plan, scale, sync_period_s=PERIOD_S, record=DriveRecord(),
                   port=SupervisorPort(ignore, ignore))
    c.subscribe()
    return c


class Frames:
    """The first wheel's frames into ``cache``'s network, stamped."""

    def __init__(self, cache: DriveCache) -> None:
        d = cache.config
        self.net, self.cache = cache._network, cache
        self.cob, self.layout, self.place = sync_statusword_tpdo(d.eds, d.node_id)

    def sync(self, stamp: float) -> None:
        self.net.notify(SYNC, bytearray(), stamp)

    def event(self, sw: int, stamp: float) -> None:
        self.net.notify(STATUS_MODE, bytearray(struct.pack("<Hb", sw, 8)), stamp)

    def latched(self, sw: int, stamp: float) -> None:
        values = [0] * len(self.layout.unpack(bytes(self.layout.size)))
        values[self.place] = sw
        self.net.notify(self.cob, bytearray(self.layout.pack(*values)), stamp)

    @property
    def statusword(self) -> int:
        return self.cache.received.statusword


def test_a_latched_statusword_behind_a_newer_event_one_is_not_taken(cache: DriveCache) -> None:
    f = Frames(cache)
    f.sync(100.000)
    f.latched(OPERATION_ENABLED_SW, 100.0004)
    f.sync(100.010)  # latched Operation Enabled; then the fault, whose TPDO1 wins the bus
    f.event(FAULT_SW, 100.0102)
    seq = cache.status_seq
    f.latched(OPERATION_ENABLED_SW, 100.0104)
    assert f.statusword == FAULT_SW and cache.state in FAULT_STATES
    assert cache.status_seq == seq and cache.stale_statuswords == 1  # not counted as a statusword heard
    f.sync(100.020)
    f.latched(FAULT_SW, 100.0204)  # the next SYNC's: latched after the change, taken
    assert f.statusword == FAULT_SW and cache.status_seq == seq + 1 and cache.stale_statuswords == 1


def test_a_latched_statusword_newer_than_the_event_one_is_taken(cache: DriveCache) -> None:
    """An event TPDO sent before the SYNC is older than what the SYNC latched."""
    f = Frames(cache)
    f.sync(100.000)
    f.event(FAULT_SW, 100.0098)
    f.sync(100.010)
    f.latched(OPERATION_ENABLED_SW, 100.0104)  # recovered meanwhile (its own TPDO1 lost, or inhibited)
    assert f.statusword == OPERATION_ENABLED_SW and cache.stale_statuswords == 0


def test_without_its_sync_heard_a_latched_statusword_is_taken(cache: DriveCache) -> None:
    """A bus that does not show the driver its own SYNC (a kernel socket sending it): the TPDO keeps
    its own stamp, later than the event one, and is taken as before."""
    f = Frames(cache)
    f.event(FAULT_SW, 50.0002)
    f.latched(OPERATION_ENABLED_SW, 50.0004)
    assert f.statusword == OPERATION_ENABLED_SW and cache.stale_statuswords == 0


def test_a_bus_clock_stepped_back_does_not_stop_the_latched_statuswords(cache: DriveCache) -> None:
    """Only an event within a SYNC period after the latch can have passed it: an event stamp far
    ahead (a server's clock stepped back) never leaves the synchronous statuswords untaken for good."""
    f = Frames(cache)
    f.event(FAULT_SW, 900.0)
    f.sync(100.000)
    f.latched(OPERATION_ENABLED_SW, 100.0004)
    assert f.statusword == OPERATION_ENABLED_SW and cache.stale_statuswords == 0


DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]


def test_a_fault_whose_tpdo1_passes_the_latched_tpdo3_is_never_shown_as_enabled(
        driver_factory: DriverFactory, listener_factory: ListenerFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    cob, layout, place = sync_statusword_tpdo(GENERIC_EDS, 1)
    held: list[tuple[int, State]] = []  # (COB-ID, the cache's state after it), on the receive thread

    def record(can_id: int, data: bytearray, timestamp: float) -> None:
        held.append((can_id, drive.cache.state))

    network = driver.buses[drive.config.bus].network
    for tpdo in (STATUS_MODE, cob):
        network.subscribe(tpdo, record)  # after the cache's own callback: what it holds then
    listener = listener_factory(sim)
    apply_action(sim, {"action": "fault", "node": 1, "code": EMCY_OVER_CURRENT, "latched": True})

    # the wire: the fault's TPDO1, then the TPDO3 latched before it, still Operation Enabled
    newer = None
    while True:
        msg = listener.recv(30.0)
        assert msg is not None, "the latched fault's frames never came on the bus"
        if msg.arbitration_id == STATUS_MODE and decode_state(int.from_bytes(msg.data[:2], "little")) in FAULT_STATES:
            newer = msg
        elif msg.arbitration_id == cob and newer is not None:
            assert decode_state(layout.unpack(msg.data)[place]) == State.OPERATION_ENABLED, \
                "the TPDO3 after the fault's TPDO1 was latched after the fault: no race on the wire"
            break
        elif msg.arbitration_id == SYNC:
            assert newer is None, "a SYNC between the fault's TPDO1 and the latched TPDO3"

    def after_fault() -> list[tuple[int, State]]:
        first = next((i for i, (_, state) in enumerate(held) if state in FAULT_STATES), None)
        return [] if first is None else held[first:]

    # two TPDO3 handed on after the fault: the stale one and the next SYNC's
    wait_for(lambda: sum(c == cob for c, _ in after_fault()) >= 2, 30.0, "two TPDO3 after the fault read")
    seen = after_fault()
    assert all(state in FAULT_STATES for _, state in seen), f"the fault shown as enabled again: {seen}"
    assert drive.cache.stale_statuswords >= 1
