"""``rovercan launch FILE.xml [name:=value ...]``: runs a ROS 2 XML launch file where the
``ros2`` CLI is absent (the PyPI ROS wheels carry no ``launch``).

It understands the subset the project's launch files use: ``<arg name default>``,
``<node pkg exec name>`` with ``<param name value>``, ``<executable cmd>``, ``$(var name)``
substitutions and ``if``/``unless`` attributes. Nodes of ``rovercan_bringup`` run as
``python -m nodes.<exec>`` subprocesses; anything else is refused with a clear error.
On SIGINT/SIGTERM (or ``--duration``) every process gets SIGINT, then SIGTERM, then SIGKILL.
"""

from __future__ import annotations

import logging
import os
import re
import shlex
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from can_config.errors import ConfigError

logger = logging.getLogger(__name__)

PACKAGE = "rovercan_bringup"
EXECUTABLES = ("motor_controller", "motor_degree", "rover_driver")
STOP_GRACE_S = 5.0
_VAR = re.compile(r"\$\(var ([A-Za-z_][A-Za-z0-9_]*)\)")


@dataclass
class Process:
    name: str
    argv: list[str]
    popen: subprocess.Popen[bytes] | None = field(default=None)


#: ROS 2 (Jazzy) discovery for graphs that are local by design (the demo, launch without ros2,
#: tests, benchmarks): DDS then sends nothing beyond loopback. The deployed nodes keep the
#: environment's setting, since a rover's graph spans machines.
LOCAL_DISCOVERY = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

def _substitute(text: str, args: dict[str, str], where: str) -> str:
    def repl(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in args:
            raise ConfigError(f"{where}: $(var {name}) is not a declared <arg>; declared: {sorted(args)}")
        return args[name]
    return _VAR.sub(repl, text)


def _truthy(value: str, where: str) -> bool:
    lowered = value.strip().lower()
    if lowered in ("true", "1"):
        return True
    if lowered in ("false", "0", ""):
        return False
    raise ConfigError(f"{where}: condition {value!r} is not true/false")


def parse_launch(path: Path, overrides: dict[str, str]) -> list[Process]:
    """The processes a launch file starts, with its args resolved."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as err:
        raise ConfigError(f"{path}: cannot read the launch file: {err}") from err
    if root.tag != "launch":
        raise ConfigError(f"{path}: the root element is <{root.tag}>, expected <launch>")
    args: dict[str, str] = {}
    for arg in root.iter("arg"):
        name = arg.get("name", "")
        args[name] = arg.get("default", "")
    unknown = set(overrides) - set(args)
    if unknown:
        raise ConfigError(f"{path}: unknown launch argument(s) {sorted(unknown)}; declared: {sorted(args)}")
    args.update(overrides)
    processes: list[Process] = []
    for element in root:
        where = f"{path}: <{element.tag}>"
        cond_if = element.get("if")
        cond_unless = element.get("unless")
        if cond_if is not None and not _truthy(_substitute(cond_if, args, where), where):
            continue
        if cond_unless is not None and _truthy(_substitute(cond_unless, args, where), where):
            continue
        if element.tag == "executable":
            argv = shlex.split(_substitute(element.get("cmd", ""), args, where))
            if argv and argv[0] == "rovercan":
                argv = [sys.executable, "-m", "rovercan", *argv[1:]]
            processes.append(Process(Path(argv[0]).name if argv else "?", argv))
        elif element.tag == "node":
            pkg, exe = element.get("pkg"), element.get("exec", "")
            if pkg != PACKAGE or exe not in EXECUTABLES:
                raise ConfigError(f"{where}: pkg={pkg!r} exec={exe!r} is not an executable of this project"
                                  f" ({PACKAGE}: {', '.join(EXECUTABLES)})")
            name = element.get("name", exe)
            argv = [sys.executable, "-m", f"nodes.{exe}", "--ros-args", "-r", f"__node:={name}"]
            for param in element.iter("param"):
                value = _substitute(param.get("value", ""), args, where)
                if value != "":
                    argv += ["-p", f"{param.get('name')}:={value}"]
            processes.append(Process(name, argv))
        elif element.tag != "arg":
            raise ConfigError(f"{where}: element not supported by rovercan launch")
    return processes


def run_launch(path: Path, overrides: dict[str, str], duration_s: float | None) -> int:
    processes = parse_launch(path, overrides)
    stop = {"flag": False}

    def on_signal(signum: int, frame: object) -> None:
        stop["flag"] = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    env = dict(os.environ)
    env.setdefault(*LOCAL_DISCOVERY)
    failed = 0
    try:
        for proc in processes:
            print(f"rovercan launch: starting {proc.name}: {' '.join(proc.argv)}", flush=True)
            proc.popen = subprocess.Popen(proc.argv, env=env)
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not stop["flag"] and (deadline is None or time.monotonic() < deadline):
            for proc in processes:
                assert proc.popen is not None
                code = proc.popen.poll()
                if code is not None:
                    print(f"rovercan launch: {proc.name} exited with {code}; stopping the others",
                          file=sys.stderr, flush=True)
                    failed = 1 if code != 0 else failed
                    stop["flag"] = True
            time.sleep(0.1)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            alive = [p for p in reversed(processes) if p.popen is not None and p.popen.poll() is None]
            for proc in alive:
                assert proc.popen is not None
                proc.popen.send_signal(sig)
            end = time.monotonic() + STOP_GRACE_S
            while any(p.popen is not None and p.popen.poll() is None for p in alive) and time.monotonic() < end:
                time.sleep(0.05)
        for sig, handler in old.items():
            signal.signal(sig, handler)
    for proc in processes:
        assert proc.popen is not None
        code = proc.popen.returncode
        if code not in (0, -signal.SIGINT, -signal.SIGTERM):
            failed = 1
    return failed
