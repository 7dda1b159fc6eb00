"""What every bench command shares: bus and drive arguments, opening the bus, SDO helpers, output.

No state: each command runs once on the CLI's main thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import re
import sys
import time
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import can.cli
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config import RoverConfig, load_config, load_od, parse_config
from can_config.config import GEAR_RATIO_MAX, GEAR_RATIO_MIN, BusConfig, DriveConfig
from can_config.errors import BusLostError, ConfigError, RovercanError, SdoError, SdoTimeoutError
from can_config.model import SOCKETCAND_PORT
from can_config.objects import sdo_abort_text
from motor_driver.bus.adapters import connection_closed
from motor_driver.bus.sdo_client import OwnAnswersNode
from motor_driver.bus.traffic import LOOK_BENCH_S
from motor_driver.drive.constants import SDO_TRANSFER_TIMEOUTS
from motor_driver.drive.sdo import SdoPort
from motor_driver.runtime.driver import open_bus as driver_open_bus
from motor_driver.runtime.driver import wait_for_server
from rovercan.argtypes import real, whole

logger = logging.getLogger(__name__)

SDO_TIMEOUT_S = 0.5
#: The bench waits this long for a socketcand server by default (--timeout; the driver in a node: 10 s).
CLI_CONNECT_TIMEOUT_S = 3.0
CAUSES = "check the node id, power, bitrate and termination (120 ohm at both ends)"


class CliError(RovercanError):
    """A bench command failed; the message is printed on stderr."""


# ------------------------------------------------------------------------------ shared helpers
def output_file(path: str | Path, what: str) -> Path:
    """A file the command writes at its end, checked before it opens a bus or moves a motor (a
    step test moved the motor and then lost its measurement to a bad ``--out``): its folder made
    now, as the write would, and writable; the path not a folder. ``what`` names the argument."""
    out = Path(path)
    folder = out.parent
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{what} {path}: {folder} is a file, not a folder; give a path in a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{what} {path}: its folder {folder} cannot be made ({err.strerror}); give a path in a"
                          " writable folder") from err
    if out.is_dir():
        raise ConfigError(f"{what} {path}: is a folder; give a file's path")
    if not os.access(folder, os.W_OK):
        raise ConfigError(f"{what} {path}: folder {folder} is not writable; give a path in a writable folder")
    return out


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    can.cli.add_bus_arguments(parser)
    parser.add_argument("--timeout", type=real(0.1, 600), default=CLI_CONNECT_TIMEOUT_S, metavar="S",
                        help=f"seconds to wait for a socketcand server (default {CLI_CONNECT_TIMEOUT_S:g})")


def connect_timeout(args: argparse.Namespace) -> float:
    return float(getattr(args, "timeout", CLI_CONNECT_TIMEOUT_S))


CONFIG_HELP = ("the rover config: its drives by name or node id, their buses (-c BUS picks one), units and"
               " settings")


def add_config_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help=CONFIG_HELP)


def add_drive_args(parser: argparse.ArgumentParser) -> None:
    add_config_arg(parser)
    parser.add_argument("--eds", help="EDS of a drive on its own (default: the generic CiA 402 EDS)")
    parser.add_argument("--counts-per-rev", type=whole(1, 2**31 - 1), help="encoder counts per motor revolution")
    parser.add_argument("--gear-ratio", type=real(GEAR_RATIO_MIN, GEAR_RATIO_MAX), default=1.0,
                        help="motor revolutions per joint revolution")


def add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="machine-readable output")


NO_BUS = ("no bus given: pass -i INTERFACE -c CHANNEL (e.g. -i socketcan -c can0, or -i socketcand -c can0"
          " --bus-kwargs host=127.0.0.1 port=29536) or --config FILE")


def config_bus(args: argparse.Namespace, config: RoverConfig) -> BusConfig:
    """The bus of --config a command works on: the bus of the drive it names (resolve_drive),
    else the one -c/--channel names (a bus name or channel of the config), else the first."""
    chosen = getattr(args, "config_bus", None)
    if chosen:
        return config.bus(chosen)
    wanted = getattr(args, "channel", None)
    if not wanted:
        return config.buses[0]
    matching = [b for b in config.buses if wanted in (b.name, b.channel)]
    if not matching:
        raise ConfigError(f"{args.config}: no bus named {wanted!r} or on channel {wanted!r}; buses:"
                          f" {', '.join(f'{b.name} (channel {b.channel})' for b in config.buses)}")
    return matching[0]


def resolve_drive(args: argparse.Namespace, spec: str) -> tuple[int, DriveConfig | None]:
    """The drive a bench command works on: ``spec`` is a node id, or with --config a drive name
    or a node id; -c/--channel picks among the config's buses (each bus has its own node ids).
    Every setting then comes from the drive named. Records its bus for :func:`open_bus`."""
    config_path = getattr(args, "config", None)
    if not config_path:
        return parse_node(spec), None
    config = load_config(config_path)
    wanted = getattr(args, "channel", None)
    on_bus = [d for d in config.drives if not wanted or wanted in (config.bus(d.bus).name, config.bus(d.bus).channel)]
    by_name = {d.name: d for d in config.drives}
    listing = ", ".join(f"{d.name} (node {d.node_id} on {d.bus})" for d in config.drives)
    if spec in by_name:
        drive = by_name[spec]
        if drive not in on_bus:
            raise ConfigError(f"{config_path}: drive {spec} is on bus {drive.bus}, not {wanted}; drop -c or name"
                              " a drive of that bus")
    else:
        try:
            node_id = parse_node(spec)
        except ConfigError:
            raise ConfigError(f"{spec!r}: neither a drive of {config_path} nor a node id 1..127; drives: {listing}") from None
        found = [d for d in on_bus if d.node_id == node_id]
        where = f" on bus {wanted}" if wanted else ""
        if not found:
            raise ConfigError(f"{config_path}: no drive with node id {node_id}{where}; drives: {listing}")
        if len(found) > 1:
            raise ConfigError(f"{config_path}: node id {node_id} is on several buses ("
                              f"{', '.join(f'{d.name} on {d.bus}' for d in found)}): name the drive, or the bus"
                              " with -c BUS")
        drive = found[0]
    args.config_bus = drive.bus
    return drive.node_id, drive


def open_bus(args: argparse.Namespace) -> can.BusABC:
    if getattr(args, "interface", None) is None and getattr(args, "config", None):
        config = load_config(args.config)
        return driver_open_bus(config_bus(args, config).bus_kwargs(), connect_timeout(args))
    if getattr(args, "interface", None) is None:
        raise ConfigError(NO_BUS)
    tuned: dict[str, Any] = {"tcp_tune": True} if args.interface == "socketcand" else {}  # --bus-kwargs overrides
    extra = getattr(args, "bus_kwargs", None) or {}
    if "port" in extra:
        extra["port"] = tcp_port(extra["port"])
    if args.interface == "socketcand" and not ("host" in extra and "port" in extra):
        raise ConfigError("-i socketcand needs --bus-kwargs host=HOST port=PORT (rovercan sim prints them, e.g."
                          f" host=127.0.0.1 port={SOCKETCAND_PORT})")
    if args.interface == "socketcand":
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
        raise ConfigError(f"node {text!r}: expected a node id 1..127 (or a drive's name, with --config FILE)") from None
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
def remote_node(args: argparse.Namespace, node_id: int, drive: DriveConfig | None = None,
                ) -> Iterator[tuple[canopen.RemoteNode, can.BusABC]]:
    """A canopen node of ``node_id`` on the command's bus, with the EDS of ``drive`` (of --config)
    or of --eds, else an empty dictionary."""
    bus = open_bus(args)
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1  # so stopping it is quick and precedes the bus shutdown
    network.connect()
    try:
        eds = drive.eds if drive is not None else getattr(args, "eds", None)
        od: ObjectDictionary | str = load_od(eds, node_id) if eds else ObjectDictionary()
        node = OwnAnswersNode(node_id, od)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        network.add_node(node)
        yield node, bus
    finally:
        network.notifier.stop(1.0) if network.notifier else None
        bus.shutdown()


@contextmanager
def sdo_errors(node_id: int, what: str, timeout_s: float) -> Iterator[None]:
    """SDO failures as one-line CLI errors naming the node, the object and the cause."""
    try:
        yield
    except SdoTimeoutError as err:
        if "took over" in str(err):  # it answered, and went on answering: a transfer without end
            raise CliError(f"node {node_id}: {what}: the transfer ran past {SDO_TRANSFER_TIMEOUTS} x the SDO timeout"
                           f" ({timeout_s:g} s) and was aborted") from err
        raise CliError(f"node {node_id}: no answer to {what} within {timeout_s:g} s; {CAUSES}") from err
    except SdoError as err:
        if err.abort_code is not None:
            raise CliError(f"node {node_id}: {what} aborted: 0x{err.abort_code:08X} {sdo_abort_text(err.abort_code)}") from err
        detail = str(err).split(f"0x{err.index:04X}:{err.subindex}", 1)[-1].lstrip(": ")
        raise CliError(f"node {node_id}: {what}: {detail}") from err


def sdo_port(node: canopen.RemoteNode, timeout_s: float = SDO_TIMEOUT_S) -> SdoPort:
    """The driver's SDO port for a node the bench talks to: bounded in size and time, one
    transfer at a time, one typed codec (motor_driver.drive.sdo)."""
    return SdoPort(f"node {node.id}", node, node.object_dictionary, timeout_s)


def sdo_upload(node: canopen.RemoteNode, index: int, sub: int) -> bytes:
    with sdo_errors(node.id, f"SDO read 0x{index:04X}:{sub}", SDO_TIMEOUT_S):
        return sdo_port(node).read(index, sub)


def sdo_download(node: canopen.RemoteNode, index: int, sub: int, data: bytes, timeout_s: float = SDO_TIMEOUT_S,
                 what: str = "") -> None:
    with sdo_errors(node.id, what or f"SDO write 0x{index:04X}:{sub}", timeout_s):
        sdo_port(node, timeout_s).write(index, sub, data)


def _u8(raw: bytes) -> int:
    """The first byte of an answer; an empty answer reads as 0 (a drive's short answer, never an IndexError)."""
    return raw[0] if raw else 0


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
    socketcand client would otherwise return None forever, spinning), or sent a line that is no
    CAN frame (python-can's client then fails on that line at every receive)."""
    try:
        msg = bus.recv(timeout_s)
    except can.CanError as err:
        logger.debug("receive failed: %s", err)
        raise BusLostError(f"{bus.channel_info}: the bus server sent what is no CAN frame (or the receive failed);"
                           " is it a socketcand server (rovercan sim, socketcand), and is it the right port?") from err
    if msg is None and connection_closed(bus):
        raise BusLostError(f"{bus.channel_info}: the bus server closed the connection; is 'rovercan sim' (or"
                           " socketcand) still running?")
    return msg


def add_master_flags(parser: argparse.ArgumentParser) -> None:
    """The flags of a command that drives a drive: taking the bus over, and arming a drive that
    cannot watch this host."""
    parser.add_argument("--force", action="store_true",
                        help="take the bus over even when another master (a running driver) is live on it")
    parser.add_argument("--look", type=real(0.05, 60), default=LOOK_BENCH_S, metavar="S",
                        help=f"seconds to listen for another master before the first NMT command (default"
                             f" {LOOK_BENCH_S:g}: the longest heartbeat or SYNC period a config allows, and a tenth)")
    parser.add_argument("--allow-no-host-watch", action="store_true",
                        help="arm a drive that cannot watch this host (no 0x1016, or node guarding on a bus without"
                             " remote frames): if this command dies, NOTHING stops the drive")


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


def say_look(args: argparse.Namespace, where: str) -> float:
    """The look-before-reset window of the command, said on stderr before it is spent."""
    window = float(getattr(args, "look", LOOK_BENCH_S))
    print(f"rovercan {args.command}: listening {window:g} s for another master on {where} before any NMT command"
          " (--look S)", file=sys.stderr, flush=True)
    return window


def refuse_beside_a_master(args: argparse.Namespace, bus: can.BusABC, node_ids: Collection[int]) -> None:
    """Before the first NMT command or enable of a bench command: listen for another master (two
    host-heartbeat periods) and refuse, naming what was heard, unless --force."""
    from motor_driver.runtime.driver import look_for_master, other_master_error

    host_id = 127
    if getattr(args, "config", None):
        host_id = config_bus(args, load_config(args.config)).host_node_id
    window = say_look(args, bus.channel_info)
    evidence = look_for_master(bus, host_id, node_ids, window)
    if evidence and not getattr(args, "force", False):
        raise other_master_error(f"rovercan {args.command}", evidence)
    if evidence:
        logger.warning("another master is live (%s); going ahead as --force says", evidence)


# ------------------------------------------------------------------------------ drive commands
def one_drive_config(args: argparse.Namespace, spec: str) -> RoverConfig:
    """A config with the one drive ``spec`` names (resolve_drive): from --config, or built from
    --eds and units."""
    node_id, found = resolve_drive(args, spec)
    if found is not None:
        config = load_config(args.config)
        bus = dataclasses.replace(config.bus(found.bus), connect_timeout_s=connect_timeout(args))
        drive = found
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
def bench_driver(args: argparse.Namespace, spec: str) -> Iterator[Any]:
    """A driver of the one drive ``spec`` names (a node id, or a drive of --config)."""
    from motor_driver import MotorDriver

    config = one_drive_config(args, spec)
    bus = open_bus(args) if getattr(args, "interface", None) else None
    driver = MotorDriver(config, {config.buses[0].name: bus} if bus is not None else None)
    try:
        look = say_look(args, f"bus {config.buses[0].name}") if hasattr(args, "look") else None
        driver.start(take_over=bool(getattr(args, "force", False)), look_s=look)
        yield driver.drive(config.drives[0].name)
    finally:
        driver.close()  # quick stop + disable: the bench never leaves a drive armed by accident
        if bus is not None:
            bus.shutdown()
