"""Bench commands that address one node over CiA 301 services: scan, info, sdo, save, nmt.

Owner: the CLI's main thread.
"""

from __future__ import annotations

import argparse
import logging
import struct
import sys
import time
from collections.abc import Callable
from typing import Any

import can
import can.cli
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config import GENERIC_EDS, load_od
from can_config.eds import variable
from can_config.errors import ConfigError
from can_config.objects import OD, SUPPORTED_MODE_BIT, NmtCommand, NmtState, OperationMode
from motor_driver.protocol.codec import pack_value, unpack_value, value_format
from rovercan.argtypes import real, whole
from rovercan.bench.common import (
    CAUSES,
    CliError,
    _heard_from,
    _text,
    _u8,
    _u32,
    _untyped,
    add_bus_args,
    add_config_arg,
    add_json,
    add_master_flags,
    emit,
    open_bus,
    parse_index,
    receive,
    refuse_beside_a_master,
    remote_node,
    resolve_drive,
    sdo_download,
    sdo_upload,
)
from rovercan.decode import node_of

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ scan
def cmd_scan(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    bus = open_bus(args)
    found: dict[int, dict[str, Any]] = {}
    try:
        ids = range(1, 128)
        for node_id in tqdm(ids, desc="probing 0x1000", disable=args.json, file=sys.stderr,
                            bar_format="{desc}: {bar} {n_fmt}/{total_fmt} node ids"):  # no rate: sends are instant
            bus.send(can.Message(arbitration_id=0x600 + node_id, data=bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]),
                                 is_extended_id=False))
        deadline = time.monotonic() + args.listen
        while (remaining := deadline - time.monotonic()) > 0:
            msg = receive(bus, remaining)
            if msg is None:
                continue
            node = node_of(msg)
            if node is None:
                continue
            if msg.arbitration_id == 0x580 + node and msg.data[0] & 0xE0 == 0x40 and msg.data[1:3] == b"\x00\x10":
                found.setdefault(node, {})["device_type"] = f"0x{_u32(bytes(msg.data[4:])):08X}"
            elif msg.arbitration_id == 0x700 + node and msg.data and not msg.is_remote_frame:
                found.setdefault(node, {})["nmt"] = _state_name(msg.data[0] & 0x7F)
    finally:
        bus.shutdown()
    rows = []
    for node_id in sorted(found):
        row: dict[str, Any] = {"node": node_id, "device_type": found[node_id].get("device_type", "?"),
                               "nmt": found[node_id].get("nmt", "no heartbeat")}
        if "device_type" in found[node_id]:
            with remote_node(args, node_id) as (node, _):
                for sub, key in ((1, "vendor"), (2, "product"), (3, "revision")):
                    try:
                        row[key] = f"0x{_u32(sdo_upload(node, OD.IDENTITY, sub)):08X}"
                    except CliError:
                        row[key] = "?"
        rows.append(row)
    if not rows:
        print(f"rovercan scan: no node answered on the bus within {args.listen:g} s; {CAUSES}", file=sys.stderr)
        return 1
    emit(args, rows, "CANopen nodes", ["node", "device_type", "vendor", "product", "revision", "nmt"])
    return 0


def _state_name(value: int) -> str:
    try:
        return NmtState(value).name
    except ValueError:
        return f"0x{value:02X}"


