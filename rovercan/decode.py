"""CANopen-decoded text for one frame (pure): NMT, SYNC, TIME, EMCY with its text, TPDO/RPDO
(decoded by mapping when one is known), SDO requests/responses/aborts with their meaning,
heartbeats and node guarding, LSS. Used by ``rovercan monitor`` and ``rovercan decode``."""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass

import can

from can_config.objects import NmtCommand, NmtState, emcy_text, sdo_abort_text
from motor_driver.protocol.errorframes import decode_error_frame

PDO_NAMES = {0x180: "TPDO1", 0x200: "RPDO1", 0x280: "TPDO2", 0x300: "RPDO2", 0x380: "TPDO3", 0x400: "RPDO3",
             0x480: "TPDO4", 0x500: "RPDO4"}


@dataclass(frozen=True)
class PdoField:
    name: str
    fmt: str  # struct format of one field, e.g. "<H"


PdoLayouts = Mapping[int, tuple[PdoField, ...]]  # COB-ID -> fields


def node_of(msg: can.Message) -> int | None:
    """The node id a frame belongs to (None for broadcast / non-CANopen ids)."""
    cob = msg.arbitration_id
    if cob == 0x000 and len(msg.data) >= 2 and msg.data[1]:
        return int(msg.data[1])  # an NMT command addressed to one node
    if msg.is_extended_id or cob in (0x000, 0x080, 0x100) or cob >= 0x7E4:
        return None
    node = cob & 0x7F
    return node or None


def _state_name(value: int) -> str:
    try:
        return NmtState(value).name
    except ValueError:
        return f"0x{value:02X}"


def _sdo(kind: str, data: bytes) -> str:
    if len(data) < 4:
        return f"{kind} (short frame: {data.hex(' ')})"
    cs = data[0] >> 5
    index, sub = struct.unpack_from("<HB", data, 1)
    where = f"0x{index:04X}:{sub}"
    if cs == 4:
        code = struct.unpack_from("<I", data, 4)[0] if len(data) >= 8 else 0
        return f"{kind} ABORT {where} 0x{code:08X} {sdo_abort_text(code)}"
    if kind == "SDO request":
        if cs == 2:
            return f"SDO read {where}"
        if cs == 1:
            if data[0] & 0x02:
                return f"SDO write {where} = {_expedited(data)}"
            return f"SDO write {where} (segmented)"
        if cs in (0, 3):
            return f"SDO {'download' if cs == 0 else 'upload'} segment"
        return f"SDO request cs={cs}"
    if cs == 2:
        if data[0] & 0x02:
            return f"SDO reply {where} = {_expedited(data)}"
        return f"SDO reply {where} (segmented, {int.from_bytes(data[4:8], 'little')} bytes)"
    if cs == 3:
        return f"SDO write {where} ok"
    if cs in (0, 1):
        return "SDO segment"
    return f"SDO response cs={cs}"


def _expedited(data: bytes) -> str:
    """The payload of an expedited SDO frame, as bytes and as a little-endian number."""
    n = (data[0] >> 2) & 3 if data[0] & 1 else 0
    payload = data[4:8 - n]
    return f"{payload.hex(' ')} ({int.from_bytes(payload, 'little')})"


def decode(msg: can.Message, pdo_layouts: PdoLayouts | None = None) -> str:
    """One line of CANopen meaning for a frame."""
    cob = msg.arbitration_id
    data = bytes(msg.data)
    if msg.is_error_frame:
        return f"error frame: {decode_error_frame(msg.arbitration_id, bytes(msg.data)).text}"
    if msg.is_extended_id:
        return f"extended id 0x{cob:08X} (not CANopen)"
    fn, node = cob & 0x780, cob & 0x7F
    service = _decode_service(msg, cob, fn, node, data)
    if service is not None:
        return service
    if fn == 0x580 and node:
        return f"node {node}: " + _sdo("SDO response", data)
    if fn == 0x600 and node:
        return f"node {node}: " + _sdo("SDO request", data)
    if cob in (0x7E4, 0x7E5):
        return "LSS " + ("response" if cob == 0x7E4 else "request")
    base = cob - node if node else cob
    if base in PDO_NAMES and node:
        return _decode_pdo(PDO_NAMES[base], cob, node, data, pdo_layouts)
    return f"0x{cob:03X} (not a predefined CANopen id): {data.hex(' ')}"


def _decode_service(msg: can.Message, cob: int, fn: int, node: int, data: bytes) -> str | None:
    """NMT, SYNC, TIME, EMCY and heartbeat / node guarding frames; None for any other."""
    if cob == 0x000:
        if len(data) < 2:
            return "NMT (short frame)"
        try:
            command = NmtCommand(data[0]).name
        except ValueError:
            command = f"0x{data[0]:02X}"
        return f"NMT {command} {'all nodes' if data[1] == 0 else f'node {data[1]}'}"
    if cob == 0x080:
        return "SYNC" + (f" counter {data[0]}" if data else "")
    if cob == 0x100:
        return "TIME"
    if fn == 0x080 and node:
        if len(data) < 3:
            return f"EMCY node {node} (short frame)"
        code, register = struct.unpack_from("<HB", data)
        return f"EMCY node {node}: 0x{code:04X} {emcy_text(code)} (error register 0x{register:02X})"
    if fn == 0x700 and node:
        if msg.is_remote_frame:
            return f"node guarding request node {node}"
        if not data:
            return f"heartbeat node {node} (empty)"
        if data[0] == 0:
            return f"BOOT-UP node {node}"
        toggle = " toggle" if data[0] & 0x80 else ""
        return f"heartbeat node {node}: {_state_name(data[0] & 0x7F)}{toggle}"
    return None


def _decode_pdo(name: str, cob: int, node: int, data: bytes, pdo_layouts: PdoLayouts | None) -> str:
    """A PDO by the driver's mapping where one is known, else its bytes."""
    fields = (pdo_layouts or {}).get(cob)
    if fields:
        try:
            values = struct.unpack("<" + "".join(f.fmt[1:] for f in fields), data[:struct.calcsize(
                "<" + "".join(f.fmt[1:] for f in fields))])
            return f"{name} node {node}: " + ", ".join(
                f"{f.name}={_fmt_value(f.name, v)}" for f, v in zip(fields, values, strict=True))
        except struct.error:
            pass
    return f"{name} node {node}: {data.hex(' ')}"


def _fmt_value(name: str, value: object) -> str:
    if isinstance(value, int) and name in ("statusword", "controlword"):
        return f"0x{value:04X}"
    return str(value)


def candump_line(msg: can.Message, channel: str = "can0") -> str:
    """``  can0  181   [2]  37 06`` as candump prints it."""
    cob = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    body = "remote request" if msg.is_remote_frame else " ".join(f"{b:02X}" for b in msg.data)
    return f"  {channel}  {cob}   [{msg.dlc}]  {body}"
