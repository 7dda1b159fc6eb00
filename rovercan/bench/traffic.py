"""Bench commands on the bus's traffic: monitor, record, replay, decode, incident.

Owner: the CLI's main thread; a bus's reader threads only hand it frames.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import sys
import time
from pathlib import Path

import can
import can.cli
from canopen.objectdictionary import ObjectDictionary

from can_config import load_config, load_drive_od
from can_config.eds import variable
from can_config.errors import ConfigError
from can_config.objects import OD, STRUCT_FORMAT
from motor_driver.process.stop import StopSignal
from motor_driver.recording.files import read_recording
from rovercan.argtypes import real, whole
from rovercan.bench.common import add_bus_args, add_json, emit, open_bus, output_file, receive
from rovercan.decode import PdoField, PdoLayouts, candump_line, decode, node_of

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ traffic
def pdo_layouts_for(args: argparse.Namespace) -> PdoLayouts:
    """PDO layouts the driver would configure, for decoding (config or EDS given)."""
    from motor_driver.protocol.pdo import plan_pdos

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
    if args.foxglove is not None:
        from rovercan.bench.views import monitor_foxglove
        return monitor_foxglove(args)
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
    from rovercan.bench.views import open_buses, read_buses, record_mcap

    if Path(args.file).suffix.lower() == ".mcap":
        output_file(args.file, "recording")
        return record_mcap(args)
    check_recording_target(args.file)
    buses = open_buses(args)
    print(f"rovercan record: recording {', '.join(name for name, _ in buses)} to {args.file}", file=sys.stderr,
          flush=True)
    n = 0
    with StopSignal() as stop, can.Logger(args.file) as logger:
        for name, got in read_buses(buses, stop.event, args.seconds):
            msg = got if len(buses) == 1 else can.Message(  # which bus, in a file of several
                timestamp=got.timestamp, arbitration_id=got.arbitration_id, data=got.data, dlc=got.dlc,
                is_extended_id=got.is_extended_id, is_remote_frame=got.is_remote_frame,
                is_error_frame=got.is_error_frame, is_rx=got.is_rx, channel=name)
            logger(msg)
            n += 1
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
    output_file(path, "recording")


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
    if args.output:
        from rovercan.bench.views import decode_mcap
        return decode_mcap(args)
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
#: An incident's table shows the first and the last this many events (a flapping drive's can
#: have a hundred thousand: laying them all out took 43 s); --json gives every one.
EVENTS_SHOWN = 50


def cmd_incident(args: argparse.Namespace) -> int:
    """The summary the flight recorder wrote, or its drives' faults as a simulator scenario."""
    from motor_driver.recording.incident import fault_steps, load_incident

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
    every = summary["events"]
    shown = every if len(every) <= 2 * EVENTS_SHOWN else every[:EVENTS_SHOWN] + every[-EVENTS_SHOWN:]
    events = [{"t_s": round(e["t"] - summary["t"], 3), "kind": e["kind"], "bus": e["bus"],
               "drive": e.get("drive") or "", "node": e.get("node") or "",
               "code": f"0x{e['code']:04X}" if e.get("code") is not None else "", "what": e.get("text", "")}
              for e in shown]
    print(f"incident {summary['kind']} at {summary['time']}: {summary['frames']} frames kept from"
          f" {summary['window_s'][0]:+.2f} s to {summary['window_s'][1]:+.2f} s"
          f" (buses {', '.join(summary['channels'].values())}); files: {summary['blf']}"
          f"{', ' + summary['png'] if summary.get('png') else ''}")
    if summary.get("plot_skipped"):
        print(f"no plot: {summary['plot_skipped']}; draw it with: python -m motor_driver.recording"
              f" {Path(args.file).with_suffix('.json')}")
    emit(args, events, "events", ["t_s", "kind", "bus", "drive", "node", "code", "what"])
    if len(shown) < len(every):
        print(f"(the first and last {EVENTS_SHOWN} of {len(every):,} events; --json gives every one)")
    return 0



def _decoding_args(parser: argparse.ArgumentParser) -> None:
    """How monitor and decode read PDOs (by a config's or an EDS's mapping), and --json."""
    parser.add_argument("--config", help="decode PDOs by the driver's mapping for this config")
    parser.add_argument("--eds", help="decode PDOs by the driver's mapping for this EDS")
    add_json(parser)


def add_foxglove_args(parser: argparse.ArgumentParser) -> None:
    """``--foxglove PORT`` and its address (monitor, sim, launch)."""
    parser.add_argument("--foxglove", type=whole(0, 65535), metavar="PORT", default=None,
                        help="serve the frames and, with --config, every drive decoded over the Foxglove WebSocket"
                             " protocol on PORT (open ws://127.0.0.1:PORT in Foxglove)")
    parser.add_argument("--foxglove-host", default="127.0.0.1", metavar="ADDRESS",
                        help="the address it is served on (default 127.0.0.1: this machine only)")


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """The traffic commands' parsers."""
    p = sub.add_parser("monitor", help="live CANopen-decoded traffic")
    add_bus_args(p)
    p.add_argument("--node", type=whole(1, 127), help="only this node")
    p.add_argument("--table", action="store_true", help="a per-node table at the end instead of lines")
    p.add_argument("--seconds", type=real(0, 1e6), default=0.0, help="stop after S seconds (default: Ctrl+C)")
    _decoding_args(p)
    add_foxglove_args(p)
    p.set_defaults(func=cmd_monitor)

    p = sub.add_parser("record", help="record the bus to a file: .mcap (ROS 2 messages, with --config every drive"
                       " decoded) or a python-can log (.log .asc .blf .trc .csv)")
    p.add_argument("file")
    add_bus_args(p)
    p.add_argument("--config", help="record every bus of this config (-c BUS: one), and with .mcap decode its drives")
    p.add_argument("--seconds", type=real(0, 1e6), default=0.0, help="stop after S seconds (default: Ctrl+C)")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", help="replay a recording onto the bus with its timing")
    p.add_argument("file")
    add_bus_args(p)
    p.add_argument("--fast", action="store_true", help="as fast as possible, ignoring timestamps")
    p.add_argument("--filter", type=parse_filter, action="append", metavar="ID[:MASK]",
                   help="only frames matching (hex, repeatable), e.g. 0x181 or 0x180:0x780")
    p.add_argument("--allow-commands", action="store_true",
                   help="also send NMT, RPDO, SDO request and LSS frames (left out by default)")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("decode", help="CANopen-decoded transcript of a recording")
    p.add_argument("file")
    p.add_argument("--node", type=whole(1, 127), help="only this node")
    p.add_argument("-o", "--output", metavar="OUT.mcap",
                   help="write the recording as ROS 2 messages to OUT.mcap (with --config every drive decoded)")
    _decoding_args(p)
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser("incident", help="what the flight recorder kept of an incident (its .json, .blf or .png)")
    p.add_argument("file")
    p.add_argument("--scenario", action="store_true",
                   help="print the drives' faults as a simulator scenario (YAML) instead: a regression test")
    add_json(p)
    p.set_defaults(func=cmd_incident)
