"""The bench commands of ``rovercan``: thin functions over the library and python-can.

Every command takes python-can's standard bus arguments (``-i/-c/-b/--bus-kwargs``); a
command that addresses a drive also takes ``--config FILE`` or ``--eds FILE`` with
``--counts-per-rev`` / ``--gear-ratio``. Human tables by default, ``--json`` for scripts.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import logging
import math
import re
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import can.cli
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config import GENERIC_EDS, RoverConfig, load_config, load_drive_od, load_od, parse_config
from can_config.config import GEAR_RATIO_MAX, GEAR_RATIO_MIN
from can_config.eds import consumer_subs, variable
from can_config.errors import BusLostError, CommandRejected, ConfigError, RovercanError
from can_config.objects import (
    OD,
    STRUCT_FORMAT,
    SUPPORTED_MODE_BIT,
    NmtCommand,
    NmtState,
    OperationMode,
    sdo_abort_text,
)
from can_config.recording import read_recording
from can_config.stop import StopSignal
from motor_driver.adapters import connection_closed
from motor_driver.driver import open_bus as driver_open_bus
from motor_driver.driver import wait_for_server
from rovercan.argtypes import real, whole
from rovercan.decode import PdoField, PdoLayouts, candump_line, decode, node_of

logger = logging.getLogger(__name__)

SCAN_TIMEOUT_S = 0.3
SDO_TIMEOUT_S = 0.5
#: The bench waits this long for a socketcand server by default (--timeout; the driver in a node: 10 s).
CLI_CONNECT_TIMEOUT_S = 3.0
CAUSES = "check the node id, power, bitrate and termination (120 ohm at both ends)"


class CliError(RovercanError):
    """A bench command failed; the message is printed on stderr."""


# ------------------------------------------------------------------------------ shared helpers
def add_bus_args(parser: argparse.ArgumentParser) -> None:
    can.cli.add_bus_arguments(parser)
    parser.add_argument("--timeout", type=real(0.1, 600), default=CLI_CONNECT_TIMEOUT_S, metavar="S",
                        help=f"seconds to wait for a socketcand server (default {CLI_CONNECT_TIMEOUT_S:g})")


def connect_timeout(args: argparse.Namespace) -> float:
    return float(getattr(args, "timeout", CLI_CONNECT_TIMEOUT_S))


def add_drive_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="the rover config (bus, drives, units)")
    parser.add_argument("--eds", help="EDS of a drive on its own (default: the generic CiA 402 EDS)")
    parser.add_argument("--counts-per-rev", type=whole(1, 2**31 - 1), help="encoder counts per motor revolution")
    parser.add_argument("--gear-ratio", type=real(GEAR_RATIO_MIN, GEAR_RATIO_MAX), default=1.0,
                        help="motor revolutions per joint revolution")


def add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="machine-readable output")


NO_BUS = ("no bus given: pass -i INTERFACE -c CHANNEL (e.g. -i socketcan -c can0, or -i socketcand -c can0"
          " --bus-kwargs host=127.0.0.1 port=29536) or --config FILE")


def open_bus(args: argparse.Namespace) -> can.BusABC:
    if getattr(args, "interface", None) is None and getattr(args, "config", None):
        config = load_config(args.config)
        return driver_open_bus(config.buses[0].bus_kwargs(), connect_timeout(args))
    if getattr(args, "interface", None) is None:
        raise ConfigError(NO_BUS)
    tuned: dict[str, Any] = {"tcp_tune": True} if args.interface == "socketcand" else {}  # --bus-kwargs overrides
    extra = getattr(args, "bus_kwargs", None) or {}
    if "port" in extra:
        extra["port"] = tcp_port(extra["port"])
    if args.interface == "socketcand" and "host" in extra and "port" in extra:
        wait_for_server(str(extra["host"]), int(extra["port"]), connect_timeout(args))  # python-can's loop spins
    try:
        return can.cli.create_bus_from_namespace(args, **tuned)
    except argparse.ArgumentError as err:
        raise CliError(f"cannot open the bus {args.interface} {getattr(args, 'channel', '')}: {err.__cause__}") from err


def tcp_port(value: object) -> int:
    """``--bus-kwargs port=...`` as a TCP port: decimal or 0x hex, as every number of the CLI."""
    try:
        port = value if isinstance(value, int) and not isinstance(value, bool) else int(str(value), 0)
    except ValueError:
        raise ConfigError(f"--bus-kwargs port={value}: expected a TCP port 1..65535 (decimal, or hex as 0x71D8)") from None
    if not 1 <= port <= 65535:
        raise ConfigError(f"--bus-kwargs port={value}: a TCP port is 1..65535")
    return port


def parse_node(text: str) -> int:
    try:
        node = int(text, 0)
    except ValueError:
        raise ConfigError(f"node {text!r}: expected a node id 1..127") from None
    if not 1 <= node <= 127:
        raise ConfigError(f"node {node}: CANopen node ids are 1..127")
    return node


def parse_index(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(0x)?([0-9a-fA-F]{1,4})(?::(\d+|0x[0-9a-fA-F]+))?", text)
    if not match:
        raise ConfigError(f"index {text!r}: expected INDEX[:SUB] in hex, e.g. 0x6041 or 1018:1")
    sub = int(match.group(3), 0) if match.group(3) else 0
    if sub > 0xFF:
        raise ConfigError(f"index {text!r}: sub-index {sub} out of range 0..255")
    return int(match.group(2), 16), sub


def emit(args: argparse.Namespace, data: Any, title: str, columns: list[str] | None = None) -> None:
    if getattr(args, "json", False):
        print(json.dumps(data, indent=2, default=str))
        return
    from rich.console import Console
    from rich.table import Table

    console = Console()
    if columns is not None and isinstance(data, list):
        table = Table(title=title)
        for col in columns:
            table.add_column(col)
        for row in data:
            table.add_row(*(str(row.get(c, "")) for c in columns))
        console.print(table)
    elif isinstance(data, dict):
        table = Table(title=title, show_header=False)
        table.add_column("key")
        table.add_column("value")
        for key, value in data.items():
            table.add_row(str(key), json.dumps(value) if isinstance(value, (list, dict)) else str(value))
        console.print(table)
    else:
        console.print(data)


@contextmanager
def remote_node(args: argparse.Namespace, node_id: int) -> Iterator[tuple[canopen.RemoteNode, can.BusABC]]:
    bus = open_bus(args)
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1  # so stopping it is quick and precedes the bus shutdown
    network.connect()
    try:
        eds = getattr(args, "eds", None)
        od: ObjectDictionary | str = load_od(eds, node_id) if eds else ObjectDictionary()
        node = canopen.RemoteNode(node_id, od)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        network.add_node(node)
        yield node, bus
    finally:
        network.notifier.stop(1.0) if network.notifier else None
        bus.shutdown()


@contextmanager
def sdo_errors(node_id: int, what: str, timeout_s: float) -> Iterator[None]:
    """canopen's SDO failures as one-line CLI errors naming the node, the object and the cause."""
    try:
        yield
    except canopen.SdoAbortedError as err:
        raise CliError(f"node {node_id}: {what} aborted: 0x{err.code:08X} {sdo_abort_text(err.code)}") from err
    except canopen.SdoCommunicationError as err:
        raise CliError(f"node {node_id}: no answer to {what} within {timeout_s:g} s; {CAUSES}") from err


