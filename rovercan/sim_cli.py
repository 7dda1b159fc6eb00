"""``rovercan sim``: serve a virtual CAN bus with simulated CiA 402 drives (socketcand protocol
on loopback), or put them on a python-can bus; ``--foxglove PORT`` serves the live view of the
buses it serves (:func:`rovercan.bench.views.serve_sims_view`).

Owner: the CLI's main thread; the simulator's service owns its threads.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from can_config import RoverConfig, load_config
from can_config.errors import ConfigError
from can_config.realtime import ensure_thread_realtime
from motor_driver.process import heap
from motor_driver.process.stop import StopSignal
from rovercan.argtypes import BusKwargs, real, whole
from rovercan.bench.traffic import add_foxglove_args
from rovercan.exits import EXIT_FAILED, EXIT_OK


def add_sim_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
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
    add_foxglove_args(p)
    p.set_defaults(func=cmd_sim)


def _sim_steps(args: argparse.Namespace) -> list[dict[str, Any]] | None:
    """The fault steps of --scenario or --scenario-from-log, refused before anything is served."""
    if args.scenario and args.scenario_from_log:
        raise ConfigError("give --scenario or --scenario-from-log, not both")
    if args.scenario:
        from virtual_can.scenario import load_scenario
        return load_scenario(args.scenario)
    if args.scenario_from_log:
        from motor_driver.recording.incident import fault_steps
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
    if args.drive_processes and args.foxglove is not None:
        raise ConfigError("--foxglove with --drive-processes: not served; run `rovercan monitor --config C --foxglove"
                          " PORT` beside it")
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
        if args.foxglove is not None:
            from rovercan.bench.views import serve_sims_view
            stack.enter_context(serve_sims_view(sims, args.config, args.foxglove_host, args.foxglove))
        heap.settle()  # the drives' object dictionaries live as long as the server: out of the collector's walks
        next_status = time.monotonic() + args.status_period if args.status_period else None
        # this loop wakes 5 times a second: an ordinary thread holding the interpreter when other
        # real-time work takes the cores would hold every simulator thread behind it (issue 73)
        ensure_thread_realtime("rovercan sim's main thread")
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
    if args.foxglove is not None:
        raise ConfigError("--foxglove serves the simulator's own buses; with --bus-interface run `rovercan monitor"
                          " --foxglove PORT` on that bus")
    import can.cli

    from can_config import load_drive_od
    from can_config.config import GENERIC_EDS
    from virtual_can.service import specs_from_config
    from virtual_can.sim import DriveSimulator, SimulatedDrive

    if args.config:
        config = load_config(args.config)
        served = _config_bus_for(config, args.config, getattr(args, "bus_channel", None))
        drives = [spec.drive() for spec, d in zip(specs_from_config(config), config.drives, strict=True)
                  if d.bus == served]
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
