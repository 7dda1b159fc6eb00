"""The simulated drive's synchronous TPDOs carry its actual position at the SYNC's moment, as a
CiA 402 drive latches it (issue 70): the simulator's physics ticks every few ms and answered a SYNC
with the position of its last tick, up to a tick old, so that two buses' samples of one SYNC moment
told two moments apart (a straight drive's heading swung). Exact values of one drive, no bus, no
clock: the runner's time and the bus's stamps are given."""

from __future__ import annotations

import struct

import can
import pytest

from can_config import GENERIC_EDS, load_drive_od
from can_config.objects import OD, OperationMode
from virtual_can.sim import SimulatedDrive
from virtual_can.sim.drive import State as SimState
from virtual_can.sim.drive.model import Pdo

TICK_S = 0.01
POSITION_TPDO = 0x281
#: the bus's clock is the runner's plus this (a wall clock against a monotonic one)
BUS_AHEAD_S = 1000.0
SPEED_COUNTS_S = 100_000


def cruising() -> SimulatedDrive:
    """A drive turning at a steady speed (profile velocity), a synchronous TPDO with its position."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.on_frame(can.Message(arbitration_id=0x000, data=[0x01, 1], is_extended_id=False), 0.0)  # NMT start
    drive.tpdos.append(Pdo(POSITION_TPDO, 1, [(OD.POSITION_ACTUAL, 0, "<i")]))
    drive.store.values[(OD.MODES_OF_OPERATION_DISPLAY, 0)] = int(OperationMode.PROFILE_VELOCITY)
    drive.store.values[(OD.PROFILE_ACCELERATION, 0)] = 400_000
    drive.store.values[(OD.TARGET_VELOCITY, 0)] = SPEED_COUNTS_S
    drive.state = SimState.OPERATION_ENABLED
    return drive


def sync(drive: SimulatedDrive, handled: float, on_bus: float) -> int:
    """A SYNC that was on the bus at ``on_bus`` (runner's time), handled at ``handled``: the position
    its TPDO carries."""
    msg = can.Message(arbitration_id=0x080, timestamp=on_bus + BUS_AHEAD_S, is_extended_id=False)
    out = [m for m in drive.on_frame(msg, handled) if m.arbitration_id == POSITION_TPDO]
    assert len(out) == 1
    return int(struct.unpack("<i", out[0].data)[0])


@pytest.mark.parametrize(("into_tick", "late"), [(0.003, 0.0), (0.008, 0.0), (0.004, 0.005)])
def test_a_sync_tpdo_carries_the_position_at_the_syncs_moment(into_tick: float, late: float) -> None:
    """A SYNC ``into_tick`` after the last physics tick (handled ``late`` after it was on the bus: a
    runner held meanwhile): its TPDO says where the shaft was at the SYNC, which a twin drive ticked
    to that very moment shows, within a count; the last tick's position is thousands of counts off."""
    drive, twin = cruising(), cruising()
    now = 0.0
    while now < 1.0:  # at speed; the SYNCs before teach the drive the bus's clock (handled at once)
        sync(drive, now, now)
        now += TICK_S
        drive.tick(now, TICK_S)
        twin.tick(now, TICK_S)
    last_tick = drive.position_counts
    assert abs(drive.omega / drive._rad_per_count - SPEED_COUNTS_S) < 0.01 * SPEED_COUNTS_S
    latched = sync(drive, now + into_tick + late, now + into_tick)
    twin.tick(now + into_tick, into_tick)  # the plant at the SYNC's moment
    assert abs(latched - twin.position_counts) <= 2.0, (latched, twin.position_counts, last_tick)
    assert abs(latched - last_tick) > 0.5 * SPEED_COUNTS_S * into_tick  # not the last tick's
    drive.tick(now + TICK_S, TICK_S)
    assert drive.store.values[(OD.POSITION_ACTUAL, 0)] == round(drive.position_counts)  # the tick's own again


def test_a_late_answer_leaves_when_due_with_the_syncs_position_and_in_order() -> None:
    """``Faults.sync_delay_s`` (a slow drive, a busy bus): a SYNC's answer is held, not sent, and
    leaves that long after the SYNC's moment (when the runner asks at its ``next_release``, not at a
    tick), carrying the position of the SYNC's moment; an SDO answer the drive made meanwhile leaves
    after it, never before (one transmit queue)."""
    drive, twin = cruising(), cruising()
    now = 0.0
    while now < 1.0:
        sync(drive, now, now)
        now += TICK_S
        drive.tick(now, TICK_S)
        twin.tick(now, TICK_S)
    drive.faults.sync_delay_s = 0.03
    at = now + 0.004
    assert drive.on_frame(can.Message(arbitration_id=0x080, timestamp=at + BUS_AHEAD_S, is_extended_id=False), at) == []
    twin.tick(at, 0.004)  # the plant at the SYNC's moment
    assert drive.next_release == pytest.approx(at + 0.03)
    upload = can.Message(arbitration_id=0x601, data=[0x40, 0x41, 0x60, 0, 0, 0, 0, 0], is_extended_id=False)
    assert drive.on_frame(upload, at + 0.001) == []  # behind the held answer
    drive.tick(now + TICK_S, TICK_S)  # time moves on: nothing leaves before it is due
    assert drive.release(at + 0.029) == []
    out = drive.release(at + 0.0301)
    ids = [m.arbitration_id for m in out]
    assert POSITION_TPDO in ids and ids[-1] == 0x581 and drive.next_release is None, [hex(i) for i in ids]
    latched = struct.unpack("<i", out[ids.index(POSITION_TPDO)].data)[0]
    assert abs(latched - twin.position_counts) <= 2.0, (latched, twin.position_counts)
