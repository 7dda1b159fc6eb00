"""Bench commands that check without moving: safety-check, check, plan; and can-up.

Owner: the CLI's main thread.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import math
import re
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config import RoverConfig, load_config, load_drive_od
from can_config.eds import consumer_subs, variable
from can_config.errors import ConfigError
from can_config.objects import OD
from motor_driver.bus.sdo_client import OwnAnswersNode
from motor_driver.protocol.codec import unpack_value, value_format
from rovercan.argtypes import real, whole
from rovercan.bench.common import (
    SDO_TIMEOUT_S,
    CliError,
    _u32,
    add_bus_args,
    add_config_arg,
    add_drive_args,
    add_json,
    config_bus,
    emit,
    one_drive_config,
    open_bus,
    receive,
    sdo_upload,
)

if TYPE_CHECKING:
    import can

    from can_config.config import BusConfig, DriveConfig
    from motor_driver.protocol.safety import SafetyCheck

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ safety-check
def safety_configs(args: argparse.Namespace) -> list[RoverConfig]:
    """The drives to check, one config per bus: every drive of --config on each of its buses (or
    on the one -c names), or --node N ... with --eds on the bus given."""
    if args.config:
        config = load_config(args.config)
        buses = [config_bus(args, config)] if getattr(args, "channel", None) else list(config.buses)
        out = []
        for bus in buses:
            drives = tuple(d for d in config.drives if d.bus == bus.name and (not args.node or d.node_id in args.node))
            if drives:
                out.append(RoverConfig((bus,), drives, None, config.source))
        if not out:
            raise ConfigError(f"{args.config}: no drive on bus {' or '.join(b.name for b in buses)}"
                              f"{' with node id ' + str(args.node) if args.node else ''}")
        return out
    if not args.node:
        raise ConfigError("safety-check: give --config FILE, or --eds FILE with --node N (repeatable)")
    configs = [one_drive_config(args, str(node)) for node in args.node]
    return [RoverConfig(configs[0].buses, tuple(c.drives[0] for c in configs), None, None)]


def _host_heartbeat(bus: can.BusABC, bus_cfg: BusConfig, listen_s: float) -> SafetyCheck:
    """The host heartbeat on the bus for ``listen_s``, judged against its configured period."""
    from motor_driver.protocol.safety import host_heartbeat_check

    beats: list[float] = []
    deadline = time.monotonic() + listen_s
    while (remaining := deadline - time.monotonic()) > 0:
        msg = receive(bus, remaining)
        if msg is not None and msg.arbitration_id == 0x700 + bus_cfg.host_node_id and not msg.is_remote_frame:
            beats.append(msg.timestamp)
    return host_heartbeat_check(bus_cfg.host_node_id, bus_cfg.host_heartbeat_s,
                                [b - a for a, b in itertools.pairwise(beats)])


def _drive_safety_rows(network: canopen.Network, cfg: DriveConfig, bus_cfg: BusConfig) -> list[dict[str, Any]]:
    """One drive's safety objects read back by SDO and judged by the driver's rules: a drive the
    driver would guard (:func:`watch_mode`, a bus with remote frames) by its guard settings."""
    from motor_driver.bus.connect import carries_remote_frames
    from motor_driver.protocol.safety import judge, watch_mode
    from motor_driver.protocol.units import UNIT_OBJECTS, scale_from_objects

    rows: list[dict[str, Any]] = []
    od = load_drive_od(cfg.eds, cfg.node_id)
    node = OwnAnswersNode(cfg.node_id, od)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    network.add_node(node)

    def read(index: int, sub: int, node: canopen.RemoteNode = node, od: ObjectDictionary = od) -> int | None:
        if variable(od, index, sub) is None:
            return None
        raw = sdo_upload(node, index, sub)
        fmt = value_format(od, index, sub)
        value = unpack_value(fmt, raw[:struct.calcsize(fmt)] if fmt else raw)
        return _u32(raw) if value is None else int(value)

    objects = {(i, sub): v for i, subs in UNIT_OBJECTS for sub in subs if (v := read(i, sub)) is not None}
    scale, _ = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm, objects,
                                  invert=cfg.invert, offset_deg=cfg.offset_deg)
    subs = consumer_subs(od)
    guarding = watch_mode(cfg, od) == "guarding" and carries_remote_frames(network.bus)
    for check in judge(cfg, bus_cfg.host_node_id, scale, read, consumer_subs=subs, guarding=guarding):
        rows.append({"node": cfg.node_id, "drive": cfg.name, **vars(check)})
    return rows


def cmd_safety_check(args: argparse.Namespace) -> int:
    """Read back from each drive what keeps it safe when the host is gone; judge it by the
    driver's own rules (motor_driver.protocol.safety); and look for the host heartbeat on each bus."""
    if args.listen is not None and not (math.isfinite(args.listen) and 0 < args.listen <= 60):
        raise ConfigError(f"--listen {args.listen}: allowed 0 < seconds <= 60")
    failed: list[dict[str, Any]] = []
    for config in safety_configs(args):
        bus_cfg = config.buses[0]
        args.config_bus = bus_cfg.name if args.config else None
        rows = _safety_rows(args, config, args.listen or max(0.3, 4 * bus_cfg.host_heartbeat_s))
        emit(args, rows, f"safety check ({bus_cfg.name})", ["node", "drive", "check", "object", "expected", "actual",
                                                             "status"])
        failed += [r for r in rows if r["status"] == "FAIL"]
    if failed:
        names = ", ".join(f"{r['drive']} {r['check']} ({r['object']})" for r in failed)
        print(f"rovercan: safety check failed: {names}", file=sys.stderr)
        return 1
    return 0


