"""The 6-drive stack run of the performance issue, measured from outside the measured process.

Three processes, as on a bench: the simulator (``rovercan sim --config``: socketcand server,
the drives, the SYNC job the driver hands it), the measured process (``rover_driver``: driver +
ROS node), and this one (the command publisher and an independent listener, a python-can
socketcand client that sees every frame with the server's wire timestamp). Figures:

* the measured process runs a shipped config (``config/rover.yaml``: six wheels on two buses;
  the embedded default: one motor) as a user gets it, only the simulator's port put in.
* cmd_latency: publish on ``<joint>/degree_cmd`` (every joint at 100 Hz) -> the RPDO with that
  target on the wire; the bare path (rclpy publish -> a subscriber process on the
  EventsExecutor the node uses -> one python-can send) is measured the same way.
* tpdo_loss: TPDOs on the wire (the listener, connected before the driver started) minus
  TPDOs the driver applied (its count comes over /diagnostics), after an NMT "enter
  pre-operational" stopped the drives sending.
* cpu_core_fraction, rss_mb: /proc of the measured process (CPU time / wall time; VmHWM).
* sync_jitter_p99_us: SYNC period error at the listener.
* baselines: a state run (one bus, six drives' TPDOs) done the canopen library's way
  (BaseNode402 + PDO callbacks) and by the driver alone; the stack run's whole CAN work done the
  library's way is ``same_work.py`` (the reference of the CPU ratio).
* the bare path's CPU (``bare_path``): rclpy taking the same commands and python-can sending one
  frame each, nothing else; with the canopen library's state run, a reference for the node's CPU
  (not a lower bound: this driver's receive path costs less than the library's).
"""

from __future__ import annotations

import bisect
import collections
import itertools
import json
import math
import multiprocessing
import os
import re
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import can

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from rovercan.launch import LOCAL_DISCOVERY  # noqa: E402

os.environ.setdefault(*LOCAL_DISCOVERY)  # DDS on loopback; the peers it spawns inherit it

#: The bare path's peer (bare_peer.py) sends targets in counts of a 4096-count revolution.
BARE_COUNTS_PER_DEG = 4096 / 360.0
BARE_TICKS = 36_000  # the bare path's distinct values (0.1 deg apart): more than any run's ticks
FLOAT32 = struct.Struct("<f")

from can_config.objects import TPDO_BASES  # noqa: E402
from can_config.realtime import fifo_thread_count  # noqa: E402
from virtual_can import SimDriveSpec, SimService  # noqa: E402

#: The benchmark's own processes' niceness (``harness_ahead``), where SCHED_FIFO is refused.
HARNESS_NICE = -10
#: Their SCHED_FIFO priority: below the measured node's own (``realtime_priority``, 20 by
#: default), so the harness never takes the node's turn, and ahead of any ordinary load.
HARNESS_PRIORITY = 10


def harness_ahead() -> int:
    """This process and every one it starts (the publisher standing in for the rover's other nodes,
    the simulator for the drives and the bus, the listener, the baselines) under SCHED_FIFO at
    HARNESS_PRIORITY and at HARNESS_NICE, ahead of other load on the machine: a busy loop beside
    the run then delays the stack, not the harness. What stands in for the robot's hardware (the
    bus's stamps, the drives) and for its real-time controller (the commands' stamps) is not
    starved on the robot. At niceness -10 alone the harness was still preempted beside a busy
    loop: six drives at 500 Hz gave a command p99 of 1.86-2.26 ms and a set-point loss of 1.7-2.8 %
    (a late publisher's commands went out in pairs), against 0.82-0.88 ms and 0.2-0.4 %, as quiet,
    under SCHED_FIFO at 10. The measured processes run :func:`unboosted`. Where the OS refuses
    (not root), nothing changes. The niceness now."""
    try:
        os.nice(HARNESS_NICE - os.nice(0))
    except PermissionError:
        pass
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(HARNESS_PRIORITY))
    except PermissionError:
        pass
    return os.nice(0)


def harness_priority() -> int:
    """This thread's SCHED_FIFO priority (0: ordinary scheduling), as :func:`harness_ahead` left it."""
    return os.sched_getparam(0).sched_priority if os.sched_getscheduler(0) == os.SCHED_FIFO else 0


#: Run by :func:`unboosted` before the measured command: ordinary scheduling, niceness 0 (lowering
#: a priority needs no privilege), then the command in this process's place
_ORDINARY = ("import os, sys\nos.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))\n"
             "os.nice(-os.nice(0))\nos.execvp(sys.argv[1], sys.argv[1:])")


def unboosted(command: list[str]) -> list[str]:
    """A measured process's command (the driver, the canopen library's same work, the bare path's
    peer), run back at ordinary scheduling and niceness 0 however the harness runs; a measured
    process that runs real-time (the node, the baselines' ``_rt`` runs) sets its own priority. What
    is measured must not be boosted with the harness."""
    if os.nice(0) >= 0 and os.sched_getscheduler(0) == os.SCHED_OTHER:
        return command
    return [sys.executable, "-S", "-c", _ORDINARY, *command]


def _stat_cpu_s(stat: Path) -> float:
    """User + system CPU seconds of a /proc stat file (a process's or one thread's)."""
    fields = stat.read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_cpu_s(pid: int) -> float:
    return _stat_cpu_s(Path(f"/proc/{pid}/stat"))