def sdo_upload(node: canopen.RemoteNode, index: int, sub: int) -> bytes:
    with sdo_errors(node.id, f"SDO read 0x{index:04X}:{sub}", SDO_TIMEOUT_S):
        return bytes(node.sdo.upload(index, sub))


def _u32(raw: bytes) -> int:
    return int.from_bytes(raw[:4].ljust(4, b"\0"), "little")


def _untyped(raw: bytes) -> int | str:
    """A value read without an EDS: a number up to 8 bytes, printable text as text (0x1008, the
    device name, is a string of 10-70 bytes), anything else as hex."""
    text = raw.rstrip(b"\0")
    if len(raw) > 8 or (len(raw) > 4 and text and all(32 <= b < 127 for b in text)):
        return text.decode("ascii") if text and all(32 <= b < 127 for b in text) else raw.hex(" ")
    return int.from_bytes(raw, "little")


def _text(raw: bytes) -> str:
    return raw.rstrip(b"\0").decode("latin-1", errors="replace")


def receive(bus: can.BusABC, timeout_s: float) -> can.Message | None:
    """``bus.recv`` that raises :class:`BusLostError` once the bus server has gone away (python-can's
    socketcand client would otherwise return None forever, spinning)."""
    msg = bus.recv(timeout_s)
    if msg is None and connection_closed(bus):
        raise BusLostError(f"{bus.channel_info}: the bus server closed the connection; is 'rovercan sim' (or"
                           " socketcand) still running?")
    return msg


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
    node_id = parse_node(args.node)
    with remote_node(args, node_id) as (node, _):
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
        info["error_register"] = f"0x{sdo_upload(node, OD.ERROR_REGISTER, 0)[0]:02X}"
        history = []
        try:
            count = sdo_upload(node, OD.PREDEFINED_ERROR_FIELD, 0)[0]
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
        tt = sdo_upload(node, comm_base + n, 2)[0]
        count = sdo_upload(node, comm_base + 0x200 + n, 0)[0]
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
        return struct.pack(fmt, number)
    except (struct.error, OverflowError) as err:
        raise ConfigError(f"value {text} does not fit {what} ({STRUCT_NAMES.get(fmt, fmt)}): {err}") from err


STRUCT_NAMES = {"<b": "INTEGER8", "<B": "UNSIGNED8", "<h": "INTEGER16", "<H": "UNSIGNED16", "<i": "INTEGER32",
                "<I": "UNSIGNED32", "<q": "INTEGER64", "<Q": "UNSIGNED64", "<f": "REAL32", "<d": "REAL64"}


def cmd_sdo(args: argparse.Namespace) -> int:
    node_id = parse_node(args.node)
    index, sub = parse_index(args.index)
    with remote_node(args, node_id) as (node, _):
        # without --eds/--config the standard objects of CiA 301/402 are still known: the
        # project's generic CiA 402 EDS lists them with their names and types
        od = node.object_dictionary if len(node.object_dictionary) else load_od(GENERIC_EDS, node_id)
        var = variable(od, index, sub)
        name = var.name if var is not None else ""
        fmt = STRUCT_FORMAT.get(int(var.data_type)) if var is not None else None
        if args.action == "read":
            raw = sdo_upload(node, index, sub)
            value: Any = struct.unpack(fmt, raw)[0] if fmt and len(raw) == struct.calcsize(fmt) else (
                _text(raw) if var is not None and int(var.data_type) == 0x09 else _untyped(raw))
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
        with sdo_errors(node_id, f"SDO write 0x{index:04X}:{sub}", SDO_TIMEOUT_S):
            node.sdo.download(index, sub, data)
        emit(args, {"node": node_id, "index": f"0x{index:04X}", "sub": sub, "written": data.hex(" ")}, "written")
    return 0


def standard_meaning(index: int, value: Any) -> str | None:
    """What a CiA 402 status, control or mode value says, in words (None: nothing to add)."""
    from motor_driver.cia402 import CW, SW, decode_state

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
    node_id = parse_node(args.node)
    with remote_node(args, node_id) as (node, _):
        node.sdo.RESPONSE_TIMEOUT = SAVE_TIMEOUT_S
        started = time.monotonic()
        with sdo_errors(node_id, f"the save (0x1010:{args.sub})", SAVE_TIMEOUT_S):
            node.sdo.download(OD.STORE_PARAMETERS, args.sub, b"save")
        took = time.monotonic() - started
    emit(args, {"node": node_id, "saved": SAVE_WHAT[args.sub], "object": f"0x1010:{args.sub}",
                "answer_ms": round(took * 1000)}, f"node {node_id} saved")
    return 0