def _safety_rows(args: argparse.Namespace, config: RoverConfig, listen_s: float) -> list[dict[str, Any]]:
    """The host heartbeat and every drive's rows of one bus."""
    bus_cfg = config.buses[0]
    bus = open_bus(args)
    rows: list[dict[str, Any]] = []
    try:
        host = _host_heartbeat(bus, bus_cfg, listen_s)
        rows.append({"node": "-", "drive": "(host)", **vars(host)})
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.1
        network.connect()
        try:
            for cfg in config.drives:
                rows += _drive_safety_rows(network, cfg, bus_cfg)
        finally:
            if network.notifier is not None:
                network.notifier.stop(1.0)
    finally:
        bus.shutdown()
    return rows


# ------------------------------------------------------------------------------ bus-health
def cmd_bus_health(args: argparse.Namespace) -> int:
    """The bus's health as its kernel knows it (motor_driver.bus.link): state, error counters,
    bitrate, restarts. Exit 0 when up and ERROR-ACTIVE (or a vcan, which has no controller) and,
    with --watch, no error or drop counter rose; else 1 naming what is wrong and what to do. A bus
    that is not a kernel interface: said to be unknown."""
    from motor_driver.bus.link import read_kernel_health, rising

    interface, channel = getattr(args, "interface", None), getattr(args, "channel", None)
    if getattr(args, "config", None):
        bus_cfg = config_bus(args, load_config(args.config))
        interface, channel = interface or bus_cfg.interface, bus_cfg.channel if interface is None else channel
    if not interface or not channel:
        raise ConfigError("bus-health: give -i socketcan -c CHANNEL (e.g. -c can0), or --config FILE [-c BUS]")
    if interface != "socketcan":
        emit(args, {"interface": interface, "channel": channel, "state": "unknown",
                    "why": "only a kernel (socketcan) interface has a controller state to read"},
             f"bus health of {channel}")
        return 0
    health = read_kernel_health(channel)
    problems = health.problems()
    if args.watch:  # a second read: counters that rise while nothing else changed
        first = health
        time.sleep(args.watch)
        health = read_kernel_health(channel)
        problems = health.problems() + rising(first, health, args.watch)
    row = {k: ("unknown" if v is None else v) for k, v in health.as_dict().items()}
    if health.kind != "can":
        row["state"] = f"none ({health.kind}: no controller)"
    emit(args, row, f"bus health of {channel}")
    for problem in problems:
        print(f"rovercan bus-health: {problem}", file=sys.stderr)
    return 0 if health.ok and not problems else 1


# ------------------------------------------------------------------------------ plan / can-up
def cmd_plan(args: argparse.Namespace) -> int:
    from motor_driver.bus.load import MAX_LOAD, WARN_LOAD, plan_load

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


def served_text(config: RoverConfig) -> str:
    """How `rovercan sim --config` serves this config: one server per socketcand port."""
    from virtual_can.service import served_ports

    served = served_ports(config)
    servers = "; ".join(f"port {s.port}: {', '.join(s.channels)} ({len(s.specs)} drive(s))" for s in served)
    return f"rovercan sim --config serves it as {len(served)} server(s) on 127.0.0.1: {servers}"


def _host_watch_text(drive: DriveConfig, od: ObjectDictionary, bus: BusConfig) -> str:
    """How the driver will have ``drive`` watch the host, by its own rule (:func:`watch_mode`;
    guarding only where the bus carries remote frames), or why nothing will."""
    from can_config.eds import has_object
    from motor_driver.protocol.safety import watch_mode

    if watch_mode(drive, od) == "guarding":
        if not (has_object(od, OD.GUARD_TIME) and has_object(od, OD.LIFE_TIME_FACTOR)):
            why = "host_watch: guarding, but the drive has no 0x100C/0x100D"
        elif bus.interface == "socketcand":
            why = "node guarding needs remote frames, which socketcand does not carry"
        else:
            return "node guarding (0x100C/0x100D)"
    elif has_object(od, OD.CONSUMER_HEARTBEAT_TIME, 1):
        return "heartbeat consumer (0x1016)"
    else:
        why = "no heartbeat consumer (0x1016)"
    return f"none: {why} (allow_no_host_watch)" if drive.allow_no_host_watch else f"NONE: {why}; it will not be enabled"


