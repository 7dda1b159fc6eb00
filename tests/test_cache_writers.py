"""One writer per field of the state cache (motor_driver/drive/received/state.py): what a worker learns by
SDO (a mode switch confirmed, boot's seed), boot's NMT start and its guarding restart are fields
of their own, never a read-modify-write of the receive thread's. Each interleaving is forced by a
hook inside the receive thread's decoding (between its read of the state and its write)."""

from __future__ import annotations

import struct

from can_config import load_config
from can_config.eds import load_drive_od
from can_config.objects import NmtState
from motor_driver.drive.ledger import DriveRecord, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.protocol.pdo import plan_pdos
from motor_driver.protocol.units import Scale

from .conftest import REPO

ROVER = REPO / "config" / "rover.yaml"
STATUS_MODE, POSITION_VELOCITY = 0x181, 0x281  # the first wheel's TPDOs: (0x6041, 0x6061), (0x6064, 0x606C)


def ignore(event: object) -> None:
    """The cache's reports to a supervisor: none here."""


def cache() -> DriveCache:
    config = load_config(ROVER)
    d = config.drives[0]
    plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
    assert {p.cob_id for p in plan.tpdos} >= {STATUS_MODE, POSITION_VELOCITY}
    scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
    return DriveCache(d, None, plan, scale, sync_period_s=0.01, record=DriveRecord(),  # type: ignore[arg-type]
                      port=SupervisorPort(ignore, ignore))


def test_a_mode_noted_while_a_tpdo_is_decoded_is_not_rolled_back() -> None:
    c = cache()
    c.on_tpdo(STATUS_MODE, bytearray(struct.pack("<Hb", 0x0637, 1)), 1.0)  # profile position
    plausible = c.positions.plausible

    def worker_notes_meanwhile(*args: object) -> bool:  # inside on_tpdo: after its read, before its write
        c.note_mode(3)  # a switch to profile velocity confirmed by SDO on a worker
        return plausible(*args)  # type: ignore[arg-type]

    c.positions.plausible = worker_notes_meanwhile  # type: ignore[method-assign]
    c.on_tpdo(POSITION_VELOCITY, bytearray(struct.pack("<ii", 1234, 0)), 1.01)
    assert c.received.mode == 3  # the worker's fact stands
    assert c.received.position_counts == 1234  # and the receive thread's frame too
    c.positions.plausible = plausible  # type: ignore[method-assign]
    c.on_tpdo(POSITION_VELOCITY, bytearray(struct.pack("<ii", 1240, 0)), 1.02)
    assert c.received.mode == 3  # carried on by a TPDO that has no mode
    c.on_tpdo(STATUS_MODE, bytearray(struct.pack("<Hb", 0x0637, 1)), 1.03)
    assert c.received.mode == 1  # the drive's newer word wins


def test_boots_nmt_start_and_a_heard_state_each_have_their_field() -> None:
    c = cache()
    c.on_heartbeat(0x701, bytearray([NmtState.PRE_OPERATIONAL]), 1.0)
    assert c.nmt_state == "PRE_OPERATIONAL"
    c.note_started()  # boot, on its worker
    assert c.nmt_state == "OPERATIONAL" and c.last_heartbeat > 0
    c.on_heartbeat(0x701, bytearray([NmtState.STOPPED]), 1.1)  # heard after the start: the drive's word
    assert c.nmt_state == "STOPPED"


def test_a_guarding_restart_by_boot_starts_the_receive_threads_toggle_at_zero() -> None:
    c = cache()
    c.set_guarding(True)
    c.on_heartbeat(0x701, bytearray([NmtState.OPERATIONAL]), 1.0)  # toggle 0: counted, 1 expected next
    assert (c.guard_answers, c.guard_errors) == (1, 0)
    c.set_guarding(True)  # boot again (the drive reset): its toggle starts at 0
    c.on_heartbeat(0x701, bytearray([NmtState.OPERATIONAL]), 1.1)
    assert (c.guard_answers, c.guard_errors) == (2, 0)