def python_thread_names(pid: int) -> dict[int, str]:
    """Thread id -> Python thread name of ``pid`` (``py-spy dump --nonblocking``: the process is
    not paused), {} without py-spy: Python 3.11 leaves its threads named after the process. py-spy
    writes the thread holding the interpreter at the dump as ``(active+gil)``. A dump that names no
    thread at all (2 of about 25 stack runs on 12-04: that run's threads came out as one "python"
    row) is tried again, up to three times."""
    spy = str(Path(sys.executable).parent / "py-spy")
    for _ in range(3):
        try:
            dump = subprocess.run([spy, "dump", "--nonblocking", "--pid", str(pid)], capture_output=True, text=True,
                                  timeout=30).stdout
        except (OSError, subprocess.TimeoutExpired):
            return {}
        names = thread_names_in(dump)
        if names:
            return names
    return {}


def thread_names_in(dump: str) -> dict[int, str]:
    """Thread id -> name in the text of ``py-spy dump`` (``Thread 17988 (active+gil): "spinner"``)."""
    return {int(tid): name for tid, name in re.findall(r'^Thread (\d+) \([a-z+ ]+\): "(.*)"$', dump, re.MULTILINE)}


def thread_cpu_s(pid: int, names: dict[int, str] | None = None) -> dict[str, float]:
    """CPU seconds of each thread of ``pid`` so far, summed by thread name (/proc/PID/task; the
    Python name from ``names`` where it has the thread, as ``py:NAME``): where the CPU goes
    outside the interpreter too (DDS's threads, the receive threads, each executor)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name, cpu_s = (task / "comm").read_text().strip(), _stat_cpu_s(task / "stat")
        except OSError:
            continue  # the thread ended meanwhile
        if names and int(task.name) in names:
            name = "py:" + re.sub(r"-\d+$", "-N", names[int(task.name)])  # numbered alike: one row
        out[name] = out.get(name, 0.0) + cpu_s
    return out


def proc_rss_peak_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * (len(ordered) - 1)))]


def _listen(port: int, channel: str, conn: Connection) -> None:
    """The listener process: every frame on ``channel`` with the server's timestamp, until told
    to stop; ``("send", cob, data)`` puts a frame on the bus."""
    bus = can.Bus(interface="socketcand", channel=channel, host="127.0.0.1", port=port, tcp_tune=True)
    frames: list[tuple[float, int, bytes]] = []
    sync_lags: list[float] = []  # a SYNC's arrival here after its bus time (the server's stamp), s
    tpdo_lags: list[float] = []  # the same for the TPDOs: what every frame takes to reach a client
    conn.send("ready")
    try:
        while True:
            if conn.poll():
                request = conn.recv()
                if request == "stop":
                    break
                bus.send(can.Message(arbitration_id=request[1], data=request[2], is_extended_id=False))
            msg = bus.recv(0.05)
            if msg is not None:
                frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))
                if msg.arbitration_id == 0x080:
                    sync_lags.append(time.time() - msg.timestamp)
                elif is_tpdo(msg.arbitration_id):
                    tpdo_lags.append(time.time() - msg.timestamp)
        conn.send((frames, sync_lags, tpdo_lags))
    finally:
        bus.shutdown()


class StartFailed(RuntimeError):
    """The measured stack did not start: a helper process, the listener, the drives' enable, a
    command topic's match, or the first command's switch of mode. A try of its own
    (:func:`two_tries`); any other RuntimeError is a failure of the run."""


class Listener:
    """An independent listener in a process of its own: its parsing of every frame on the bus
    (thousands a second) must not hold the interpreter the benchmark publishes commands from."""

    def __init__(self, port: int, channel: str = "can0") -> None:
        self.channel = channel
        self._conn, child = multiprocessing.Pipe()
        self._proc = multiprocessing.get_context("spawn").Process(target=_listen, args=(port, channel, child),
                                                                  daemon=True)
        self.frames: list[tuple[float, int, bytes]] = []
        self.sync_lags: list[float] = []
        self.tpdo_lags: list[float] = []

    def start(self) -> None:
        self._proc.start()
        if not self._conn.poll(30) or self._conn.recv() != "ready":
            raise StartFailed(f"the listener on {self.channel} did not start")

    def send(self, cob_id: int, data: bytes) -> None:
        self._conn.send(("send", cob_id, data))

    def close(self) -> None:
        """Stop listening; :attr:`frames` then holds every frame seen."""
        if self._proc.is_alive():
            self._conn.send("stop")
            if self._conn.poll(30):
                self.frames, self.sync_lags, self.tpdo_lags = self._conn.recv()
        self._proc.join(10)


SHIPPED = {"rover": REPO / "config" / "rover.yaml", "default": REPO / "can_config" / "data" / "default.yaml"}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


SIM_PIDS: list[int] = []  # the simulator processes started, newest last


@contextmanager
def started(what: str, argv: list[str], ready: str, timeout_s: float = 30.0,
            poll_s: float = 0.05) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """``argv`` (``what``) in a process of its own until the block ends, yielded once its output has said
    ``ready``. Its output goes to a file (a pipe nobody reads could block it) that it writes in
    append mode and this process reads through a handle of its own: one shared file offset (a
    ``TemporaryFile`` for both, sought back to its start to read) had the child's lines written
    over the start of the file while it was read, its ready line among them now and then (the
    "simulator did not start" of a quiet run, exit status None). Yields the process and its output file."""
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "output.txt"
        with log.open("a") as out:
            proc = subprocess.Popen(argv, cwd=REPO, stdout=out, stderr=subprocess.STDOUT, text=True)
        try:
            deadline = time.monotonic() + timeout_s
            while ready not in log.read_text(errors="replace"):
                # read once more after the look at its end: it may have said it and ended in between
                if (time.monotonic() > deadline or proc.poll() is not None) and \
                        ready not in log.read_text(errors="replace"):
                    raise StartFailed(f"{what} did not start (no {ready!r} within {timeout_s:g} s, exit status"
                                      f" {proc.poll()}): {log.read_text(errors='replace')}")
                time.sleep(poll_s)
            yield proc, log
        finally:
            proc.terminate()
            proc.wait(20)


@contextmanager
def simulator(*args: str) -> Iterator[int]:
    """``rovercan sim ARGS`` in a process of its own on a free port, as a user runs it; yields
    the port once it serves (its pid goes to SIM_PIDS)."""
    port = free_port()
    with started("the simulator", [sys.executable, "-m", "rovercan", "sim", *args, "--port", str(port)],
                 "simulated drive") as (proc, _):
        SIM_PIDS.append(proc.pid)
        yield port


def on_port(config_path: Path, port: int, directory: str) -> Path:
    """The shipped config as a user gets it, only the simulator's port put in (a copy in ``directory``)."""
    config = Path(directory) / config_path.name
    config.write_text(config_path.read_text().replace("port: 29536", f"port: {port}"))
    return config