def cmd_check(args: argparse.Namespace) -> int:
    """A config checked without a bus: parsed, each drive's EDS read (with the objects the driver
    needs for its host watch), the drive system's wheels known, each bus's planned load. Exit 0,
    or 2 with the first problem (a ConfigError names file, key and what is allowed)."""
    from motor_driver.bus.load import MAX_LOAD, plan_load
    from motor_driver.drive import protected_reason

    config = load_config(args.config)
    rows: list[dict[str, Any]] = []
    for drive in config.drives:
        for setting in drive.sdo:  # the boot refuses them: said here, before any bus
            reason = protected_reason(setting.index)
            if reason:
                raise ConfigError(f"{args.config}: drive {drive.name!r}: sdo entry 0x{setting.index:04X}:{setting.sub}"
                                  f" is the driver's own: {reason}; remove the entry")
        od = load_drive_od(drive.eds, drive.node_id)  # an EdsError names the file
        rows.append({"bus": drive.bus, "drive": drive.name, "node": drive.node_id, "eds": Path(drive.eds).name,
                     "host watch": _host_watch_text(drive, od, config.bus(drive.bus))})
    loads = {load.bus: load.load for load in plan_load(config)}
    for bus in config.buses:
        rows.append({"bus": bus.name, "drive": "-", "node": "-", "eds": f"{bus.interface} {bus.channel}",
                     "host watch": f"planned load {100 * loads.get(bus.name, 0.0):.1f} %"})
    emit(args, rows, f"{args.config}: valid", ["bus", "drive", "node", "eds", "host watch"])
    system = config.drive_system
    if system is not None and not args.json:
        print(f"drive system: left {', '.join(system.left)}; right {', '.join(system.right)}; track"
              f" {system.track_width_m:g} m, wheel radius {system.wheel_radius_m:g} m")
    if not args.json:
        print(served_text(config))
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


def can_up_settings(args: argparse.Namespace) -> tuple[int, int, int, str]:
    """(bitrate, restart-ms, txqueuelen, where they come from): each given flag, else the --config
    bus on the interface's, else the embedded default config's."""
    config = load_config(args.config)  # None: the embedded default
    on_it = [b for b in config.buses if b.channel == args.interface_name] or list(config.buses[:1])
    bus = on_it[0]
    source = f"bus {bus.name} of {args.config or 'the embedded default config'}"
    given = [flag for flag, value in (("--bitrate", args.bitrate), ("--restart-ms", args.restart_ms),
                                      ("--txqueuelen", args.txqueuelen)) if value is not None]
    return (args.bitrate if args.bitrate is not None else bus.bitrate,
            args.restart_ms if args.restart_ms is not None else bus.restart_ms,
            args.txqueuelen if args.txqueuelen is not None else bus.txqueuelen,
            ", ".join(given) + (f"; the rest from {source}" if len(given) < 3 else "") if given else source)


def cmd_can_up(args: argparse.Namespace) -> int:
    bitrate, restart_ms, txqueuelen, source = can_up_settings(args)
    vcan = args.interface_name.startswith("vcan")
    if not vcan:
        print(f"# bitrate {bitrate} bit/s, restart-ms {restart_ms}, txqueuelen {txqueuelen} from {source}", flush=True)
    commands = can_up_commands(args.interface_name, bitrate, restart_ms, txqueuelen)
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



def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """The checks commands' parsers."""
    p = sub.add_parser("safety-check", help="read back what stops each drive when the host is gone; pass/fail")
    p.add_argument("--node", type=whole(1, 127), action="append", help="node id (repeatable; default:"
                   " every drive of --config, on each of its buses or on the one -c names)")
    add_drive_args(p)
    add_bus_args(p)
    p.add_argument("--listen", type=real(0.05, 600), help="seconds to watch for the host heartbeat (default 4 periods)")
    add_json(p)
    p.set_defaults(func=cmd_safety_check)

    p = sub.add_parser("bus-health", help="the kernel's view of a CAN bus: state, error counters, bitrate, restarts;"
                                          " exit 1 unless up and ERROR-ACTIVE")
    add_bus_args(p)
    add_config_arg(p)
    p.add_argument("--watch", type=real(0.1, 3600), metavar="S", help="read twice, S seconds apart: exit 1 also when"
                   " an error or drop counter rose")
    add_json(p)
    p.set_defaults(func=cmd_bus_health)

    p = sub.add_parser("check", help="validate a config without a bus: keys, EDS files, host watch, drive system, load")
    p.add_argument("--config", required=True)
    add_json(p)
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("plan", help="worst-case bus load of a config")
    p.add_argument("--config", required=True)
    add_json(p)
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("can-up", help="bring up a SocketCAN interface (runs ip, no shell); vcanN: a virtual one")
    p.add_argument("interface_name", metavar="INTERFACE")
    p.add_argument("--bitrate", type=whole(10_000, 1_000_000),
                   help="bit/s (default: the --config bus on INTERFACE, else the embedded default config's)")
    p.add_argument("--config", help="take bitrate, restart-ms and txqueuelen from this config's bus on INTERFACE")
    p.add_argument("--restart-ms", type=whole(0, 60_000), help="automatic restart after a bus-off (default: the"
                   " config's restart_ms, 100)")
    p.add_argument("--txqueuelen", type=whole(10, 100_000), help="transmit queue in frames (default: the config's"
                   " txqueuelen, 1000)")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    p.set_defaults(func=cmd_can_up)