NMT_COMMANDS = {"start": NmtCommand.START, "stop": NmtCommand.STOP, "preop": NmtCommand.ENTER_PREOPERATIONAL,
                "reset": NmtCommand.RESET_NODE, "reset-comm": NmtCommand.RESET_COMMUNICATION}


#: How long ``nmt`` waits for the addressed node to show itself (NMT has no reply of its own).
NMT_CONFIRM_S = 1.5


def _heard_from(bus: can.BusABC, node_id: int, timeout_s: float, *, probe: bool, bootup: bool = False) -> bool:
    """Did the node show itself within ``timeout_s``: a heartbeat (or only its boot-up), or, with
    ``probe``, an answer to an SDO read of 0x1000 (any state but STOPPED answers)?"""
    if probe:
        bus.send(can.Message(arbitration_id=0x600 + node_id, data=bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]),
                             is_extended_id=False))
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        msg = receive(bus, max(0.0, end - time.monotonic()))
        if msg is None:
            continue
        if msg.arbitration_id == 0x700 + node_id and msg.data and (not bootup or msg.data[0] == 0):
            return True
        if probe and msg.arbitration_id == 0x580 + node_id:
            return True
    return False


def add_master_flags(parser: argparse.ArgumentParser) -> None:
    """The flags of a command that drives a drive: taking the bus over, and arming a drive that
    cannot watch this host."""
    parser.add_argument("--force", action="store_true",
                        help="take the bus over even when another master (a running driver) is live on it")
    parser.add_argument("--allow-no-host-watch", action="store_true",
                        help="arm a drive that cannot watch this host (no 0x1016, or node guarding on a bus without"
                             " remote frames): if this command dies, NOTHING stops the drive")


def refuse_beside_a_master(args: argparse.Namespace, bus: can.BusABC, node_ids: Collection[int]) -> None:
    """Before the first NMT command or enable of a bench command: listen for another master (two
    host-heartbeat periods) and refuse, naming what was heard, unless --force."""
    from motor_driver.driver import look_for_master, look_window_s, other_master_error

    host_id, period = 127, 0.05
    if getattr(args, "config", None):
        bus_cfg = load_config(args.config).buses[0]
        host_id, period = bus_cfg.host_node_id, bus_cfg.host_heartbeat_s
    evidence = look_for_master(bus, host_id, node_ids, look_window_s(period))
    if evidence and not getattr(args, "force", False):
        raise other_master_error(f"rovercan {args.command}", evidence)
    if evidence:
        logger.warning("another master is live (%s); going ahead as --force says", evidence)


def cmd_nmt(args: argparse.Namespace) -> int:
    node_id = 0 if args.node == "all" else parse_node(args.node)
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


# ------------------------------------------------------------------------------ drive commands
def one_drive_config(args: argparse.Namespace, node_id: int) -> RoverConfig:
    """A config with the one drive at ``node_id``: from --config, or built from --eds and units."""
    if args.config:
        config = load_config(args.config)
        drives = [d for d in config.drives if d.node_id == node_id]
        if not drives:
            raise ConfigError(f"{args.config}: no drive with node id {node_id}; drives:"
                              f" {[(d.name, d.node_id) for d in config.drives]}")
        bus = dataclasses.replace(config.bus(drives[0].bus), connect_timeout_s=connect_timeout(args))
        drive = drives[0]
        if getattr(args, "allow_no_host_watch", False):
            drive = dataclasses.replace(drive, allow_no_host_watch=True)
        return RoverConfig((bus,), (drive,), None, config.source)
    if getattr(args, "interface", None) is None:
        raise ConfigError(NO_BUS)  # never a silent python-can virtual bus: "no boot-up" would mislead
    return parse_config({"buses": [{"name": "bench", "interface": "virtual", "channel": "bench"}],
                         "drives": [{"name": f"node{node_id}", "node_id": node_id, "eds": args.eds or "generic",
                                     "counts_per_rev": args.counts_per_rev, "gear_ratio": args.gear_ratio,
                                     "allow_no_host_watch": bool(getattr(args, "allow_no_host_watch", False))}]})


@contextmanager
def bench_driver(args: argparse.Namespace, node_id: int) -> Iterator[Any]:
    from motor_driver import MotorDriver

    config = one_drive_config(args, node_id)
    bus = open_bus(args) if getattr(args, "interface", None) else None
    driver = MotorDriver(config, {config.buses[0].name: bus} if bus is not None else None)
    try:
        driver.start(take_over=bool(getattr(args, "force", False)))
        yield driver.drive(config.drives[0].name)
    finally:
        driver.close()  # quick stop + disable: the bench never leaves a drive armed by accident
        if bus is not None:
            bus.shutdown()


def cmd_drive(args: argparse.Namespace) -> int:
    node_id = parse_node(args.node)
    with bench_driver(args, node_id) as drive:
        if args.action == "fault-reset":
            drive.recover()
        elif args.action == "disable":
            drive.disable()
        elif args.action == "enable":
            drive.enable()
            if args.hold:
                time.sleep(args.hold)
        elif args.action == "home":
            drive.enable()
            drive.home()
        state = drive.snapshot()
        result: dict[str, Any] = {"node": node_id, "action": args.action, "state": state.state.name,
                                  "angle_deg": round(state.angle_deg, 3)}
        if args.action == "enable":  # the bench never leaves a drive armed behind it
            result["on_exit"] = (f"held enabled {args.hold:g} s, then disabled" if args.hold else
                                 "disabled again as the command exits; --hold S keeps it enabled S seconds first")
        emit(args, result, f"node {node_id}")
    return 0