# ------------------------------------------------------------------------------ info
def cmd_info(args: argparse.Namespace) -> int:
    node_id, drive = resolve_drive(args, args.node)
    with remote_node(args, node_id, drive) as (node, _):
        od = node.object_dictionary if len(node.object_dictionary) else load_od(GENERIC_EDS, node_id)
        info: dict[str, Any] = {"node": node_id, "device_type": f"0x{_u32(sdo_upload(node, OD.DEVICE_TYPE, 0)):08X}"}
        for sub, key in ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial")):
            try:
                info[key] = f"0x{_u32(sdo_upload(node, OD.IDENTITY, sub)):08X}"
            except CliError as err:
                info[key] = str(err)
        for index, key in ((OD.DEVICE_NAME, "device_name"), (OD.HARDWARE_VERSION, "hardware"),
                           (OD.SOFTWARE_VERSION, "firmware")):
            try:
                info[key] = _text(sdo_upload(node, index, 0))
            except CliError:
                info[key] = "(not available)"
        try:
            modes = _u32(sdo_upload(node, OD.SUPPORTED_DRIVE_MODES, 0))
            info["supported_modes"] = [m.name for m, b in SUPPORTED_MODE_BIT.items() if modes >> b & 1]
        except CliError:
            info["supported_modes"] = "(0x6502 not available)"
        info["rpdos"] = _pdo_mapping(node, od, OD.RPDO_COMM)
        info["tpdos"] = _pdo_mapping(node, od, OD.TPDO_COMM)
        info["error_register"] = f"0x{_u8(sdo_upload(node, OD.ERROR_REGISTER, 0)):02X}"
        history = []
        try:
            count = _u8(sdo_upload(node, OD.PREDEFINED_ERROR_FIELD, 0))
            for sub in range(1, count + 1):
                from can_config.objects import emcy_text
                code = _u32(sdo_upload(node, OD.PREDEFINED_ERROR_FIELD, sub)) & 0xFFFF
                history.append(f"0x{code:04X} {emcy_text(code)}")
        except CliError:
            history.append("(0x1003 not available)")
        info["error_history"] = history
    emit(args, info, f"node {node_id}")
    return 0


def _pdo_mapping(node: canopen.RemoteNode, od: ObjectDictionary, comm_base: int) -> list[str]:
    out = []
    for n in range(4):
        try:
            cob = _u32(sdo_upload(node, comm_base + n, 1))
        except CliError:
            break
        if cob & 0x8000_0000:
            out.append(f"{n + 1}: disabled")
            continue
        tt = _u8(sdo_upload(node, comm_base + n, 2))
        count = _u8(sdo_upload(node, comm_base + 0x200 + n, 0))
        names = []
        for sub in range(1, count + 1):
            entry = _u32(sdo_upload(node, comm_base + 0x200 + n, sub))
            index, subindex = entry >> 16, (entry >> 8) & 0xFF
            var = variable(od, index, subindex)
            names.append(f"0x{index:04X} {var.name}" if var is not None else f"0x{index:04X}:{subindex}")
        out.append(f"{n + 1}: 0x{cob & 0x7FF:03X} type {tt}: " + ", ".join(names))
    return out


# ------------------------------------------------------------------------------ sdo / nmt
def sdo_value_bytes(text: str, fmt: str | None, size: int, what: str) -> bytes:
    """VALUE of ``sdo write`` as the object's bytes (its EDS type, else --size bytes), or
    :class:`ConfigError` naming the value, the object and the allowed form."""
    try:
        number: int | float = float(text) if fmt in ("<f", "<d") else int(text, 0)
    except ValueError:
        kind = "a number" if fmt in ("<f", "<d") else "a whole number (decimal or 0x hex)"
        raise ConfigError(f"value {text!r} for {what}: expected {kind}") from None
    if fmt is None:
        low, high = -(1 << (8 * size - 1)), (1 << (8 * size)) - 1
        if not low <= int(number) <= high:
            raise ConfigError(f"value {text} for {what} does not fit --size {size} bytes ({low}..{high})")
        return int(number).to_bytes(size, "little", signed=int(number) < 0)
    try:
        return pack_value(fmt, number)
    except (struct.error, OverflowError) as err:
        raise ConfigError(f"value {text} does not fit {what} ({STRUCT_NAMES.get(fmt, fmt)}): {err}") from err


STRUCT_NAMES = {"<b": "INTEGER8", "<B": "UNSIGNED8", "<h": "INTEGER16", "<H": "UNSIGNED16", "<i": "INTEGER32",
                "<I": "UNSIGNED32", "<q": "INTEGER64", "<Q": "UNSIGNED64", "<f": "REAL32", "<d": "REAL64"}


