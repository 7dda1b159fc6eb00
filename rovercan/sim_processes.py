"""``rovercan sim --config FILE --drive-processes``: the bus server in this process, each bus's
simulated drives in a process of their own, connected to it as socketcand clients (the
``--bus-interface socketcand`` form of ``rovercan sim``).

Why: a Python process runs one thread at a time. With six drive models in the
server's process, the cyclic timer that sends the SYNC waits for them to let go of the
interpreter, and the SYNC's period error grew with the number of drives (about 0.55 ms p99 with
six, 0.04 ms with one). Here the server's process holds the server alone: its clients' threads,
which each hold the interpreter for one frame's work, and the timer.

A drive process that dies is said, and the server stops (a twin with drives missing is not the
rover's twin). Fault scenarios and status lines need the drives in the server's process: the
flags are refused together with a reason.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from typing import Any

from can_config.errors import ConfigError
from motor_driver.process import heap
from motor_driver.process.stop import StopSignal
from rovercan.bench.common import CliError

#: A drive process imports python-can, canopen and the EDS files before it says it runs.
START_S = 60.0


def drive_process_argv(config: str, host: str, port: int, channel: str) -> list[str]:
    """`rovercan sim` for one bus's drives on the server at ``host:port``, channel ``channel``."""
    return [sys.executable, "-m", "rovercan", "sim", "--config", config, "--bus-interface", "socketcand",
            "--bus-channel", channel, "--bus-kwargs", f"host={host}", f"port={port}", "tcp_tune=True"]


class DriveProcess:
    """One bus's drives in a process of their own; its output kept (the last lines say why it died)."""

    def __init__(self, argv: Sequence[str], channel: str) -> None:
        self.channel = channel
        self.lines: list[str] = []
        self.proc = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"rovercan-sim-{channel}")
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))
            del self.lines[:-50]

    def running(self) -> bool:
        return any("simulated drive" in line for line in list(self.lines))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(2.0)


@contextmanager
def drive_processes(config: str, host: str, port: int, channels: Sequence[str]) -> Iterator[list[DriveProcess]]:
    """A process per channel with drives, each running once it says so; stopped on leaving."""
    started = [DriveProcess(drive_process_argv(config, host, port, ch), ch) for ch in channels]
    try:
        deadline = time.monotonic() + START_S
        while not all(p.running() for p in started):
            dead = next((p for p in started if p.proc.poll() is not None), None)
            if dead is not None or time.monotonic() > deadline:
                which = dead or next(p for p in started if not p.running())
                raise CliError(f"the simulated drives of channel {which.channel} did not start"
                               f" ({'exit ' + str(dead.proc.returncode) if dead else f'{START_S:g} s'}):"
                               f" {' | '.join(which.lines[-3:]) or 'no output'}")
            time.sleep(0.05)
        yield started
    finally:
        for proc in started:
            proc.stop()


def dead_drive_process(processes: Sequence[DriveProcess]) -> str:
    """'' while every drive process runs, else what one that died said last."""
    for proc in processes:
        if proc.proc.poll() is not None:
            return (f"the simulated drives of channel {proc.channel} exited ({proc.proc.returncode}):"
                    f" {' | '.join(proc.lines[-3:]) or 'no output'}")
    return ""


def serve_with_drive_processes(args: argparse.Namespace, served: list[Any], playing: bool) -> int:
    """The servers here, each bus's drives in a process of their own (rovercan.sim_processes)."""
    from virtual_can.service import SimService

    if not args.config:
        raise ConfigError("--drive-processes: give --config (each bus's drive process simulates that bus's drives)")
    if playing or args.status_period:
        raise ConfigError("--drive-processes: fault scenarios and --status-period need the drives in the server's"
                          " process; drop --drive-processes")
    with StopSignal() as stop, ExitStack() as stack:
        running = []
        for s in served:
            sim = stack.enter_context(SimService((), host=args.host, port=s.port, extra_channels=s.channels,
                                                 wire_time=args.wire_time, bitrate=args.bitrate,
                                                 allow_remote=args.allow_remote, drive_models=False))
            with_drives = list(dict.fromkeys(spec.channel for spec in s.specs))
            running += stack.enter_context(drive_processes(args.config, sim.host, sim.port, with_drives))
            print(f"rovercan sim: {len(s.specs)} simulated drive(s) on {', '.join(s.channels)} (each bus's drives in"
                  f" a process of their own), socketcand protocol on {sim.host}:{sim.port}", flush=True)
            for channel in s.channels:
                print(f"  python-can arguments: {sim.python_can_args(channel)}", flush=True)
        heap.settle()
        while not stop.event.wait(0.2):
            if why := dead_drive_process(running):
                print(f"rovercan sim: {why}; stopping", file=sys.stderr, flush=True)
                return 1
        print("rovercan sim: stopped", flush=True)
    return 0