class UnitCheck:
    """While a drive moves: does the distance its position covered match what its reported
    velocity adds up to? Position counts and velocity units come from different objects (0x608F,
    0x60A9, gear ratio); a wrong ``counts_per_rev`` shows as a ratio far from 1."""

    TOLERANCE = 0.2
    MIN_TRAVEL_DEG = 2.0

    def __init__(self, drive: Any) -> None:
        self.drive = drive
        self.samples: list[tuple[float, float, float]] = []

    def sample(self) -> None:
        s = self.drive.snapshot()
        self.samples.append((time.monotonic(), s.angle_deg, s.velocity_deg_s))

    def verdict(self) -> str | None:
        moved = reported = 0.0
        for (t0, a0, v0), (t1, a1, v1) in itertools.pairwise(self.samples):
            step = a1 - a0
            if self.drive.config.is_continuous:
                step = (step + 180.0) % 360.0 - 180.0  # across the wrap of a continuous joint
            moved += step
            reported += (v0 + v1) / 2 * (t1 - t0)
        if max(abs(moved), abs(reported)) < self.MIN_TRAVEL_DEG:
            return None  # too little motion to judge
        if reported and abs(moved / reported - 1) <= self.TOLERANCE:
            return None
        ratio = f"x{moved / reported:.2f}" if reported else "no velocity reported"
        return (f"node {self.drive.node_id}: the position moved {moved:.1f} deg while the reported velocity adds"
                f" up to {reported:.1f} deg ({ratio}): counts_per_rev looks wrong (or gear_ratio, or the"
                " drive's velocity unit 0x60A9); positions and velocities disagree")

    def warn(self) -> None:
        text = self.verdict()
        if text is not None:
            print(f"rovercan: warning: {text}", file=sys.stderr, flush=True)


def has_profile_position(drive: Any) -> bool:
    return bool(drive.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_POSITION] & 1)


def command_angle(drive: Any, angle_deg: float) -> float:
    """The angle to command for a multi-turn ``angle_deg``: a continuous joint takes an angle
    modulo 360 (and moves the short way to it), so after a few turns a measured start plus a step
    is brought back into -360..360 first."""
    return math.fmod(angle_deg, 360.0) if drive.config.is_continuous else angle_deg


def stream_to(drive: Any, target_deg: float, speed_deg_s: float | None = None,
              on_tick: Callable[[], None] | None = None) -> float:
    """A move on a drive whose only position modes are cyclic or interpolated (the SCHUNK PRL120):
    a trapezoid of set-points, one per SYNC period, through the driver's streaming path (limits
    enforced there), then waits until the joint is within 0.2 deg. Returns the target."""
    cfg = drive.config
    drive.check_position(command_angle(drive, target_deg))  # beyond a limit: refused before anything is sent
    period = drive.sync_period_s
    speed = min(speed_deg_s or cfg.profile_velocity_deg_s, cfg.max_velocity_deg_s)
    accel = cfg.profile_acceleration_deg_s2
    start = drive.snapshot().angle_deg
    distance = target_deg - start
    direction = 1.0 if distance >= 0 else -1.0
    span = abs(distance)
    ramp = min(speed * speed / (2 * accel), span / 2)  # distance of each ramp (v^2 / 2a, or half the way)
    peak = math.sqrt(2 * accel * ramp)  # the speed reached
    t_ramp = peak / accel if accel else 0.0
    t_total = 2 * t_ramp + ((span - 2 * ramp) / peak if peak else 0.0)
    t = 0.0
    while t < t_total:
        t = min(t + period, t_total)
        if t < t_ramp:
            done = 0.5 * accel * t * t
        elif t > t_total - t_ramp:
            done = span - 0.5 * accel * (t_total - t) ** 2
        else:
            done = ramp + peak * (t - t_ramp)
        drive.stream_position(command_angle(drive, start + direction * done))
        if on_tick is not None:
            on_tick()
        time.sleep(period)
    drive.stream_position(command_angle(drive, target_deg))
    if on_tick is not None:
        return target_deg  # the caller keeps sampling
    deadline = time.monotonic() + 3.0
    while abs(drive.snapshot().angle_deg - target_deg) > 0.2:
        if time.monotonic() > deadline:
            raise CliError(f"node {drive.node_id}: at {drive.snapshot().angle_deg:.2f} deg, not at {target_deg:g} deg"
                           " 3 s after the streamed move ended")
        time.sleep(period)
    return target_deg


def cmd_move(args: argparse.Namespace) -> int:
    node_id = parse_node(args.node)
    with bench_driver(args, node_id) as drive:
        if args.speed is not None and not 0 < args.speed <= drive.config.max_velocity_deg_s:
            raise ConfigError(f"--speed {args.speed:g} deg/s: allowed 0 < speed <= {drive.config.max_velocity_deg_s:g}"
                              " (max_velocity_deg_s)")
        drive.enable()
        if has_profile_position(drive):
            if args.speed is not None:
                drive.set_profile_velocity(args.speed)
            check = UnitCheck(drive)
            target = drive.move_to(args.degrees)
            sampling = threading.Event()

            def sample_until_done() -> None:
                while not sampling.wait(0.01):
                    check.sample()

            sampler = threading.Thread(target=sample_until_done, daemon=True, name="rovercan-unit-check")
            sampler.start()
            try:
                drive.wait_target_reached()
            finally:
                sampling.set()
                sampler.join()
            check.warn()
        else:  # cyclic or interpolated position only: streamed set-points
            target = stream_to(drive, args.degrees, args.speed)
        state = drive.snapshot()
        emit(args, {"node": node_id, "target_deg": round(target, 3), "angle_deg": round(state.angle_deg, 3),
                    "state": state.state.name}, f"node {node_id} moved")
    return 0


def has_profile_velocity(drive: Any) -> bool:
    return bool(drive.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_VELOCITY] & 1)


def stream_jog(drive: Any, velocity: float, seconds: float) -> Any:
    """A jog on a drive without profile velocity: streamed positions, ramped at the profile
    acceleration up to ``velocity``, held for ``seconds``, ramped down. Returns the state seen at
    the end of the hold."""
    cfg = drive.config
    period = drive.sync_period_s
    dv = cfg.profile_acceleration_deg_s2 * period
    position = drive.snapshot().angle_deg
    v = 0.0
    end = time.monotonic() + seconds
    peak = None
    while peak is None or abs(v) > 1e-9:
        goal = velocity if time.monotonic() < end else 0.0
        if goal == 0.0 and peak is None:
            peak = drive.snapshot()
        v += max(-dv, min(dv, goal - v))
        position += v * period
        drive.stream_position(position)
        time.sleep(period)
    return peak


