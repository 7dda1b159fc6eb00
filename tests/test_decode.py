"""Tier 1: the CANopen decoder, line by line, and on the real PCAN trace."""

from __future__ import annotations

import can
import pytest

from rovercan.decode import PdoField, candump_line, decode

from .conftest import SHARED_TRAFFIC


def m(cob: int, data: str = "", rtr: bool = False) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes.fromhex(data), is_extended_id=False, is_remote_frame=rtr,
                       dlc=1 if rtr else None)


@pytest.mark.parametrize(("msg", "text"), [
    (m(0x000, "8105"), "NMT RESET_NODE node 5"),
    (m(0x000, "0100"), "NMT START all nodes"),
    (m(0x080), "SYNC"),
    (m(0x081, "0152800000007008"), "EMCY node 1: 0x5201 device hardware: control, measurement circuit (error register 0x80)"),
    (m(0x70F, "05"), "heartbeat node 15: OPERATIONAL"),
    (m(0x70A, "85"), "heartbeat node 10: OPERATIONAL toggle"),
    (m(0x70A, rtr=True), "node guarding request node 10"),
    (m(0x701, "00"), "BOOT-UP node 1"),
    (m(0x601, "4018100100000000"), "node 1: SDO read 0x1018:1"),
    (m(0x581, "43181001564f5200"), "node 1: SDO reply 0x1018:1 = 56 4f 52 00 (5394262)"),
    (m(0x581, "8034120000000206"), "node 1: SDO response ABORT 0x1234:0 0x06020000 object does not exist in the object dictionary"),
    (m(0x601, "2b17100064000000"), "node 1: SDO write 0x1017:0 = 64 00 (100)"),
    (m(0x181, "3706"), "TPDO1 node 1: 37 06"),
    (m(0x10A, "c289230e998c0000"), "0x10A (not a predefined CANopen id): c2 89 23 0e 99 8c 00 00"),
])
def test_decode_lines(msg: can.Message, text: str) -> None:
    assert decode(msg) == text


def test_pdo_decoded_by_mapping() -> None:
    layouts = {0x181: (PdoField("statusword", "<H"), PdoField("mode", "<b"))}
    assert decode(m(0x181, "370601"), layouts) == "TPDO1 node 1: statusword=0x0637, mode=1"


def test_candump_line() -> None:
    assert candump_line(m(0x181, "3706")) == "  can0  181   [2]  37 06"


@pytest.mark.skipif(not (SHARED_TRAFFIC / "hilch_pcan2_canopen301.trc").is_file(),
                    reason="../shared/traffic is absent (only the team's checkout has it)")
def test_real_pcan_trace_decodes() -> None:
    lines = [decode(msg) for msg in can.LogReader(str(SHARED_TRAFFIC / "hilch_pcan2_canopen301.trc"))]
    assert len(lines) > 6000
    assert any(line.startswith("heartbeat node 15: OPERATIONAL") for line in lines)
    assert any("SDO" in line for line in lines)
    assert any(line.startswith("TPDO") for line in lines)