def cmd_sdo(args: argparse.Namespace) -> int:
    node_id, drive = resolve_drive(args, args.node)
    index, sub = parse_index(args.index)
    with remote_node(args, node_id, drive) as (node, _):
        # without --eds/--config the standard objects of CiA 301/402 are still known: the
        # project's generic CiA 402 EDS lists them with their names and types
        od = node.object_dictionary if len(node.object_dictionary) else load_od(GENERIC_EDS, node_id)
        var = variable(od, index, sub)
        name = var.name if var is not None else ""
        fmt = value_format(od, index, sub)
        if args.action == "read":
            raw = sdo_upload(node, index, sub)
            value: Any = unpack_value(fmt, raw)
            if value is None:
                value = _text(raw) if var is not None and int(var.data_type) == 0x09 else _untyped(raw)
            row = {"node": node_id, "index": f"0x{index:04X}", "sub": sub, "name": name, "value": value,
                   "raw": raw.hex(" ")}
            if (meaning := standard_meaning(index, value)) is not None:
                row["meaning"] = meaning
            emit(args, row, f"node {node_id} 0x{index:04X}:{sub}")
            return 0
        if args.value is None:
            raise ConfigError("sdo write needs a VALUE")
        from motor_driver.drive import protected_reason
        reason = protected_reason(index)
        if reason is not None and not args.force:
            raise ConfigError(f"writing 0x{index:04X} by SDO is refused: {reason}. On the bench, --force writes"
                              " it anyway (logged)")
        if reason is not None:
            logger.warning("node %d: forced SDO write of protected 0x%04X:%d = %s (%s)", node_id, index, sub,
                           args.value, reason)
        data = sdo_value_bytes(args.value, fmt, args.size, f"0x{index:04X}:{sub}{f' ({name})' if name else ''}")
        sdo_download(node, index, sub, data)
        emit(args, {"node": node_id, "index": f"0x{index:04X}", "sub": sub, "written": data.hex(" ")}, "written")
    return 0


def standard_meaning(index: int, value: Any) -> str | None:
    """What a CiA 402 status, control or mode value says, in words (None: nothing to add)."""
    from motor_driver.protocol.cia402 import CW, SW, decode_state

    if not isinstance(value, int) or isinstance(value, bool):
        return None
    if index == OD.STATUSWORD:
        bits = [bit.name for bit in SW if value & bit]
        return f"{decode_state(value).name}: {', '.join(bits) or 'no bit set'}"
    if index == OD.CONTROLWORD:
        low = {0x0000: "disable voltage", 0x0002: "quick stop", 0x0006: "shutdown", 0x0007: "switch on",
               0x000F: "enable operation"}.get(value & 0x000F, f"0x{value & 0x0F:X}")
        bits = [bit.name for bit in CW if value & bit]
        return ", ".join([low, *bits])
    if index in (OD.MODES_OF_OPERATION, OD.MODES_OF_OPERATION_DISPLAY):
        try:
            return OperationMode(value).name
        except ValueError:
            return f"mode {value} (vendor-specific)" if value < 0 else f"mode {value} (unknown)"
    return None


#: A drive writes its flash on a save and may not answer SDOs meanwhile (about 400 ms seen).
SAVE_TIMEOUT_S = 3.0
SAVE_WHAT = {1: "all parameters", 2: "communication parameters", 3: "application parameters",
             4: "manufacturer parameters"}


def cmd_save(args: argparse.Namespace) -> int:
    """0x1010:SUB = "save": the drive keeps its current parameters over resets and power cycles."""
    node_id, drive = resolve_drive(args, args.node)
    with remote_node(args, node_id, drive) as (node, _):
        started = time.monotonic()
        sdo_download(node, OD.STORE_PARAMETERS, args.sub, b"save", SAVE_TIMEOUT_S, f"the save (0x1010:{args.sub})")
        took = time.monotonic() - started
    emit(args, {"node": node_id, "saved": SAVE_WHAT[args.sub], "object": f"0x1010:{args.sub}",
                "answer_ms": round(took * 1000)}, f"node {node_id} saved")
    return 0