def cmd_jog(args: argparse.Namespace) -> int:
    node_id = parse_node(args.node)
    with bench_driver(args, node_id) as drive:
        drive.enable()
        if not has_profile_velocity(drive):  # a position-only drive: a streamed ramp
            peak = stream_jog(drive, args.velocity, args.seconds)
        else:
            end = time.monotonic() + args.seconds
            sent = 0
            check = UnitCheck(drive)
            while time.monotonic() < end:
                try:
                    drive.set_velocity(args.velocity)
                except CommandRejected as err:
                    if sent:  # refused on the way (a limit ahead): the drive had moved, so exit 1, not 2
                        raise CliError(str(err)) from err
                    raise
                sent += 1
                check.sample()
                time.sleep(0.05)
            peak = drive.snapshot()
            drive.set_velocity(0.0)
            check.warn()
        emit(args, {"node": node_id, "velocity_deg_s": round(peak.velocity_deg_s, 3),
                    "angle_deg": round(peak.angle_deg, 3)}, f"node {node_id} jogged")
    return 0


# ------------------------------------------------------------------------------ traffic
def pdo_layouts_for(args: argparse.Namespace) -> PdoLayouts:
    """PDO layouts the driver would configure, for decoding (config or EDS given)."""
    from motor_driver.pdo import plan_pdos

    layouts: dict[int, tuple[PdoField, ...]] = {}
    drives = []
    if getattr(args, "config", None):
        drives = [(d.eds, d.node_id) for d in load_config(args.config).drives]
    elif getattr(args, "eds", None):
        drives = [(Path(args.eds), n) for n in range(1, 128)]
    loaded: dict[Path, ObjectDictionary] = {}
    for eds, node_id in drives:
        # one parse per EDS file (127 parses took about two seconds): the plan depends on the
        # objects, and the node id only moves the COB-IDs, which plan_pdos derives itself
        od = loaded.get(eds) or loaded.setdefault(eds, load_drive_od(eds, node_id))
        plan = plan_pdos(od, node_id)
        for pdo in (*plan.tpdos, *plan.rpdos):
            layouts[pdo.cob_id] = tuple(PdoField(_field_name(od, i, s), STRUCT_FORMAT[dt]) for i, s, dt in pdo.objects)
    return layouts


def _field_name(od: ObjectDictionary, index: int, sub: int) -> str:
    if index == OD.STATUSWORD:
        return "statusword"
    if index == OD.CONTROLWORD:
        return "controlword"
    var = variable(od, index, sub)
    return var.name.lower().replace(" ", "_") if var is not None else f"0x{index:04X}"


def cmd_monitor(args: argparse.Namespace) -> int:

    layouts = pdo_layouts_for(args)
    bus = open_bus(args)
    print(f"rovercan monitor: listening on {bus.channel_info}", file=sys.stderr, flush=True)
    count = 0
    nodes: dict[int, dict[str, str]] = {}
    with StopSignal() as stop:
        try:
            end = time.monotonic() + args.seconds if args.seconds else math.inf
            while not stop.event.is_set() and time.monotonic() < end:
                msg = receive(bus, 0.2)
                if msg is None:
                    continue
                node = node_of(msg)
                if args.node is not None and node != args.node:
                    continue
                text = decode(msg, layouts)
                count += 1
                if args.table:
                    if node is not None:
                        nodes.setdefault(node, {})["last"] = text
                    continue
                if args.json:
                    print(json.dumps({"t": msg.timestamp, "id": msg.arbitration_id, "data": bytes(msg.data).hex(),
                                      "node": node, "text": text}), flush=True)
                else:
                    print(f"{candump_line(msg, str(getattr(args, 'channel', None) or 'can'))}   {text}", flush=True)
        finally:
            bus.shutdown()
    if args.table:
        emit(args, [{"node": n, "last": v["last"]} for n, v in sorted(nodes.items())], "nodes", ["node", "last"])
    print(f"rovercan monitor: {count} frames", file=sys.stderr)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    check_recording_target(args.file)
    bus = open_bus(args)
    print(f"rovercan record: recording {bus.channel_info} to {args.file}", file=sys.stderr, flush=True)
    n = 0
    with StopSignal() as stop, can.Logger(args.file) as logger:
        try:
            end = time.monotonic() + args.seconds if args.seconds else math.inf
            while not stop.event.is_set() and time.monotonic() < end:
                msg = receive(bus, 0.2)
                if msg is not None:
                    logger(msg)
                    n += 1
        finally:
            bus.shutdown()
    print(f"rovercan record: {n} frames to {args.file}", file=sys.stderr)
    return 0


#: A classic CAN frame's data bytes at most (replay refuses CAN FD frames).
CLASSIC_DATA_MAX = 8


def check_recording_target(path: str) -> None:
    """``record``'s file: a format python-can writes, checked before the bus is opened."""
    suffix = Path(path).suffix.lower()
    writers = can.io.logger.MESSAGE_WRITERS
    if suffix not in writers:
        raise ConfigError(f"{path}: {suffix or 'a file without suffix'} is not a format python-can records;"
                          f" use one of {', '.join(sorted(writers))}")


def is_command_frame(msg: can.Message) -> bool:
    """Frames that tell a drive what to do: NMT, RPDOs (set-points, controlwords), SDO requests,
    LSS from a master. Everything else (SYNC, EMCY, TPDOs, heartbeats, SDO answers) only reports."""
    cob = msg.arbitration_id
    return not msg.is_extended_id and (cob == 0x000 or 0x201 <= cob <= 0x57F or 0x601 <= cob <= 0x67F
                                       or cob == 0x7E5)


