"""``rovercan``: one CLI for the simulator, the demo and bench work.

Each subcommand is a thin function over the library. Exit codes: 0 ok, 1 the operation
failed (message on stderr), 2 bad usage or configuration.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import re
import signal
import sys
import time
from collections.abc import Sequence
from contextlib import ExitStack
from decimal import Decimal
from pathlib import Path
from typing import Any

from can_config import RoverConfig, heap, load_config
from can_config.errors import CommandRejected, ConfigError, RovercanError, SimError
from can_config.realtime import DRIVER_PRIORITY
from can_config.stop import StopSignal, stop_on_signals
from rovercan.argtypes import BusKwargs, real, whole

logger = logging.getLogger(__name__)

#: The one rule for exit codes (README, Bench testing).
EXIT_OK = 0  # done
EXIT_FAILED = 1  # the bus or a drive failed or refused
EXIT_USAGE = 2  # bad usage, a bad config or input, or a command refused before it was sent


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # python-can's socketcand client warns whenever TCP splits a line: not a fault
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    if verbose == 0:  # the command reports failures itself, with their meaning
        logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
        # its receive errors carry a Python traceback in the text; receive() says it in one line
        logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)


# ---------------------------------------------------------------------------- sim
def _sim_steps(args: argparse.Namespace) -> list[dict[str, Any]] | None:
    """The fault steps of --scenario or --scenario-from-log, refused before anything is served."""
    if args.scenario and args.scenario_from_log:
        raise ConfigError("give --scenario or --scenario-from-log, not both")
    if args.scenario:
        from virtual_can.scenario import load_scenario
        return load_scenario(args.scenario)
    if args.scenario_from_log:
        from can_config.incident import fault_steps
        steps = fault_steps(args.scenario_from_log, args.scenario_delay)
        if not steps:
            raise ConfigError(f"{args.scenario_from_log}: the incident has no drive faults to replay (no EMCY,"
                              " silence or reboot of a configured drive in its frames)")
        return steps
    return None


def sim_servers(args: argparse.Namespace, playing: bool) -> list[Any]:
    """What ``rovercan sim`` serves: with --config, one server per socketcand port of its buses
    (``virtual_can.service.served_ports``); else --drives on --channel at --port."""
    from virtual_can.server import DEFAULT_PORT
    from virtual_can.service import ServedPort, served_ports, specs_for_count

    if not args.config:
        from can_config.config import GENERIC_EDS
        specs = specs_for_count(args.drives, Path(args.eds) if args.eds else GENERIC_EDS, args.channel)
        return [ServedPort(DEFAULT_PORT if args.port is None else args.port, (args.channel,), tuple(specs))]
    served = served_ports(load_config(args.config))
    ports = ", ".join(str(s.port) for s in served)
    if args.port is not None and len(served) > 1:
        raise ConfigError(f"--port {args.port}: {args.config} has buses on ports {ports}; each is served at its"
                          " own: drop --port")
    if playing and len(served) > 1:
        raise ConfigError(f"{args.config}: a scenario plays on one server, and its buses use ports {ports};"
                          " serve one port's buses per `rovercan sim`")
    return [dataclasses.replace(served[0], port=args.port)] if args.port is not None else served


def cmd_sim(args: argparse.Namespace) -> int:
    if getattr(args, "bus_interface", None):  # python-can's bus arguments default to "absent"
        return _sim_on_bus(args)
    from virtual_can.service import SimService

    steps = _sim_steps(args)
    served = sim_servers(args, steps is not None)
    if args.drive_processes:
        from rovercan.sim_processes import serve_with_drive_processes
        return serve_with_drive_processes(args, served, steps is not None)
    with StopSignal() as stop, ExitStack() as stack:
        sims = [stack.enter_context(SimService(s.specs, host=args.host, port=s.port, extra_channels=s.channels,
                                               wire_time=args.wire_time, bitrate=args.bitrate,
                                               allow_remote=args.allow_remote)) for s in served]
        for sim in sims:
            print(f"rovercan sim: {sum(len(x.drives) for x in sim.simulators.values())} simulated drive(s) on"
                  f" {', '.join(sim.simulators)}, socketcand protocol on {sim.host}:{sim.port}", flush=True)
            for channel in sim.simulators:
                print(f"  python-can arguments: {sim.python_can_args(channel)}", flush=True)
        if steps is not None:
            from virtual_can.scenario import run_steps_in_background
            print(f"rovercan sim: playing {len(steps)} fault step(s) of"
                  f" {args.scenario or args.scenario_from_log}", flush=True)
            run_steps_in_background(sims[0], steps, stop.event)
        heap.settle()  # the drives' object dictionaries live as long as the server: out of the collector's walks
        next_status = time.monotonic() + args.status_period if args.status_period else None
        while not stop.event.wait(0.2):
            if next_status is not None and time.monotonic() >= next_status:
                next_status += args.status_period
                for simulator in (x for sim in sims for x in sim.simulators.values()):
                    for drive in simulator.drives.values():
                        print(simulator.call(drive.status_line), flush=True)
        print("rovercan sim: stopped", flush=True)
    return EXIT_OK


def _config_bus_for(config: RoverConfig, path: str, channel: str | None) -> str:
    """The config bus whose drives go on the python-can bus ``channel``: the one with that
    channel, or the only one. Each bus's node ids are its own (node 1 on can0 and node 1 on
    can1 are two drives), so the drives of two buses never share one."""
    if len(config.buses) == 1:
        return config.buses[0].name
    matching = [b.name for b in config.buses if b.channel == channel]
    if len(matching) == 1:
        return matching[0]
    buses = ", ".join(f"{b.name} (channel {b.channel})" for b in config.buses)
    raise ConfigError(f"{path}: drives on several buses ({buses}) and none has channel {channel!r}; a bus"
                      " carries the drives of one config bus: run one `rovercan sim --config ... --bus-channel"
                      " CHANNEL` per bus, with that bus's channel")


def _sim_on_bus(args: argparse.Namespace) -> int:
    """Simulated drives on a real python-can bus (e.g. a kernel vcan0), no server."""
    import can.cli

    from can_config import load_drive_od
    from can_config.config import GENERIC_EDS
    from virtual_can.sim import DriveSimulator, MotorParams, SimulatedDrive

    if args.config:
        config = load_config(args.config)
        served = _config_bus_for(config, args.config, getattr(args, "bus_channel", None))
        drives = [SimulatedDrive(d.node_id, load_drive_od(d.eds, d.node_id),
                                 MotorParams.from_model(d.sim, d.counts_per_rev), name=d.name)
                  for d in config.drives if d.bus == served]
    else:
        eds = Path(args.eds) if args.eds else GENERIC_EDS
        drives = [SimulatedDrive(i, load_drive_od(eds, i)) for i in range(1, args.drives + 1)]
    try:
        bus = can.cli.create_bus_from_namespace(args, prefix="bus")
    except argparse.ArgumentError as err:
        cause = err.__cause__
        print(f"rovercan sim: cannot open {args.bus_interface} {getattr(args, 'bus_channel', '')}: {cause}",
              file=sys.stderr)
        return EXIT_FAILED
    with StopSignal() as stop, bus, DriveSimulator(bus, drives) as sim:
        names = ", ".join(f"{d.node_id} {d.name}" for d in drives)
        print(f"rovercan sim: {len(drives)} simulated drive(s) on {bus.channel_info}: {names}", flush=True)
        while not stop.event.wait(0.2):
            pass
        del sim
    print("rovercan sim: stopped", flush=True)
    return EXIT_OK


# ---------------------------------------------------------------------------- demo
def cmd_demo(args: argparse.Namespace) -> int:
    from rovercan.demo import run_demo

    return run_demo(args)


# ---------------------------------------------------------------------------- launch
def cmd_launch(args: argparse.Namespace) -> int:
    from rovercan.launch import run_launch

    overrides: dict[str, str] = {}
    for item in args.args:
        name, sep, value = item.partition(":=")
        if not sep:
            raise ConfigError(f"launch argument {item!r}: expected name:=value")
        overrides[name] = value
    return run_launch(Path(args.file), overrides, args.duration)


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rovercan", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("sim", help="serve a virtual CAN bus with simulated CiA 402 drives")
    p.add_argument("--drives", type=whole(1, 127), default=1, help="number of drives, node ids 1..N")
    p.add_argument("--config", help="simulate the drives of this rover config (a twin of the rover)")
    p.add_argument("--eds", help="EDS of the simulated drives (default: the generic CiA 402 EDS)")
    p.add_argument("--channel", default="can0", help="channel name served (default can0)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=whole(0, 65535), default=None,
                   help="TCP port (default: the config's, else 29536; 0: any free)")
    p.add_argument("--allow-remote", action="store_true", help="allow binding a non-loopback address")
    p.add_argument("--wire-time", action="store_true", help="frames take their real bit time")
    p.add_argument("--bitrate", type=whole(10_000, 8_000_000), default=1_000_000)
    p.add_argument("--scenario", help="YAML fault-injection scenario to play")
    p.add_argument("--scenario-from-log", metavar="INCIDENT",
                   help="replay the drives' faults of a flight-recorder incident (.json/.blf) at their times")
    p.add_argument("--scenario-delay", type=real(0, 3600), default=2.0,
                   help="seconds from the start to the incident's first fault (default 2: time for a driver to boot)")
    p.add_argument("--status-period", type=real(0, 3600), default=0.0, help="print a status line per drive every S seconds")
    p.add_argument("--drive-processes", action="store_true", help="with --config: each bus's drives in a process of its"
                   " own, the server alone in this one (its SYNC timer then waits for no drive model)")
    _sim_bus_args(p)
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("demo", help="the motor demo: simulator + driver + ROS nodes, live MotorState")
    p.add_argument("--config", help="rover config (default: the embedded one)")
    p.add_argument("--duration", type=real(0.1, 1e6), default=None, help="stop after S seconds (default: Ctrl+C)")
    p.add_argument("--port", type=whole(0, 65535), default=0, help="simulator port (default: any free)")
    p.add_argument("--step", type=real(-360, 360), default=0.1, help="degrees added per 0.1 s command (default 0.1)")
    p.add_argument("--print-period", type=real(0.05, 3600), default=0.5, help="seconds between printed states")
    p.add_argument("--realtime-priority", type=whole(0, 99), default=DRIVER_PRIORITY,
                   help=f"SCHED_FIFO priority of every thread, as the deployed node (default {DRIVER_PRIORITY}; 0: ordinary)")
    p.set_defaults(func=cmd_demo)

    _bench_parsers(sub)

    p = sub.add_parser("launch", help="run a ROS 2 XML launch file of this project without the ros2 CLI")
    p.add_argument("file", help="launch file, e.g. ros/rovercan_bringup/launch/motor_launch.xml")
    p.add_argument("args", nargs="*", help="launch arguments name:=value")
    p.add_argument("--duration", type=real(0.1, 1e6), default=None, help="stop after S seconds")
    p.set_defaults(func=cmd_launch)
    return parser


def _sim_bus_args(parser: argparse.ArgumentParser) -> None:
    """``--bus-*``: put the simulated drives on a python-can bus instead of serving one; the names
    python-can's ``create_bus_from_namespace(prefix="bus")`` reads (its own option set would
    name the last one --bus-bus-kwargs)."""
    group = parser.add_argument_group("instead of serving a bus: put the simulated drives on this python-can bus"
                                      " (e.g. --bus-interface socketcan --bus-channel vcan0)")
    group.add_argument("--bus-interface", default=argparse.SUPPRESS, metavar="INTERFACE",
                       help="python-can interface (socketcan, socketcand, virtual, ...)")
    group.add_argument("--bus-channel", default=argparse.SUPPRESS, metavar="CHANNEL", help="its channel, e.g. vcan0")
    group.add_argument("--bus-bitrate", type=whole(10_000, 8_000_000), default=argparse.SUPPRESS, metavar="BITRATE",
                       help="bit/s, where the interface sets it")
    group.add_argument("--bus-kwargs", dest="bus_bus_kwargs", nargs="+", action=BusKwargs, default=argparse.SUPPRESS,
                       metavar="KEY=VALUE", help="more arguments of that python-can bus, e.g. host=127.0.0.1 port=29536")


def _bench_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    from rovercan import audit
    from rovercan.bench import checks, motion, nodes, traffic

    for family in (nodes, motion, traffic, checks, audit):
        family.add_parsers(sub)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    words = list(sys.argv[1:] if argv is None else argv)
    for i, word in enumerate(words):
        if re.fullmatch(r"-(inf|infinity|nan)", word, re.IGNORECASE):  # argparse would read "-i nf"
            parser.error(f"{word} is not a finite number: angles, speeds and times must be finite")
        if re.fullmatch(r"-(\d+\.?\d*|\.\d+)[eE][+-]?\d+", word):  # argparse takes "-1e3" for an option
            words[i] = f"{Decimal(word):f}"  # the same number, in the form argparse reads as one
    args = parser.parse_args(words)
    _setup_logging(args.verbose)
    try:
        with stop_on_signals() as stop:  # SIGINT/SIGTERM/SIGHUP: the with blocks unwind, drives stopped
            return int(args.func(args))
        name = signal.Signals(stop.signum).name if stop.signum else "a signal"
        print(f"rovercan: stopped by {name}; any drive this command had armed was quick-stopped and disabled",
              file=sys.stderr)
        return EXIT_FAILED
    except (ConfigError, CommandRejected, SimError) as err:  # refused before anything was sent
        print(f"rovercan: {err}", file=sys.stderr)
        return EXIT_USAGE
    except RovercanError as err:
        print(f"rovercan: {err}", file=sys.stderr)
        return EXIT_FAILED
    except BrokenPipeError:
        # the reader went away ('rovercan monitor | head'): not a failure of this command; stdout
        # goes to /dev/null so that the interpreter's last flush does not complain again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except OSError as err:
        print(f"rovercan: {err}", file=sys.stderr)
        return EXIT_FAILED