NMT_COMMANDS = {"start": NmtCommand.START, "stop": NmtCommand.STOP, "preop": NmtCommand.ENTER_PREOPERATIONAL,
                "reset": NmtCommand.RESET_NODE, "reset-comm": NmtCommand.RESET_COMMUNICATION}
#: How long ``nmt`` waits for the addressed node to show itself (NMT has no reply of its own).
NMT_CONFIRM_S = 1.5


def cmd_nmt(args: argparse.Namespace) -> int:
    node_id = 0 if args.node == "all" else resolve_drive(args, args.node)[0]
    command = NMT_COMMANDS[args.action]
    bus = open_bus(args)
    try:
        refuse_beside_a_master(args, bus, range(1, 128) if node_id == 0 else (node_id,))
        # a node that is not there is an error, not "done": before a stop (a stopped node answers
        # no SDO), after a start or pre-op (it answers then), its boot-up after a reset
        present = bool(node_id) and command == NmtCommand.STOP and _heard_from(bus, node_id, 0.5, probe=True)
        bus.send(can.Message(arbitration_id=0, data=bytes([command, node_id]), is_extended_id=False))
        if node_id and not present:
            resets = command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION)
            if not _heard_from(bus, node_id, NMT_CONFIRM_S, probe=command != NmtCommand.STOP and not resets,
                               bootup=resets):
                raise CliError(f"node {node_id}: nothing heard from it within {NMT_CONFIRM_S:g} s of NMT {args.action}"
                               f" ({'no boot-up' if resets else 'no SDO answer or heartbeat'}); check the node id,"
                               " power, bitrate and termination")
    finally:
        bus.shutdown()
    emit(args, {"nmt": args.action, "node": args.node}, "NMT")
    return 0



def _node_options(p: argparse.ArgumentParser, func: Callable[[argparse.Namespace], int], *, eds_help: str = "",
                  master_flags: bool = False) -> None:
    """What every nodes command takes after its own arguments: the bus, an EDS (where it names
    objects), the rover config, --json; and the function that runs it."""
    add_bus_args(p)
    if eds_help:
        p.add_argument("--eds", help=eds_help)
    add_config_arg(p)
    if master_flags:
        add_master_flags(p)
    add_json(p)
    p.set_defaults(func=func)


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """The nodes commands' parsers."""
    p = sub.add_parser("scan", help="find CANopen nodes: heartbeats and an SDO probe of 0x1000/0x1018 over ids 1-127")
    p.add_argument("--listen", type=real(0.05, 600), default=1.2, help="seconds to collect answers and heartbeats")
    _node_options(p, cmd_scan)

    p = sub.add_parser("info", help="identity, firmware, modes, PDO mapping and error history of a node")
    p.add_argument("node")
    _node_options(p, cmd_info, eds_help="EDS for object names")

    p = sub.add_parser("sdo", help="SDO read or write (types and names from --eds)")
    p.add_argument("action", choices=("read", "write"))
    p.add_argument("node")
    p.add_argument("index", help="INDEX[:SUB] in hex, e.g. 0x6041 or 1018:1")
    p.add_argument("value", nargs="?")
    p.add_argument("--size", type=int, default=4, choices=(1, 2, 4), help="bytes to write without an EDS")
    p.add_argument("--force", action="store_true", help="write an object the driver protects (bench only; logged)")
    _node_options(p, cmd_sdo, eds_help="EDS for the object's type and name")

    p = sub.add_parser("save", help="store the drive's parameters in its memory (0x1010 'save')")
    p.add_argument("node")
    p.add_argument("--sub", type=whole(1, 4), default=1,
                   help="1 all (default), 2 communication, 3 application, 4 manufacturer parameters")
    _node_options(p, cmd_save)

    p = sub.add_parser("nmt", help="NMT command to a node or all nodes")
    p.add_argument("action", choices=tuple(NMT_COMMANDS))
    p.add_argument("node", help="node id, a drive's name (with --config) or 'all'")
    _node_options(p, cmd_nmt, master_flags=True)