def parse_filter(text: str) -> tuple[int, int]:
    """``ID[:MASK]`` in hex: a frame passes when ``frame_id & MASK == ID & MASK`` (MASK: 0x7FF)."""
    match = re.fullmatch(r"(?:0x)?([0-9a-fA-F]{1,8})(?::(?:0x)?([0-9a-fA-F]{1,8}))?", text)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ID[:MASK] in hex, e.g. 0x181 or 0x180:0x780")
    return int(match.group(1), 16), int(match.group(2), 16) if match.group(2) else 0x7FF


def cmd_replay(args: argparse.Namespace) -> int:
    messages = [m for m in read_recording(args.file) if not m.is_error_frame]
    if fd := sum(1 for m in messages if len(m.data) > CLASSIC_DATA_MAX):
        raise ConfigError(f"{args.file}: {fd} CAN FD frames (over {CLASSIC_DATA_MAX} data bytes); the buses of this"
                          " stack are classic CAN and cannot carry them. Nothing was sent.")
    if args.filter:
        messages = [m for m in messages if any(m.arbitration_id & mask == fid & mask for fid, mask in args.filter)]
    commands = sum(1 for m in messages if is_command_frame(m))
    if commands and not args.allow_commands:
        messages = [m for m in messages if not is_command_frame(m)]
        print(f"rovercan replay: {commands} command frames (NMT, RPDO, SDO requests, LSS) left out: on a live bus"
              " they would move or reconfigure drives; --allow-commands sends them", file=sys.stderr, flush=True)
    elif commands:
        logger.warning("replaying %d command frames (NMT, RPDO, SDO requests, LSS) onto the bus", commands)
    bus = open_bus(args)
    n = 0
    try:
        source = messages if args.fast else can.MessageSync(messages, timestamps=True)
        for msg in source:
            bus.send(can.Message(arbitration_id=msg.arbitration_id, data=msg.data, is_extended_id=msg.is_extended_id,
                                 is_remote_frame=msg.is_remote_frame, dlc=msg.dlc))
            n += 1
    finally:
        bus.shutdown()
    print(f"rovercan replay: {n} frames from {args.file}", file=sys.stderr)
    return 0


def cmd_decode(args: argparse.Namespace) -> int:
    frames = read_recording(args.file)
    layouts = pdo_layouts_for(args)
    n = 0
    for msg in frames:
        node = node_of(msg)
        if args.node is not None and node != args.node:
            continue
        text = decode(msg, layouts)
        if args.json:
            print(json.dumps({"t": msg.timestamp, "id": msg.arbitration_id, "data": bytes(msg.data).hex(), "text": text}))
        else:
            print(f"{msg.timestamp:14.6f} {candump_line(msg).strip()}   {text}")
        n += 1
    print(f"rovercan decode: {n} frames", file=sys.stderr)
    return 0


# ------------------------------------------------------------------------------ incident
def cmd_incident(args: argparse.Namespace) -> int:
    """The summary the flight recorder wrote, or its drives' faults as a simulator scenario."""
    from can_config.incident import fault_steps, load_incident

    summary = load_incident(args.file)
    if args.scenario:
        import yaml
        steps = fault_steps(args.file)
        print(f"# drive faults of {Path(args.file).with_suffix('.json').name}: rovercan sim --scenario FILE")
        print(yaml.safe_dump({"steps": steps}, sort_keys=False), end="")
        return 0
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    events = [{"t_s": round(e["t"] - summary["t"], 3), "kind": e["kind"], "bus": e["bus"],
               "drive": e.get("drive") or "", "node": e.get("node") or "",
               "code": f"0x{e['code']:04X}" if e.get("code") is not None else "", "what": e.get("text", "")}
              for e in summary["events"]]
    print(f"incident {summary['kind']} at {summary['time']}: {summary['frames']} frames kept from"
          f" {summary['window_s'][0]:+.2f} s to {summary['window_s'][1]:+.2f} s"
          f" (buses {', '.join(summary['channels'].values())}); files: {summary['blf']}"
          f"{', ' + summary['png'] if summary.get('png') else ''}")
    emit(args, events, "events", ["t_s", "kind", "bus", "drive", "node", "code", "what"])
    return 0


# ------------------------------------------------------------------------------ step test
def step_metrics(t: list[float], y: list[float], start: float, step: float, torque: list[float]) -> dict[str, float]:
    """Rise time (10-90 %), overshoot (%), settling time (2 % band), steady-state error, peak torque."""
    final = start + step
    sign = 1.0 if step >= 0 else -1.0
    rel = [(v - start) * sign / abs(step) for v in y]
    t10 = next((ti for ti, r in zip(t, rel, strict=True) if r >= 0.1), math.nan)
    t90 = next((ti for ti, r in zip(t, rel, strict=True) if r >= 0.9), math.nan)
    overshoot = max(0.0, (max(rel) - 1.0) * 100.0)
    band = 0.02
    settle = 0.0
    for ti, r in zip(t, rel, strict=True):
        if abs(r - 1.0) > band:
            settle = ti
    return {"rise_time_s": round(t90 - t10, 4), "overshoot_pct": round(overshoot, 3),
            "settling_time_s": round(settle, 4), "steady_state_error_deg": round(abs(final - y[-1]), 4),
            "peak_torque_nm": round(max((abs(x) for x in torque if not math.isnan(x)), default=math.nan), 4)}