def tpdos_on_wire(listeners: Iterable[Listener], t_stop: float) -> int:
    """The TPDOs the listeners saw up to just after the drives were told to stop sending at ``t_stop``."""
    return sum(1 for listener in listeners for t, cob, _ in listener.frames if is_tpdo(cob) and t < t_stop + 0.5)


def is_tpdo(cob: int) -> bool:
    return cob & 0x7F != 0 and cob & 0x780 in TPDO_BASES


def count_by_bus(sent: dict[tuple[str, int, int], list[float]]) -> collections.Counter[str]:
    """The commands published, by bus (before matching takes them)."""
    out: collections.Counter[str] = collections.Counter()
    for (ch, _, _), times in sent.items():
        out[ch] += len(times)
    return out


def catch_up_by_bus(sent: dict[tuple[str, int, int], list[float]]) -> dict[str, float]:
    """By bus: the fraction of commands the harness published less than half its drive's period
    (the median gap) after that drive's previous one: published late, then caught up. Of such a
    pair a keep-last-1 subscription may keep only the newest: set-point loss of the harness's
    making, not the driver's."""
    times: dict[tuple[str, int], list[float]] = {}
    for (ch, node_id, _), stamps in sent.items():
        times.setdefault((ch, node_id), []).extend(stamps)
    short: collections.Counter[str] = collections.Counter()
    total: collections.Counter[str] = collections.Counter()
    for (ch, _), stamps in times.items():
        gaps = [b - a for a, b in itertools.pairwise(sorted(stamps))]
        if gaps:
            half = statistics.median(gaps) / 2
            short[ch] += sum(g < half for g in gaps)
            total[ch] += len(gaps)
    return {ch: round(short[ch] / n, 5) for ch, n in sorted(total.items()) if n}


def match_latencies(listeners: dict[str, Any], sent: dict[tuple[str, int, int], list[float]],
                    drives: list[Any]) -> tuple[list[float], dict[int, list[float]], list[float], collections.Counter[str]]:
    """Each position RPDO on the wire matched to the degree command that asked for it: latencies
    (ms), by the command's place in each burst, when each was published, and how many matched, by bus."""
    latencies = []
    by_order: dict[int, list[float]] = {}  # latency by the command's place in each burst of publishes
    published_at: list[float] = []  # of each latency
    order = {(ch, d.node_id): i for i, (d, ch, _, _) in enumerate(drives)}
    matched: collections.Counter[str] = collections.Counter()  # by bus
    per_rev = {(ch, d.node_id): rev for d, ch, _, rev in drives}
    for ch, listener in listeners.items():
        for t, cob, data in listener.frames:
            node_id = cob - 0x300
            # the target RPDO (controlword + target) with Enable Operation: a profile-position
            # set-point (bit 4 rising) or a streamed one (position_mode: cyclic, no handshake)
            if (ch, node_id) in per_rev and len(data) >= 6 and data[0] & 0x0F == 0x0F:
                # continuous joints go the short way: the target on the wire is multi-turn, so match
                # it modulo one revolution of the joint
                times = sent.get((ch, node_id, int.from_bytes(data[2:6], "little", signed=True) % per_rev[(ch, node_id)]), [])
                while times and times[0] < t - 1.0:
                    times.pop(0)  # a command superseded before it was sent (latest wins)
                if times and times[0] <= t:
                    published = times.pop(0)
                    latencies.append((t - published) * 1000)
                    by_order.setdefault(order[(ch, node_id)], []).append(latencies[-1])
                    published_at.append(published)
                    matched[ch] += 1
    return latencies, by_order, published_at, matched


