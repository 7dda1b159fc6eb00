"""Tier 1: the PDO plan, the SDO writes that configure it, and RPDO payloads, byte for byte."""

from __future__ import annotations

import struct

import pytest

from can_config import GENERIC_EDS, load_drive_od, load_od
from can_config.objects import OD
from motor_driver.protocol.pdo import encode_rpdo, mapping_writes, plan_pdos

from .conftest import SHARED_EDS, requires_shared


def test_generic_plan() -> None:
    plan = plan_pdos(load_drive_od(GENERIC_EDS, 5), 5)
    assert [p.indexes for p in plan.rpdos] == [(0x6040,), (0x6040, 0x607A), (0x6040, 0x60FF), (0x6040, 0x6071)]
    assert [p.cob_id for p in plan.rpdos] == [0x205, 0x305, 0x405, 0x505]
    assert [p.indexes for p in plan.tpdos] == [(0x6041, 0x6061), (0x6064, 0x606C), (0x6077, 0x6041)]
    assert [p.trans_type for p in plan.tpdos] == [255, 1, 1]
    assert plan.sdo_only == ()


def test_mapping_writes_follow_the_cia301_procedure() -> None:
    plan = plan_pdos(load_drive_od(GENERIC_EDS, 1), 1)
    writes = [(i, s, d.hex()) for i, s, d, _ in mapping_writes(plan)]
    rpdo2 = writes[writes.index((0x1401, 1, "01030080")):][:7]
    assert rpdo2 == [
        (0x1401, 1, "01030080"),  # invalidate: COB-ID 0x301 with bit 31
        (0x1601, 0, "00"),  # mapping count 0
        (0x1601, 1, "10004060"),  # 0x6040 sub 0, 16 bits
        (0x1601, 2, "20007a60"),  # 0x607A sub 0, 32 bits
        (0x1601, 0, "02"),  # two objects
        (0x1401, 2, "ff"),  # event-driven
        (0x1401, 1, "01030000"),  # valid again
    ]
    # the unused TPDO4 is invalidated and nothing else
    assert (0x1803, 1, "81040080") in writes
    assert not any(i == 0x1A03 for i, _, _ in writes)


def test_rpdo_payload_bytes() -> None:
    plan = plan_pdos(load_drive_od(GENERIC_EDS, 1), 1)
    rpdo2 = plan.rpdo_with(OD.TARGET_POSITION)
    assert rpdo2 is not None
    assert encode_rpdo(rpdo2, {OD.CONTROLWORD: 0x3F, OD.TARGET_POSITION: -2}) == bytes.fromhex("3f00feffffff")
    assert struct.calcsize(rpdo2.struct_format) == 6


@requires_shared
def test_schunk_target_position_falls_back_to_sdo() -> None:
    od = load_drive_od(SHARED_EDS / "schunk_prl120.eds", 3)
    plan = plan_pdos(od, 3)
    assert plan.n_rpdo == 2
    assert OD.TARGET_POSITION in plan.sdo_only
    assert all(OD.TARGET_POSITION not in p.indexes for p in plan.rpdos)
    # its modes are homing and interpolated position: the second RPDO carries the IP set-point
    ip = plan.rpdo_with(OD.INTERPOLATION_DATA)
    assert ip is not None and ip.cob_id == 0x303
    assert encode_rpdo(ip, {OD.CONTROLWORD: 0x1F, OD.INTERPOLATION_DATA: 4096}) == bytes.fromhex("1f0000100000")
    assert (0x1601, 2, bytes.fromhex("2001c160"), "RPDO2 map 0x60C1") in mapping_writes(plan)  # 0x60C1:01, 32 bits


@requires_shared
def test_sample_eds_is_not_a_drive() -> None:
    from can_config.errors import EdsError
    load_od(SHARED_EDS / "python_canopen_sample.eds")  # parses ...
    with pytest.raises(EdsError, match=r"not a usable CiA 402 drive: the EDS lacks 0x6040 controlword"):
        load_drive_od(SHARED_EDS / "python_canopen_sample.eds")  # ... but is refused as a drive