def cmd_step_test(args: argparse.Namespace) -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    node_id = parse_node(args.node)
    with bench_driver(args, node_id) as drive:
        if drive.config.is_continuous and abs(args.step) >= 180:
            raise ConfigError(f"--step {args.step:g}: a continuous joint moves the short way, so a step test"
                              " needs |step| < 180 deg")
        drive.enable()
        start = drive.snapshot().angle_deg
        t0 = time.monotonic()
        ts: list[float] = []
        setpoint: list[float] = []
        angle: list[float] = []
        velocity: list[float] = []
        torque: list[float] = []
        target = start + args.step

        def sample() -> None:
            s = drive.snapshot()
            ts.append(time.monotonic() - t0)
            setpoint.append(target)
            angle.append(s.angle_deg)
            velocity.append(s.velocity_deg_s)
            torque.append(s.torque_nm)

        if has_profile_position(drive):
            target = drive.move_to(command_angle(drive, target))
        else:  # position streamed: the set-point is a trapezoid, sampled as it goes
            stream_to(drive, target, on_tick=sample)
        while time.monotonic() - t0 < args.seconds:
            sample()
            time.sleep(0.005)
    metrics = step_metrics(ts, angle, start, args.step, torque)
    metrics.update({"step_deg": args.step, "start_deg": round(start, 3),
                    "profile_velocity_deg_s": drive.config.profile_velocity_deg_s,
                    "profile_acceleration_deg_s2": drive.config.profile_acceleration_deg_s2})
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    axes[0].plot(ts, setpoint, "--", label="setpoint")
    axes[0].plot(ts, angle, label="angle")
    axes[0].set_ylabel("deg")
    axes[0].legend()
    axes[0].set_title(f"step test node {node_id}: {args.step:g} deg, rise {metrics['rise_time_s']} s,"
                      f" overshoot {metrics['overshoot_pct']} %")
    axes[1].plot(ts, velocity)
    axes[1].set_ylabel("deg/s")
    axes[2].plot(ts, torque)
    axes[2].set_ylabel("Nm")
    axes[2].set_xlabel("s")
    for ax in axes:
        ax.grid(True)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"))
    plt.close(fig)
    out.with_suffix(".json").write_text(json.dumps(metrics, indent=2) + "\n")
    emit(args, metrics, f"step test node {node_id} -> {out.with_suffix('.png')}")
    return 0


# ------------------------------------------------------------------------------ safety-check
def safety_configs(args: argparse.Namespace) -> RoverConfig:
    """The drives to check: every drive of --config (on its first bus), or --node N ... with --eds."""
    if args.config:
        config = load_config(args.config)
        bus = config.buses[0]
        drives = tuple(d for d in config.drives if d.bus == bus.name and (not args.node or d.node_id in args.node))
        if not drives:
            raise ConfigError(f"{args.config}: no drive on bus {bus.name!r}"
                              f"{' with node id ' + str(args.node) if args.node else ''}")
        return RoverConfig((bus,), drives, None, config.source)
    if not args.node:
        raise ConfigError("safety-check: give --config FILE, or --eds FILE with --node N (repeatable)")
    configs = [one_drive_config(args, node) for node in args.node]
    return RoverConfig(configs[0].buses, tuple(c.drives[0] for c in configs), None, None)


def cmd_safety_check(args: argparse.Namespace) -> int:
    """Read back from each drive what keeps it safe when the host is gone; judge it by the
    driver's own rules (motor_driver.safety); and look for the host heartbeat on the bus."""
    from motor_driver.safety import host_heartbeat_check, judge
    from motor_driver.units import UNIT_OBJECTS, scale_from_objects

    if args.listen is not None and not (math.isfinite(args.listen) and 0 < args.listen <= 60):
        raise ConfigError(f"--listen {args.listen}: allowed 0 < seconds <= 60")
    config = safety_configs(args)
    bus_cfg = config.buses[0]
    listen_s = args.listen or max(0.3, 4 * bus_cfg.host_heartbeat_s)
    bus = open_bus(args)
    rows: list[dict[str, Any]] = []
    try:
        beats: list[float] = []
        deadline = time.monotonic() + listen_s
        while (remaining := deadline - time.monotonic()) > 0:
            msg = receive(bus, remaining)
            if msg is not None and msg.arbitration_id == 0x700 + bus_cfg.host_node_id and not msg.is_remote_frame:
                beats.append(msg.timestamp)
        host = host_heartbeat_check(bus_cfg.host_node_id, bus_cfg.host_heartbeat_s,
                                    [b - a for a, b in itertools.pairwise(beats)])
        rows.append({"node": "-", "drive": "(host)", **vars(host)})
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.1
        network.connect()
        try:
            for cfg in config.drives:
                od = load_drive_od(cfg.eds, cfg.node_id)
                node = canopen.RemoteNode(cfg.node_id, od)
                node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
                network.add_node(node)

                def read(index: int, sub: int, node: canopen.RemoteNode = node, od: ObjectDictionary = od) -> int | None:
                    var = variable(od, index, sub)
                    if var is None:
                        return None
                    raw = sdo_upload(node, index, sub)
                    fmt = STRUCT_FORMAT.get(int(var.data_type))
                    if fmt is None or len(raw) < struct.calcsize(fmt):
                        return _u32(raw)
                    return int(struct.unpack_from(fmt, raw)[0])

                objects = {(i, sub): v for i, subs in UNIT_OBJECTS for sub in subs if (v := read(i, sub)) is not None}
                scale, _ = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm, objects,
                                              invert=cfg.invert, offset_deg=cfg.offset_deg)
                subs = consumer_subs(od)
                for check in judge(cfg, bus_cfg.host_node_id, scale, read, consumer_subs=subs):
                    rows.append({"node": cfg.node_id, "drive": cfg.name, **vars(check)})
        finally:
            if network.notifier is not None:
                network.notifier.stop(1.0)
    finally:
        bus.shutdown()
    emit(args, rows, f"safety check ({bus_cfg.name})", ["node", "drive", "check", "object", "expected", "actual", "status"])
    failed = [r for r in rows if r["status"] == "FAIL"]
    if failed:
        names = ", ".join(f"{r['drive']} {r['check']} ({r['object']})" for r in failed)
        print(f"rovercan: safety check failed: {names}", file=sys.stderr)
        return 1
    return 0


