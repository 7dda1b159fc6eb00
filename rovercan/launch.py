"""``rovercan launch FILE.xml [name:=value ...]``: runs a ROS 2 XML launch file where the
``ros2`` CLI is absent (the PyPI ROS wheels carry no ``launch``).

It understands the subset the project's launch files use: ``<arg name default>``,
``<node pkg exec name>`` with ``<param name value>``, ``<executable cmd>``, ``$(var name)``
substitutions and ``if``/``unless`` attributes. Nodes of ``rovercan_bringup`` run as
``python -m nodes.<exec>`` subprocesses; anything else is refused with a clear error.
On SIGINT/SIGTERM (or ``--duration``) the processes are stopped in reverse start order, each
with SIGINT, then SIGTERM, then SIGKILL, and each gone before the next one is signalled.

Owner: the CLI's main thread, which starts, watches and ends the launched processes.
"""

from __future__ import annotations

import ctypes
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
EXECUTABLES = ("motor_controller", "motor_degree", "rover_driver", "rover_lifecycle")
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


def _split_then_substitute(cmd: str, args: dict[str, str], where: str) -> list[str]:
    """The command split into words as written, then each ``$(var ...)`` filled in within its
    word (the substitution is masked while splitting: it holds a space)."""
    names: list[str] = []

    def mask(match: re.Match[str]) -> str:
        names.append(match.group(0))
        return f"\x00{len(names) - 1}\x00"

    try:
        words = shlex.split(_VAR.sub(mask, cmd))
    except ValueError as err:
        raise ConfigError(f"{where}: cannot split cmd {cmd!r}: {err}") from err
    return [_substitute(re.sub("\x00(\\d+)\x00", lambda m: names[int(m.group(1))], word), args, where)
            for word in words]


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
            # split first, then substitute into each word: a value is one argument whatever it
            # holds (quotes, spaces, "--flags")
            argv = _split_then_substitute(element.get("cmd", ""), args, where)
            if argv and argv[0] == "rovercan":
                argv = [sys.executable, "-m", "rovercan", *argv[1:]]
            processes.append(Process(Path(argv[0]).name if argv else "?", argv))
        elif element.tag == "node":
            pkg, exe = element.get("pkg"), element.get("exec", "")
            if pkg != PACKAGE or exe not in EXECUTABLES:
                raise ConfigError(f"{where}: pkg={pkg!r} exec={exe!r} is not an executable of this project"
                                  f" ({PACKAGE}: {', '.join(EXECUTABLES)})")
            node_name = element.get("name")  # as ros2 launch: a name renames every node of the process
            argv = [sys.executable, "-m", f"nodes.{exe}", "--ros-args", *(["-r", f"__node:={node_name}"] if node_name else [])]
            for param in element.iter("param"):
                value = _substitute(param.get("value", ""), args, where)
                if value != "":
                    argv += ["-p", f"{param.get('name')}:={value}"]
            processes.append(Process(node_name or exe, argv))
        elif element.tag != "arg":
            raise ConfigError(f"{where}: element not supported by rovercan launch")
    return processes


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the launcher dies (even by SIGKILL), since the
    children run in their own process group and a terminal's Ctrl+C no longer reaches them."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass  # not Linux: the launcher's own stop path remains


PR_SET_PDEATHSIG = 1


def _stop(proc: Process) -> None:
    """SIGINT, then SIGTERM, then SIGKILL, STOP_GRACE_S apart, until the process is gone."""
    assert proc.popen is not None
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if proc.popen.poll() is not None:
            return
        proc.popen.send_signal(sig)
        try:
            proc.popen.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            print(f"rovercan launch: {proc.name} still running {STOP_GRACE_S:g} s after {signal.Signals(sig).name}",
                  file=sys.stderr, flush=True)


def foxglove_monitor(processes: list[Process], port: int, host: str) -> Process:
    """``--foxglove PORT``: a ``rovercan monitor`` of the driver's config (its nodes' ``config``
    parameter, else the embedded default) serving the live view, started after the others."""
    from can_config import DEFAULT_CONFIG

    given = [arg.partition(":=")[2] for proc in processes for arg in proc.argv if arg.startswith("config:=")]
    config = next((value for value in given if value), str(DEFAULT_CONFIG))
    return Process("foxglove", [sys.executable, "-m", "rovercan", "monitor", "--config", config, "--foxglove", str(port),
                                "--foxglove-host", host])


def run_launch(path: Path, overrides: dict[str, str], duration_s: float | None, foxglove: int | None = None,
               foxglove_host: str = "127.0.0.1") -> int:
    """Starts the processes in file order, each in its own session (a terminal's Ctrl+C
    reaches only this runner), and stops them in reverse order, each gone before the next is
    signalled: the driver brings its drives to a safe state while the bus (the simulator) is
    still there. ``foxglove``: also the live view on that port (:func:`foxglove_monitor`)."""
    processes = parse_launch(path, overrides)
    if foxglove is not None:
        processes.append(foxglove_monitor(processes, foxglove, foxglove_host))
    stop = {"flag": False}

    def on_signal(signum: int, frame: object) -> None:
        stop["flag"] = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    env = dict(os.environ)
    env.setdefault(*LOCAL_DISCOVERY)
    failed = 0
    try:
        for proc in processes:
            print(f"rovercan launch: starting {proc.name}: {shlex.join(proc.argv)}", flush=True)
            # the runner has no threads, so preexec_fn is safe here
            proc.popen = subprocess.Popen(proc.argv, env=env, start_new_session=True,
                                          preexec_fn=_die_with_parent)  # noqa: PLW1509
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
        for proc in reversed(processes):
            if proc.popen is not None:
                _stop(proc)
        for sig, handler in old.items():
            signal.signal(sig, handler)
    for proc in processes:
        assert proc.popen is not None
        code = proc.popen.returncode
        if code not in (0, -signal.SIGINT, -signal.SIGTERM):
            failed = 1
    return failed
