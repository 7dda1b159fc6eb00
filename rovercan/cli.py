"""``rovercan``: one CLI for the simulator, the demo and bench work.

Each subcommand is a thin function over the library. Exit codes: 0 ok, 1 the operation
failed (message on stderr), 2 bad usage or configuration.

Owner: the CLI's main thread.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import sys
from collections.abc import Sequence
from decimal import Decimal
from pathlib import Path

from can_config.errors import CommandRejected, ConfigError, RovercanError, SimError
from can_config.realtime import DRIVER_PRIORITY
from motor_driver.process.stop import stop_on_signals
from rovercan.argtypes import real, whole
from rovercan.exits import EXIT_FAILED, EXIT_OK, EXIT_USAGE

logger = logging.getLogger(__name__)



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
