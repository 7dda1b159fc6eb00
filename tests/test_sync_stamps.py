"""A synchronous TPDO's values are stamped with the SYNC they answer (issue 70): a CiA 402 drive
latches its actual values at the SYNC, so two buses' samples are paired by the moment they
measured, not by when each answer reached the bus (a drive's, or a simulator's, reply time varies
by milliseconds). The cache on a canopen network of its own (no bus): frames notified as the bus's
receive thread notifies them, with their bus stamps."""

from __future__ import annotations

import struct

import canopen
import pytest

from can_config import load_config
from can_config.eds import load_drive_od
from motor_driver.drive.ledger import DriveRecord, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.protocol.pdo import plan_pdos
from motor_driver.protocol.units import Scale

from .conftest import REPO
from .test_cache_writers import POSITION_VELOCITY, STATUS_MODE, ignore

SYNC = 0x080
PERIOD_S = 0.01


@pytest.fixture
def network() -> canopen.Network:
    config = load_config(REPO / "config" / "rover.yaml")
    d = config.drives[0]
    plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
    scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
    net = canopen.Network()
    cache = DriveCache(d, net, plan, scale, sync_period_s=PERIOD_S, record=DriveRecord(), port=SupervisorPort(ignore, ignore))
    cache.subscribe()
    net.cache = cache  # type: ignore[attr-defined]
    return net


def position(net: canopen.Network, counts: int, stamp: float) -> float:
    net.notify(POSITION_VELOCITY, bytearray(struct.pack("<ii", counts, 0)), stamp)
    return float(net.cache.received.stamp)  # type: ignore[attr-defined]


def test_a_sync_tpdo_is_stamped_with_its_sync(network: canopen.Network) -> None:
    net = network
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.0043) == 100.000  # the answer, 4.3 ms later: measured at its SYNC
    net.notify(SYNC, bytearray(), 100.010)
    assert position(net, 1100, 100.0101) == 100.010  # answered at once: the same rule
    assert net.cache.received.position_counts == 1100  # type: ignore[attr-defined]


def test_without_its_sync_a_tpdo_keeps_its_own_stamp(network: canopen.Network) -> None:
    net = network
    assert position(net, 1000, 50.0) == 50.0  # no SYNC heard (a kernel socket sending this driver's own)
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.002) == 100.000
    assert position(net, 1010, 100.008) == 100.008  # its SYNC not heard: not the one before, taken already
    assert position(net, 1020, 100.0125) == 100.0125  # more than a period after the newest SYNC
    net.notify(SYNC, bytearray(), 100.020)
    net.notify(STATUS_MODE, bytearray(struct.pack("<Hb", 0x0637, 1)), 100.021)  # event-driven: when it was sent
    assert net.cache.received.stamp == 100.021  # type: ignore[attr-defined]


def test_a_late_answer_keeps_the_sync_it_answers(network: canopen.Network) -> None:
    """The answer to one SYNC reaching the bus after the next (a drive or a simulator late) carries
    what was latched at the first: it is stamped with it, and the next answer with the next SYNC,
    never the first one period too new (the review's case: 100.030 for a value of 100.020)."""
    net = network
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.004) == 100.000
    net.notify(SYNC, bytearray(), 100.010)  # its answer is late: after the next SYNC
    net.notify(SYNC, bytearray(), 100.020)
    assert position(net, 1100, 100.0235) == 100.010  # the late answer: latched at 100.010
    assert position(net, 1200, 100.0245) == 100.020  # the answer to 100.020, on time
    net.notify(SYNC, bytearray(), 100.030)
    assert position(net, 1300, 100.034) == 100.030


def test_an_answer_after_a_silence_is_the_newest_syncs(network: canopen.Network) -> None:
    """A TPDO back after several SYNCs without an answer (a drive silent, a bus back) answers the
    newest SYNC, not the one before it."""
    net = network
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.004) == 100.000
    for k in range(1, 5):
        net.notify(SYNC, bytearray(), 100.000 + 0.010 * k)
    assert position(net, 1400, 100.043) == pytest.approx(100.040)


def test_an_answer_later_than_the_period_still_counts_its_sync(network: canopen.Network) -> None:
    """An answer that comes more than a period after its SYNC (the next SYNC late too) keeps its own
    stamp, and the SYNC it answered is counted: the next answer, after the next SYNC, is stamped with
    that SYNC, and every one after it with its own (before: with the SYNC before, ever after)."""
    net = network
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.004) == 100.000
    net.notify(SYNC, bytearray(), 100.010)
    assert position(net, 1100, 100.0205) == 100.0205  # 10.5 ms after its SYNC: beyond the period
    net.notify(SYNC, bytearray(), 100.022)  # the next SYNC, late
    assert position(net, 1200, 100.024) == 100.022
    net.notify(SYNC, bytearray(), 100.030)
    assert position(net, 1300, 100.034) == 100.030


def test_after_a_lost_answer_the_answers_are_the_newest_syncs_again(network: canopen.Network) -> None:
    """One answer lost (frame loss): the next, after the next SYNC, cannot be told from a late answer
    to the lost one's SYNC and is stamped with it; the one after it, again after the next SYNC, says
    the drive answers the newest SYNC: stamped with it, and so on (before: a period early, ever after)."""
    net = network
    net.notify(SYNC, bytearray(), 100.000)
    assert position(net, 1000, 100.004) == 100.000
    net.notify(SYNC, bytearray(), 100.010)  # its answer lost
    net.notify(SYNC, bytearray(), 100.020)
    assert position(net, 1200, 100.024) == 100.010  # taken for the late answer to 100.010
    net.notify(SYNC, bytearray(), 100.030)
    assert position(net, 1300, 100.034) == 100.030
    net.notify(SYNC, bytearray(), 100.040)
    assert position(net, 1400, 100.044) == 100.040