# ------------------------------------------------------------------------------ plan / can-up
def cmd_plan(args: argparse.Namespace) -> int:
    from motor_driver.busload import MAX_LOAD, WARN_LOAD, plan_load

    loads = plan_load(load_config(args.config))
    rows = []
    worst = 0.0
    for load in loads:
        for line in load.lines:
            rows.append({"bus": line.bus, "what": line.what, "frames/s": round(line.frames_per_s, 1),
                         "load_pct": round(100 * line.bits_per_s / load.bitrate, 1)})
        rows.append({"bus": load.bus, "what": "TOTAL", "frames/s": round(sum(x.frames_per_s for x in load.lines), 1),
                     "load_pct": round(100 * load.load, 1)})
        worst = max(worst, load.load)
    emit(args, rows, "worst-case bus load (% of the bitrate)", ["bus", "what", "frames/s", "load_pct"])
    if worst > MAX_LOAD:
        print(f"rovercan plan: a bus needs {worst:.0%} of its bitrate: it cannot carry this config", file=sys.stderr)
        return 1
    if worst > WARN_LOAD:
        print(f"rovercan plan: warning: a bus is planned at {worst:.0%} (over {WARN_LOAD:.0%})", file=sys.stderr)
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """A config checked without a bus: parsed, each drive's EDS read (with the objects the driver
    needs for its host watch), the drive system's wheels known, each bus's planned load. Exit 0,
    or 2 with the first problem (a ConfigError names file, key and what is allowed)."""
    from can_config.eds import has_object
    from can_config.objects import OD
    from motor_driver.busload import MAX_LOAD, plan_load

    config = load_config(args.config)
    rows: list[dict[str, Any]] = []
    for drive in config.drives:
        od = load_drive_od(drive.eds, drive.node_id)  # an EdsError names the file
        watch = ("heartbeat consumer (0x1016)" if has_object(od, OD.CONSUMER_HEARTBEAT_TIME, 1) and
                 drive.host_watch != "guarding" else "node guarding (0x100C/0x100D)"
                 if has_object(od, OD.GUARD_TIME) and has_object(od, OD.LIFE_TIME_FACTOR) else
                 "none (allow_no_host_watch)" if drive.allow_no_host_watch else "NONE: it will not be enabled")
        rows.append({"bus": drive.bus, "drive": drive.name, "node": drive.node_id, "eds": Path(drive.eds).name,
                     "host watch": watch})
    loads = {load.bus: load.load for load in plan_load(config)}
    for bus in config.buses:
        rows.append({"bus": bus.name, "drive": "-", "node": "-", "eds": f"{bus.interface} {bus.channel}",
                     "host watch": f"planned load {100 * loads.get(bus.name, 0.0):.1f} %"})
    emit(args, rows, f"{args.config}: valid", ["bus", "drive", "node", "eds", "host watch"])
    system = config.drive_system
    if system is not None and not args.json:
        print(f"drive system: left {', '.join(system.left)}; right {', '.join(system.right)}; track"
              f" {system.track_width_m:g} m, wheel radius {system.wheel_radius_m:g} m")
    worst = max(loads.values(), default=0.0)
    if worst > MAX_LOAD:
        raise ConfigError(f"{args.config}: a bus is planned at {worst:.0%} of its bitrate, over {MAX_LOAD:.0%}: it"
                          " cannot carry this config (rovercan plan shows each frame); lower sync or PDO rates")
    return 0


_IFNAME = re.compile(r"^[a-zA-Z][a-zA-Z0-9_-]{0,14}$")


def can_up_commands(interface: str, bitrate: int, restart_ms: int, txqueuelen: int) -> list[list[str]]:
    """The ``ip`` commands that bring a SocketCAN interface up the way the Orin's mttcan needs, or
    a virtual ``vcanN`` (created; it has no bitrate) as CI uses (pure)."""
    if not _IFNAME.match(interface):
        raise ConfigError(f"interface {interface!r}: expected a Linux interface name (letters, digits, '_' or '-',"
                          " at most 15 characters), e.g. can0")
    if not 10_000 <= bitrate <= 1_000_000:
        raise ConfigError(f"--bitrate {bitrate}: classic CAN allows 10000 to 1000000 bit/s")
    if not 0 <= restart_ms <= 60_000:
        raise ConfigError(f"--restart-ms {restart_ms}: allowed 0 to 60000")
    if not 10 <= txqueuelen <= 100_000:
        raise ConfigError(f"--txqueuelen {txqueuelen}: allowed 10 to 100000")
    if interface.startswith("vcan"):
        return [["ip", "link", "add", "dev", interface, "type", "vcan"],
                ["ip", "link", "set", interface, "txqueuelen", str(txqueuelen)],
                ["ip", "link", "set", interface, "up"]]
    return [["ip", "link", "set", interface, "down"],
            ["ip", "link", "set", interface, "type", "can", "bitrate", str(bitrate), "restart-ms", str(restart_ms),
             "berr-reporting", "on"],
            ["ip", "link", "set", interface, "txqueuelen", str(txqueuelen)],
            ["ip", "link", "set", interface, "up"]]


def can_up_bitrate(args: argparse.Namespace) -> tuple[int, str]:
    """--bitrate, else the bitrate of the --config bus on the interface, else the embedded default's."""
    if args.bitrate is not None:
        return int(args.bitrate), "--bitrate"
    config = load_config(args.config)  # None: the embedded default
    on_it = [b for b in config.buses if b.channel == args.interface_name] or list(config.buses[:1])
    return on_it[0].bitrate, f"bus {on_it[0].name} of {args.config or 'the embedded default config'}"


def cmd_can_up(args: argparse.Namespace) -> int:
    bitrate, source = can_up_bitrate(args)
    vcan = args.interface_name.startswith("vcan")
    if not vcan:
        print(f"# bitrate {bitrate} bit/s from {source}", flush=True)
    commands = can_up_commands(args.interface_name, bitrate, args.restart_ms, args.txqueuelen)
    for argv in commands:
        print(" ".join(argv), flush=True)
        if args.dry_run:
            continue
        result = subprocess.run(argv, capture_output=True, text=True, check=False)  # a list: no shell
        if vcan and argv[2] == "add" and "File exists" in result.stderr:
            continue  # the vcan interface is there already
        if result.returncode != 0:
            raise CliError(f"{' '.join(argv)} failed ({result.returncode}): {result.stderr.strip()}"
                           " (root or CAP_NET_ADMIN needed; is the CAN controller's driver loaded?)")
    return 0