def profiler(pid: int, seconds: float) -> subprocess.Popen[bytes] | None:
    """With $ROVERCAN_PROFILE=FILE.svg (a flame graph) or FILE.txt (collapsed stacks): py-spy
    samples the measured process 250 times a second for the measured window, only the thread that
    holds the interpreter (--gil: where its CPU goes, not where threads wait), without pausing it
    (issue 43's profile). Without: None."""
    out = os.environ.get("ROVERCAN_PROFILE")
    if not out:
        return None
    fmt = "raw" if out.endswith(".txt") else "flamegraph"  # .txt: collapsed stacks, to rank the entries
    # ROVERCAN_PROFILE_NATIVE=1: every running thread with its native (C/C++) frames instead:
    # where the CPU goes that the interpreter's holder does not show
    # (py-spy then pauses the process for each sample: figures of such a run are not comparable)
    native = os.environ.get("ROVERCAN_PROFILE_NATIVE") == "1"
    scope = ["--native", "--threads"] if native else ["--gil", "--nonblocking", "--threads"]  # by thread
    return subprocess.Popen([str(Path(sys.executable).parent / "py-spy"), "record", "--pid", str(pid), "--rate", "250",
                             *scope, "--duration", str(max(1, int(seconds))), "--format", fmt,
                             "--output", out],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def command_rates(sync_periods_s: list[float], command_hz: float) -> tuple[float, list[int]]:
    """The command loop's rate and, per drive, every how many of its ticks the drive is commanded:
    every drive at ``command_hz``, or (``command_hz`` 0) each at its bus's SYNC rate
    (``sync_periods_s``, one a drive), the loop at the fastest."""
    if command_hz > 0:
        return command_hz, [1] * len(sync_periods_s)
    fastest = min(sync_periods_s)
    return 1.0 / fastest, [max(1, round(p / fastest)) for p in sync_periods_s]


def due(tick: int, every: list[int]) -> list[int]:
    """The drives (indexes) commanded at the command loop's ``tick`` (:func:`command_rates`)."""
    return [i for i, n in enumerate(every) if tick % n == 0]


#: How late the command loop may fall and still catch up in a burst: beyond it the ticks missed are
#: skipped. A burst is published microseconds apart, the driver's keep-last-1 subscription takes
#: its newest, and a burst of 28 ticks (56 ms at 500 Hz) moved the ramp beyond a streamed joint's
#: step (2.88 deg): refused as a jump, and so was the rest of the ramp (the run in issue 72).
CATCH_UP_MAX_PERIODS = 10


def next_tick(next_t: float, period: float, now: float) -> float:
    """When the command loop's next tick is due: one period on, or, when the loop is more than
    CATCH_UP_MAX_PERIODS late, now (the ticks missed skipped: fewer commands, no jump in a ramp)."""
    next_t += period
    return now if now - next_t > CATCH_UP_MAX_PERIODS * period else next_t


_FLOAT32 = struct.Struct("<f")


class Ramps:
    """Each joint's ramp: the team's demo ramp, +0.1 deg a command from 0.15, modulo 360
    (continuous on a continuous joint; a streamed joint, position_mode: cyclic, refuses a jump:
    modulo 300 jumped 60 deg). A joint whose commands the driver refused (its /diagnostics
    ``refused_commands``) has its ramp planned again from where it stands (``angle_deg``), as a
    trajectory client starts its next goal from the joint's state: a streamed joint judges each
    step from the set-point it last sent, so after a stall of 28 commands (56 ms at 500 Hz: late
    data, a starved process) the ramp had gone out of its reach and every later command was
    refused, and the run measured refusals (94 % of the set-points beside another session's
    real-time load). The refused commands still count as lost (``setpoint_loss_fraction``)."""

    def __init__(self, names: list[str], seen: int) -> None:
        self._index = {name: i for i, name in enumerate(names)}
        self._start = [(0.05, 0)] * len(names)  # (angle, command count) each ramp starts from
        self._seen = seen  # /diagnostics arrays looked at
        self.replanned = 0

    def angle(self, i: int, count: int) -> float:
        """Joint ``i``'s ``count``-th command, as its Float32 carries it."""
        base, at = self._start[i]
        return float(_FLOAT32.unpack(_FLOAT32.pack((base + (count - at) * 0.1) % 360.0))[0])

    def replan(self, diags: list[Any], tick: int, every: list[int]) -> None:
        """The joints the newest /diagnostics arrays say refused commands start again from where they stand."""
        for array in diags[self._seen:]:
            for st in array.status:
                i = self._index.get(st.name)
                values = {kv.key: kv.value for kv in st.values}
                if i is not None and values.get("refused_commands", "0") != "0" and "angle_deg" in values:
                    self._start[i] = (float(values["angle_deg"]), tick // every[i])
                    self.replanned += 1
        self._seen = len(diags)


#: the modes of operation a first position command switches a drive to: a stream (CSP, IP), a profile move
STREAMED_MODES, PROFILE_MODE = frozenset({"8", "7"}), frozenset({"1"})


def two_tries(name: str, key: str, invalid: dict[str, str], prefix: str,
              run: Callable[[], tuple[dict[str, Any], str | None]]) -> list[dict[str, Any]]:
    """A stack run (``run``: its figures and why the emulator did not carry it, None when it did),
    once more when it was not carried or did not start (:class:`StartFailed`: the machine can
    starve a start as well as a window); the runs made, the one to report last. Each run's
    ``{prefix}run_try`` says which try it was, and the last's ``{prefix}start_failures`` each
    start that failed before it: a start that fails now and then is a finding, not hidden by the
    try after it. Not carried twice, the reason goes into ``invalid`` under ``key`` and the
    figures resting on it get no verdict; not started twice, the second start's error is raised."""
    runs: list[dict[str, Any]] = []
    failures: list[str] = []
    for attempt in (1, 2):
        try:
            out, reason = run()
        except StartFailed as err:
            print(f"{name} did not start (run {attempt} of 2): {err}", file=sys.stderr, flush=True)
            failures.append(f"run {attempt}: {err}")
            if attempt == 2 and not runs:
                raise
            continue
        out[f"{prefix}run_try"] = attempt
        runs.append(out)
        if reason is None:
            invalid.pop(key, None)
            break
        invalid[key] = reason
        print(f"{name} invalid (run {attempt} of 2): {reason}", file=sys.stderr, flush=True)
    runs[-1][f"{prefix}start_failures"] = failures
    return runs


def modes_off(diags: list[Any], wanted: dict[str, frozenset[str]]) -> dict[str, str] | None:
    """Each named drive whose mode of operation, as the newest /diagnostics array that reports
    modes says, is not one of those wanted, with that mode ("none": not reported); None before any
    array reports a mode."""
    for array in reversed(diags):
        modes = {st.name: kv.value for st in array.status for kv in st.values if kv.key == "mode"}
        if modes:
            return {name: modes.get(name, "none") for name, allowed in wanted.items() if modes.get(name) not in allowed}
    return None


#: how long the start waits for the first command's switches, and how often it sends that command again
FIRST_SWITCH_WAIT_S, FIRST_COMMAND_AGAIN_S = 30.0, 2.0


def start_streams(first: Any, shipped: Any, diags: list[Any], executor: Any, proc: subprocess.Popen[bytes]) -> None:
    """Each joint's first command (the ramp's start) before the measured window: a stream's first
    set-point switches its drive's mode by SDO (on a worker of its joint since
    nodes/joints/handoff.py; it held every other joint's commands before: docs/performance.md);
    the window measures the streams running, not their start. It waits for each drive's switch to
    be done, not a fixed half second: on a busy machine six switches took longer, the handoff kept
    each joint's newest command, and the first set-point after the switch jumped (37 deg at
    500 Hz) and was refused, and so was the rest of its ramp (a streamed joint judges each step
    from the last one sent). The window's first command is then one step from the start.

    The first command goes out again every FIRST_COMMAND_AGAIN_S until the switch is seen: the
    publisher seeing the subscription matched does not mean the subscriber has matched the
    publisher (DDS discovery is two one-way matches), and a volatile message sent between the two
    is lost (a quick run once waited the whole 30 s for one). The same set-point again is no
    step for the driver to judge."""
    first()  # every joint's first command, 0.05 deg
    wanted = {f"rovercan: {d.name}": STREAMED_MODES if d.position_mode == "cyclic" else PROFILE_MODE
              for d in shipped.drives}
    deadline = time.monotonic() + FIRST_SWITCH_WAIT_S
    again = time.monotonic() + FIRST_COMMAND_AGAIN_S
    while (off := modes_off(diags, wanted)) != {}:
        if proc.poll() is not None:
            raise StartFailed(f"the measured process ended (exit status {proc.returncode}) before its drives switched"
                              " to their position mode for the first command")
        if time.monotonic() > deadline:
            refused, reason = refusals(diags)
            said = "no /diagnostics array reported a mode" if off is None else ", ".join(
                f"{name} in {mode}" for name, mode in sorted(off.items()))
            raise StartFailed(f"the drives did not switch to their position mode for the first command ({said}; "
                              f"{refused} commands refused{': ' + reason if reason else ''})")
        if time.monotonic() > again:
            first()
            again = time.monotonic() + FIRST_COMMAND_AGAIN_S
        executor.spin_once(timeout_sec=0.1)
    time.sleep(0.2)  # the worker's set-point after the switch (the switch's last step) goes out


def _stamp_s(array: Any) -> float:
    return float(array.header.stamp.sec + array.header.stamp.nanosec * 1e-9)


def _tpdos_applied(diags: list[Any]) -> list[int]:
    """The driver's per-drive ``tpdos_applied`` from the newest /diagnostics array that has them:
    the drive system publishes its own array on the same topic, without them (taking the newest
    array alone read the count as 0 and the loss as every TPDO, in about half the rover's runs)."""
    for array in reversed(diags):
        counts = [int(kv.value) for st in array.status for kv in st.values if kv.key == "tpdos_applied"]
        if counts:
            return counts
    return []


def refusals(diags: list[Any]) -> tuple[int, str]:
    """The commands the driver refused, summed over the /diagnostics arrays (each drive's
    ``refused_commands`` counts those since its previous array), and the newest reason: a run
    whose set-points went missing says whether the driver refused them, and why."""
    total, last = 0, ""
    for array in diags:
        for st in array.status:
            values = {kv.key: kv.value for kv in st.values}
            if values.get("refused_commands", "0") != "0":
                total += int(values["refused_commands"])
                last = values.get("last_refusal", "") or last
    return total, last


def every_topic_matched(pubs: list[Any], deadline: float, proc: subprocess.Popen[bytes]) -> None:
    """Wait until the measured process subscribes to every command topic (the last drive's topic
    alone had been waited for: another's first commands could be lost before its match)."""
    while any(pub.get_subscription_count() == 0 for pub in pubs):
        if time.monotonic() > deadline or proc.poll() is not None:
            raise StartFailed("the measured process did not subscribe to every command topic")
        time.sleep(0.05)


class Commands:
    """A stack run's command publishers: a Float32 ``degree_cmd`` a joint, or (``joint_commands``)
    one ``/joint_commands`` JointState a tick naming every joint due, its positions in radians, as
    ros2_control's topic-based hardware interface sends them (the driver's /joint_commands)."""

    def __init__(self, node: Any, shipped: Any, joint_commands: bool) -> None:
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32

        from motor_driver.protocol.units import DEG_PER_RAD
        from nodes.process.qos import COMMAND_QOS

        self._float32, self._joint_state, self._per_rad = Float32, JointState, DEG_PER_RAD
        self.joint_commands = joint_commands
        self.names = [d.name for d in shipped.drives]
        self.pubs = ([node.create_publisher(JointState, "/joint_commands", COMMAND_QOS)] if joint_commands else
                     [node.create_publisher(Float32, f"{d.ros_prefix}/degree_cmd", COMMAND_QOS) for d in shipped.drives])

    def as_driver_reads(self, angle: float) -> float:
        """The degrees the driver commands for ``angle`` (a JointState's radians times its DEG_PER_RAD)."""
        return angle / self._per_rad * self._per_rad if self.joint_commands else angle

    def publish(self, indexes: list[int], angles: list[float],
                stamp: Callable[[int, float], None] = lambda i, angle: None) -> None:
        """Joints ``indexes`` commanded to ``angles`` (degrees); ``stamp(i, angle)`` right before the
        message that carries joint ``i``'s command is published (a latency runs from there: stamped
        before the other joints' messages of its burst, it would carry their publishing too)."""
        if self.joint_commands:
            for i, angle in zip(indexes, angles, strict=True):
                stamp(i, angle)
            self.pubs[0].publish(self._joint_state(name=[self.names[i] for i in indexes],
                                                   position=[a / self._per_rad for a in angles]))
            return
        for i, angle in zip(indexes, angles, strict=True):
            stamp(i, angle)
            self.pubs[i].publish(self._float32(data=angle))


def node_command(accounts: str | None) -> list[str]:
    """The measured node as deployed, or (``accounts``: $ROVERCAN_CALLBACK_CPU) by callback_cpu.py,
    each callback's CPU counted into that file."""
    if accounts:
        return [sys.executable, str(REPO / "benchmarks" / "callback_cpu.py"), accounts]
    return [sys.executable, "-m", "nodes.rover_driver"]


def snapshot_accounts(proc: subprocess.Popen[bytes], accounts: str | None) -> None:
    """A snapshot of a node run by callback_cpu.py (its SIGUSR1); nothing for a node run as deployed."""
    if accounts:
        proc.send_signal(signal.SIGUSR1)


def callback_accounts(accounts: str | None) -> dict[str, Any]:
    """The window's callback accounts (callback_cpu.window) from the file the node wrote; none without."""
    if not accounts:
        return {}
    sys.path.insert(0, str(REPO / "benchmarks"))
    import callback_cpu
    return callback_cpu.window(json.loads(Path(accounts).read_text()))


def run_stack(config_path: Path, seconds: float, command_hz: float, sim_args: tuple[str, ...] = (),
              joint_commands: bool = False) -> dict[str, Any]:
    """The measured process runs a shipped config as a user gets it; only the simulator's port
    is put into it. Every drive gets a ``degree_cmd`` at ``command_hz`` (0.1 % slow: below), or
    with ``command_hz`` 0 at its bus's SYNC rate (:func:`command_rates`).
    ``sim_args``: more arguments of ``rovercan sim`` (``--drive-processes``).
    ``joint_commands``: the same set-points as one ``/joint_commands`` JointState a tick for every
    joint due (radians), as ros2_control's topic-based hardware interface sends its joints'
    commands, instead of a Float32 a joint: the same CAN work for a sixth of the ROS messages."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from can_config import load_config
    from motor_driver.protocol.units import Scale
    from nodes.process.qos import DIAGNOSTICS_QOS

    shipped = load_config(config_path)
    channels = {b.name: b.channel for b in shipped.buses}
    sync_s = {b.name: b.sync_period_s for b in shipped.buses}
    with simulator("--config", str(config_path), *sim_args) as port, tempfile.TemporaryDirectory() as tmp:
        config = on_port(config_path, port, tmp)
        # the listener first: it must see every TPDO the drives send to count the loss
        listeners = {ch: Listener(port, ch) for ch in sorted(set(channels.values()))}
        for listener in listeners.values():
            listener.start()
        accounts = os.environ.get("ROVERCAN_CALLBACK_CPU")  # FILE.json: each callback's CPU counted
        proc = subprocess.Popen(unboosted([*node_command(accounts), "--ros-args", "-p", f"config:={config}",
                                 "-p", "arm:=true", "-p", "diagnostics_rate_hz:=2.0"]),
                                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_publisher", context=context)
        diags: list[Any] = []
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, DIAGNOSTICS_QOS)
        # the target each degree command puts on the wire, as the driver scales it (a mirrored
        # wheel's `invert`, `offset_deg`): matching on the unsigned counts would miss those wheels
        scales = [Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
                  for d in shipped.drives]
        drives = [(d, channels[d.bus], scale, round(d.counts_per_deg * 360))
                  for d, scale in zip(shipped.drives, scales, strict=True)]
        commands = Commands(node, shipped, joint_commands)
        pubs = commands.pubs
        from rclpy.executors import SingleThreadedExecutor
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        names = {f"rovercan: {d.name}" for d in shipped.drives}

        def all_enabled() -> bool:
            """Every drive in Operation Enabled, as the newest /diagnostics says."""
            status = diags[-1].status if diags else []
            states = {st.name: kv.value for st in status for kv in st.values if kv.key == "cia402_state"}
            return all(states.get(n) == "OPERATION_ENABLED" for n in names)

        try:
            deadline = time.monotonic() + 30
            while not all_enabled():  # every drive enabled, as the driver reports it
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise StartFailed("the measured process did not enable its drives")
                executor.spin_once(timeout_sec=0.1)
            every_topic_matched(pubs, deadline, proc)
            start_streams(lambda: commands.publish(list(range(len(drives))), [0.05] * len(drives)), shipped, diags,
                          executor, proc)
            sent: dict[tuple[str, int, int], list[float]] = {}
            names = python_thread_names(proc.pid)
            cpu0, wall0, threads0 = proc_cpu_s(proc.pid), time.monotonic(), thread_cpu_s(proc.pid, names)
            spy = profiler(proc.pid, seconds)
            snapshot_accounts(proc, accounts)  # the window's first
            window0 = time.time()
            # the command clock runs 0.1 % slow: over each 10 s the bursts pass once through every
            # phase of the SYNC period. At exactly the SYNC's rate one run would see one phase only
            # (on one clock the two stay locked), and the p50 would be 0.9 or 1.5 ms by luck
            loop_hz, every = command_rates([sync_s[d.bus] for d in shipped.drives], command_hz)
            period = 1.001 / loop_hz
            next_t = time.monotonic()
            k = 0
            ramps = Ramps([f"rovercan: {d.name}" for d in shipped.drives], len(diags))

            def stamp(i: int, angle: float) -> None:  # the set-point joint i's command puts on the wire, when
                d, ch, scale, per_rev = drives[i]
                sent.setdefault((ch, d.node_id, scale.deg_to_counts(commands.as_driver_reads(angle)) % per_rev),
                                []).append(time.time())
            while time.monotonic() - wall0 < seconds:
                k += 1
                indexes = due(k, every)
                commands.publish(indexes, [ramps.angle(i, k // every[i]) for i in indexes], stamp)
                executor.spin_once(timeout_sec=0)
                ramps.replan(diags, k, every)
                next_t = next_tick(next_t, period, time.monotonic())
                time.sleep(max(0.0, next_t - time.monotonic()))
            snapshot_accounts(proc, accounts)  # and its last
            cpu = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
            threads = {name: (t - threads0.get(name, 0.0)) / (time.monotonic() - wall0)
                       for name, t in thread_cpu_s(proc.pid, names).items()}
            if spy is not None:
                spy.wait(60)
            sync_timer_realtime = fifo_thread_count(SIM_PIDS[-1], children=True) > 0
            window1 = time.time()
            rss = proc_rss_peak_mb(proc.pid)
            first = listeners[min(listeners)]
            t_stop = time.time()
            for listener in listeners.values():  # the drives stop sending: loss can be counted exactly
                listener.send(0x000, bytes([0x80, 0]))
            # the driver's count from a /diagnostics published a second after the stop (one
            # published at once can miss the last TPDOs still on their way), taken before the
            # driver takes the drives back (FOREIGN_RELEASE_S after the other master's NMT)
            end = time.monotonic() + 1.0
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
            refused, last_refusal = refusals([a for a in diags if _stamp_s(a) >= window0])
            diags.clear()
            end = time.monotonic() + 5
            while not _tpdos_applied(diags) and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
            tpdo_applied = sum(_tpdos_applied(diags))
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.shutdown(context=context)
            proc.terminate()
            proc.wait(20)
            for listener in listeners.values():
                listener.close()
    by_callback = callback_accounts(accounts)
    tpdo_sent = tpdos_on_wire(listeners.values(), t_stop)
    published_by_bus, caught_up = count_by_bus(sent), catch_up_by_bus(sent)
    n_published = sum(published_by_bus.values())
    latencies, by_order, published_at, matched_by_bus = match_latencies(listeners, sent, drives)
    matched = sum(matched_by_bus.values())
    unmatched = sum(len(v) for v in sent.values())
    syncs = [t for t, cob, _ in first.frames if cob == 0x080]
    sync_s = shipped.buses[0].sync_period_s
    jitter = [abs((b - a) - sync_s) * 1e6 for a, b in itertools.pairwise(syncs)]
    # latency by when the command was published within the SYNC period (tenths of it after a SYNC)
    by_phase: dict[int, list[float]] = {}
    for published, latency in zip(published_at, latencies, strict=True):
        i = bisect.bisect_right(syncs, published) - 1
        if 0 <= i < len(syncs) - 1:
            by_phase.setdefault(min(9, int(10 * (published - syncs[i]) / sync_s)), []).append(latency)
    # the driver's heartbeat (node 127) as the drives see it: its longest gap is what their
    # consumer time (150 ms by default) must cover while the process is busy
    beats = [t for t, cob, _ in first.frames if cob == 0x77F and window0 <= t <= window1]
    # a drive that faulted or stopped itself in the window (its EMCY, not an error reset): the
    # figures then measure a run that stopped carrying its load
    emcy = sorted({f"{ch} node {cob - 0x80} EMCY 0x{int.from_bytes(d[:2], 'little'):04X}"
                   for ch, listener in listeners.items() for t, cob, d in listener.frames
                   if 0x081 <= cob <= 0x0FF and window0 <= t <= window1 and d[:2] != b"\0\0"})
    gaps = [(b - a) * 1000 for a, b in itertools.pairwise(beats)]
    return {"config": str(config_path.relative_to(REPO)), "drives": len(drives),
            "host_heartbeat_gap_p99_ms": round(pct(gaps, 0.99), 1) if gaps else None,
            "host_heartbeat_gap_max_ms": round(max(gaps), 1) if gaps else None,
            "cmd_latency_p50_ms": round(statistics.median(latencies), 3) if latencies else None,
            "cmd_latency_p99_ms": round(pct(latencies, 0.99), 3) if latencies else None,
            "cmd_latency_p50_ms_by_publish_order": [round(statistics.median(by_order[i]), 3) for i in sorted(by_order)],
            "cmd_latency_p50_ms_by_sync_phase": [round(statistics.median(by_phase[i]), 3) if i in by_phase else None
                                                 for i in range(10)],
            # set-point loss: of the commands published, those that never went on the wire as a
            # set-point (a profile-position set-point superseded before it was sent, or a command
            # the ROS layer dropped; a CSP drive takes one set-point a SYNC, the newest, whatever
            # the count). Not matched + unmatched: matching drops a command's time once a later
            # command of the same value (the ramp comes round) has gone out
            "commands_published": n_published, "commands_matched": matched, "commands_superseded": unmatched,
            "setpoint_loss_fraction": round((n_published - matched) / n_published, 5) if n_published else None,
            "setpoint_loss_by_bus": {ch: round((n - matched_by_bus[ch]) / n, 5) for ch, n in sorted(published_by_bus.items()) if n},
            "commands_refused": refused, "last_refusal": last_refusal, "ramps_replanned": ramps.replanned,
            "harness_catch_up_by_bus": caught_up,
            "tpdo_sent": tpdo_sent, "tpdo_applied": tpdo_applied, "tpdo_loss": tpdo_sent - tpdo_applied,
            "cpu_core_fraction": round(cpu, 3), "rss_mb": round(rss, 1),
            "cpu_by_thread": {name: round(f, 3) for name, f in sorted(threads.items(), key=lambda kv: -kv[1]) if f >= 0.002},
            "sync_jitter_p99_us": round(pct(jitter, 0.99), 1) if jitter else None,
            # how late the listener (a client like the drives) heard the SYNC after its bus time
            "sync_delivery_p99_us": round(pct(first.sync_lags, 0.99) * 1e6, 1) if first.sync_lags else None,
            "tpdo_delivery_p99_us": round(pct(first.tpdo_lags, 0.99) * 1e6, 1) if first.tpdo_lags else None,
            "sync_timer_realtime": sync_timer_realtime, "emcy_in_window": emcy, "drive_stops": len(emcy),
            **by_callback}


def bare_path(seconds: float, topics: int = 1, priority: int = 0, hz: float = 100.0) -> dict[str, Any]:
    """rclpy publish -> subscription callback -> one python-can send, to the listener, for
    ``topics`` topics published in a burst ``hz`` times a second (every 10 ms by default), as the
    stack run publishes one command per drive.

    The subscriber is its own process (``bare_peer.py``), as the driver node is: publisher and
    subscriber in one process would take DDS's intra-process shortcut the node never gets.
    ``priority`` > 0: its threads under SCHED_FIFO, as the node's (``realtime_priority``); the
    keys then say ``bare_rt``.
    """
    import rclpy
    from std_msgs.msg import Float32

    from nodes.process.qos import COMMAND_QOS

    with simulator("--drives", "1") as port:  # the same server process as the stack's (its drive stays pre-op)
        listener = Listener(port)
        listener.start()
        peer = subprocess.Popen(unboosted([sys.executable, str(Path(__file__).resolve().parent / "bare_peer.py"), "127.0.0.1",
                                 str(port), str(topics), str(priority)]),
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bare", context=context)
        pubs = [node.create_publisher(Float32, f"bare_cmd_{i}", COMMAND_QOS) for i in range(topics)]
        try:
            assert peer.stdout is not None and peer.stdout.readline().strip() == "ready"
            deadline = time.monotonic() + 10
            while any(pub.get_subscription_count() == 0 for pub in pubs) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            sent: dict[tuple[int, int], float] = {}
            start = time.monotonic()
            cpu0 = proc_cpu_s(peer.pid)
            next_t = start
            k = published = 0
            while time.monotonic() - start < seconds:
                k += 1
                # a value a tick, never repeated within a run (60 s at 500 Hz: 30,000 ticks), as the
                # peer reads it: a Float32's (a send's latency is matched to its frame by the value)
                angle = FLOAT32.unpack(FLOAT32.pack((k % BARE_TICKS) * 0.1 + 0.05))[0]
                for i, pub in enumerate(pubs):
                    sent[(0x301 + i, round(angle * BARE_COUNTS_PER_DEG))] = time.time()
                    pub.publish(Float32(data=angle))
                published += len(pubs)
                next_t += 1.0 / hz
                time.sleep(max(0.0, next_t - time.monotonic()))
            cpu = (proc_cpu_s(peer.pid) - cpu0) / (time.monotonic() - start)
            time.sleep(0.3)
        finally:
            peer.terminate()
            peer.wait(10)
            node.destroy_node()
            rclpy.shutdown(context=context)
            listener.close()
    latencies = [(t - sent.pop((cob, int.from_bytes(d[2:6], "little", signed=True)))) * 1000
                 for t, cob, d in listener.frames if (cob, int.from_bytes(d[2:6], "little", signed=True)) in sent]
    name = "bare_rt" if priority else "bare"
    key = f"{name}_latency_p50_ms" if topics == 1 else f"{name}_latency_{topics}_topics_p50_ms"
    # what rclpy itself costs to take the commands and python-can to send them (a starved run, its
    # commands lost on the way, costs less: the share that went on the wire says so)
    of = name if topics == 1 else f"{name}_{topics}_topics"
    # the share floored, never rounded up over a bound (run.py's 95 %)
    return {key: round(statistics.median(latencies), 3) if latencies else None, f"{of}_cpu_core_fraction": round(cpu, 3),
            f"{of}_delivered": math.floor(1000 * len(latencies) / max(published, 1)) / 1000}


def state_run(script: str, prefix: str, n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    """A driver-level state run (no ROS) in its own process: TPDO loss and CPU."""
    with SimService([SimDriveSpec(i) for i in range(1, n_drives + 1)], port=0) as sim:
        proc = subprocess.Popen(unboosted([sys.executable, str(Path(__file__).resolve().parent / script),
                                 sim.host, str(sim.port), str(n_drives), str(sync_ms), str(seconds)]),
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=REPO)
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("measuring")
        cpu0, wall0 = proc_cpu_s(proc.pid), time.monotonic()
        time.sleep(seconds)
        cpu = (proc_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
        sims = [sim.simulator_for(i) for i in range(1, n_drives + 1)]
        for i, s in enumerate(sims, start=1):
            s.call(lambda s=s, i=i: setattr(s.drive(i), "nmt", 0x7F))
        time.sleep(0.3)
        sent = sum(s.call(lambda s=s, i=i: s.drive(i).counters["tpdo"]) for i, s in enumerate(sims, start=1))
        proc.stdin = None
        out = json.loads(proc.stdout.readline())
        proc.wait(30)
    return {f"{prefix}_tpdo_loss": sent - out["received"], f"{prefix}_tpdo_sent": sent,
            f"{prefix}_cpu_core_fraction": round(cpu, 3)}


def baseline_canopen(n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    return state_run("baseline_canopen.py", "baseline_canopen", n_drives, sync_ms, seconds)


def driver_only(n_drives: int, sync_ms: float, seconds: float) -> dict[str, Any]:
    return state_run("driver_only.py", "driver_only", n_drives, sync_ms, seconds)


if __name__ == "__main__":
    print(json.dumps({**run_stack(SHIPPED["rover"], 10.0, 100.0), **bare_path(5.0), **bare_path(5.0, 6)}, indent=2))
