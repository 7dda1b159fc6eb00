"""The shipped rover on a crowded machine, watched from outside (issue 64's check, runnable by anyone).

``rovercan sim --config config/rover.yaml`` (on a free port, as ``stack_run.simulator`` starts it)
and ``rovercan launch rover_launch.xml`` with the shipped config pointed at it; the rover is armed
(``/arm``) and driven forward by ``/cmd_vel`` at 20 Hz for ``--seconds`` (180) beside load started
before either: two busy loops per core at ordinary priority, and one real-time burst per core
(SCHED_FIFO 10, below the driver's 20; pinned to its core, busy the first 250 ms of each wall-clock
second, so every core's burst falls in the same quarter second, and asleep the rest). The bursts
need root (CAP_SYS_NICE); without it they are left out, and the run says so.

An independent listener on every bus of the config (a python-can socketcand client of the
simulator's server, ``stack_run.Listener``, connected before the rover starts) counts the drives'
EMCY frames (COB-ID 0x80 + node) by node and code, EMCY 0x8130 (host heartbeat lost: the drive
stopped itself) among them, from its start to the end of the drive; each wheel's travel is the sum
of its position's changes in its position TPDO (TPDO2, 0x280 + node: position, velocity), and
its fraction of what /cmd_vel asked over the drive. Prints one JSON line of the figures and a
verdict line: PASS when no EMCY 0x8130 was seen and every wheel turned at least half as far as
asked (exit 0), else FAIL with what was seen (exit 1). Everything it starts (load, launch,
simulator, listeners) is ended when it ends, on Ctrl-C (exit 130) and on an error too.

    python benchmarks/crowded_rover.py [--seconds 180] [--busy-per-core 2] [--no-bursts]
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
# a DDS domain of the run's own unless one is set: another rover on this machine in the default
# domain would share /cmd_vel and /arm
os.environ.setdefault("ROS_DOMAIN_ID", str(70 + os.getpid() % 30))

from stack_run import SHIPPED, SIM_PIDS, Listener, on_port, simulator  # noqa: E402  (sets DDS on loopback)

from can_config import RoverConfig, load_config  # noqa: E402
from can_config.realtime import DRIVER_PRIORITY, SIM_PRIORITY, fifo_thread_count  # noqa: E402

# the listeners' socketcand client warns of every frame split across two reads, which a busy
# machine makes common; this module is imported in their processes too (multiprocessing's spawn)
logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml"
#: The bursts' SCHED_FIFO priority: real-time work of lesser weight than the driver's.
BURST_PRIORITY = 10
assert BURST_PRIORITY < DRIVER_PRIORITY
BURST_BUSY_S = 0.25
HOST_LOSS_CODE = 0x8130
POSITION_TPDO = 0x280  # + node id: TPDO2 of motor_driver/protocol/pdo.py, position (int32) then velocity
HOST_HEARTBEAT_ID = 0x700 + 127
CMD_VEL_HZ = 20.0
#: Hang bounds, generous: under the bursts a process start takes seconds.
ARM_HANG_S = 120.0
STOP_HANG_S = 60.0
#: The rover drove: every wheel turned at least this fraction of what /cmd_vel asked (a stale
#: /cmd_vel, 500 ms unpublished, stops the wheels; before the simulator judged heartbeats by their
#: bus stamps, 20 s under this load turned them 1.6 % of it, between 197 EMCY 0x8130)
MOVED_FRACTION = 0.5

# The load, each in a process of its own that dies with this one (PR_SET_PDEATHSIG) however it ends.
_DIE_WITH_PARENT = "import ctypes, signal\nctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"
_BUSY = _DIE_WITH_PARENT + "while True: pass"
_BURST = _DIE_WITH_PARENT + """import os, sys, time
os.sched_setaffinity(0, {int(sys.argv[1])})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(sys.argv[2])))
busy_s = float(sys.argv[3])
while True:
    time.sleep(1.0 - time.time() % 1.0)  # the next whole second: every core's burst at once
    end = time.monotonic() + busy_s
    while time.monotonic() < end:
        pass
"""


def realtime_refused() -> str | None:
    """Why this process may not start SCHED_FIFO work (None: it may): tried on this thread and undone."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(BURST_PRIORITY))
    except OSError as err:
        return str(err)
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return None


def start_load(stack: ExitStack, busy_per_core: int, bursts: bool) -> tuple[int, int]:
    """The busy loops and (``bursts``) the real-time bursts, ended when ``stack`` closes; how many of each."""
    cores = sorted(os.sched_getaffinity(0))
    procs = [subprocess.Popen([sys.executable, "-c", _BUSY], stderr=subprocess.DEVNULL)
             for _ in range(busy_per_core * len(cores))]
    n_busy = len(procs)
    if bursts:
        procs += [subprocess.Popen([sys.executable, "-c", _BURST, str(cpu), str(BURST_PRIORITY), str(BURST_BUSY_S)],
                                   stderr=subprocess.DEVNULL) for cpu in cores]

    def stop() -> None:
        for proc in procs:
            proc.kill()
        for proc in procs:
            proc.wait()

    stack.callback(stop)
    return n_busy, len(procs) - n_busy


def start_launch(stack: ExitStack, config: Path, log: Any) -> subprocess.Popen[bytes]:
    """The rover launch on ``config`` (the simulator already serves it), its output to ``log``;
    stopped as a terminal's Ctrl+C stops it (SIGINT: the driver's safe stop) when ``stack`` closes."""
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), f"config:={config}", "sim:=false"],
                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT)

    def stop() -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(STOP_HANG_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    stack.callback(stop)
    return proc


def foreign_realtime_threads() -> int:
    """Real-time threads on this machine at the simulator's priority or above (SCHED_FIFO/RR,
    /proc/PID/task/TID/stat's rt_priority) that this run did not start: another's drivers and
    simulators contend with the rover's, and a run beside them measures more than the bursts."""
    parents: dict[int, int] = {}
    tasks: dict[int, list[tuple[int, int]]] = {}
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            parents[int(proc.name)] = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            tasks[int(proc.name)] = [(int(f[37]), int(f[38])) for f in
                                     ((t / "stat").read_text().rsplit(")", 1)[1].split() for t in (proc / "task").iterdir())]
        except (OSError, ValueError, IndexError):
            continue  # ended meanwhile
    ours = {os.getpid()}
    while grown := {pid for pid, ppid in parents.items() if ppid in ours} - ours:
        ours |= grown
    return sum(prio >= SIM_PRIORITY and policy in (os.SCHED_FIFO, os.SCHED_RR)
               for pid, threads in tasks.items() if pid not in ours for prio, policy in threads)


def arm_and_drive(seconds: float, speed_m_s: float, launch: subprocess.Popen[bytes]) -> dict[str, Any]:
    """Call /arm until every drive is armed, then publish /cmd_vel for ``seconds``; what happened
    (with the most real-time threads of others seen meanwhile, every 5 s)."""
    import rclpy
    from geometry_msgs.msg import Twist
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    from nodes.process.spinning import SpinThread

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("crowded_rover", context=context)
    arm = node.create_client(Trigger, "/arm")
    cmd_vel = node.create_publisher(Twist, "/cmd_vel", 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spin = SpinThread(executor, "crowded-rover")
    out: dict[str, Any] = {"armed": False, "cmd_vel_published": 0, "foreign_realtime_threads_max": 0}
    try:
        started = time.monotonic()
        while not out["armed"] and launch.poll() is None and time.monotonic() - started < ARM_HANG_S:
            if not arm.wait_for_service(timeout_sec=1.0):
                continue
            reply = call(arm, ARM_HANG_S, launch)
            out["armed"], out["arm_message"] = bool(reply and reply.success), reply.message if reply else "no reply"
            if not out["armed"]:
                time.sleep(1.0)  # a drive still booting: ask again
        out["armed_after_s"] = round(time.monotonic() - started, 1)
        while out["armed"] and not cmd_vel.get_subscription_count() and time.monotonic() - started < ARM_HANG_S:
            time.sleep(0.1)
        forward = Twist()
        forward.linear.x = speed_m_s
        out["drive_from"] = time.time()
        begin = next_t = time.monotonic()
        while out["armed"] and launch.poll() is None and time.monotonic() - begin < seconds:
            cmd_vel.publish(forward)
            out["cmd_vel_published"] += 1
            if out["cmd_vel_published"] % round(5 * CMD_VEL_HZ) == 1:
                out["foreign_realtime_threads_max"] = max(out["foreign_realtime_threads_max"], foreign_realtime_threads())
            next_t += 1.0 / CMD_VEL_HZ
            time.sleep(max(0.0, next_t - time.monotonic()))
        out["drive_until"] = time.time()
    finally:
        spin.stop(5.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
    return out


def call(client: Any, hang_s: float, server: subprocess.Popen[bytes]) -> Any:
    """A service's reply (None: none within ``hang_s``, or its ``server`` ended); the client's node
    spins on another thread."""
    future = client.call_async(client.srv_type.Request())
    deadline = time.monotonic() + hang_s
    while not future.done() and time.monotonic() < deadline and server.poll() is None:
        time.sleep(0.05)
    return future.result() if future.done() else None


def wheel_figures(frames: dict[str, list[tuple[float, int, bytes]]], wheels: dict[tuple[str, int], str],
                  drive: tuple[float, float], asked_counts: float) -> dict[str, Any]:
    """From the frames the listeners saw up to the end of the ``drive`` (its start and end, wall
    clock): EMCYs by wheel and code, EMCY 0x8130 by wheel, each wheel's travel (counts, and its
    fraction of ``asked_counts``), and the longest gap between two host heartbeats on each bus
    while it drove."""
    emcy: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    positions: dict[str, list[int]] = collections.defaultdict(list)
    beats: dict[str, list[float]] = collections.defaultdict(list)
    for channel, seen in frames.items():
        for t, cob, data in seen:
            if t > drive[1]:
                continue
            name = wheels.get((channel, cob & 0x7F), f"{channel} node {cob & 0x7F}")
            if 0x081 <= cob <= 0x0FF and len(data) >= 2:
                emcy[name][f"0x{int.from_bytes(data[:2], 'little'):04X}"] += 1
            elif cob & 0x780 == POSITION_TPDO and cob & 0x7F and len(data) >= 4:
                positions[name].append(int.from_bytes(data[:4], "little", signed=True))
            elif cob == HOST_HEARTBEAT_ID and t >= drive[0]:
                beats[channel].append(t)
    host_loss = {name: codes[f"0x{HOST_LOSS_CODE:04X}"] for name, codes in emcy.items() if codes[f"0x{HOST_LOSS_CODE:04X}"]}
    travel = {name: sum(abs(b - a) for a, b in itertools.pairwise(positions.get(name, []))) for name in wheels.values()}
    gaps = {ch: round(max((b - a for a, b in itertools.pairwise(ts)), default=0.0) * 1000, 1) for ch, ts in beats.items()}
    return {"emcy_8130": sum(host_loss.values()), "emcy_8130_by_wheel": host_loss,
            "emcy_by_wheel": {name: dict(codes) for name, codes in sorted(emcy.items())},
            "wheel_travel_counts": travel, "wheel_travel_asked_counts": round(asked_counts),
            "wheel_travel_fraction": {name: round(c / asked_counts, 3) if asked_counts else 0.0 for name, c in travel.items()},
            "host_heartbeat_gap_max_ms_driving": gaps}


def asked_counts(shipped: RoverConfig, speed_m_s: float, driven_s: float) -> float:
    """How far (position counts) a wheel of ``shipped`` turns at ``speed_m_s`` for ``driven_s``."""
    assert shipped.drive_system is not None
    wheel_rev = speed_m_s * driven_s / (2 * math.pi * shipped.drive_system.wheel_radius_m)
    return wheel_rev * shipped.drives[0].counts_per_deg * 360


def launch_log_figures(log: Any) -> dict[str, int]:
    """What the launch's own output says: lines naming EMCY 0x8130, lost heartbeats, tracebacks."""
    log.seek(0)
    lines = log.read().decode(errors="replace").splitlines()
    return {"log_8130_lines": sum("0x8130" in line for line in lines),
            "log_heartbeat_lost_lines": sum("heartbeat lost" in line for line in lines),
            "log_tracebacks": sum(line.startswith("Traceback") for line in lines)}


def verdict(figures: dict[str, Any]) -> tuple[bool, str]:
    """PASS when no EMCY 0x8130 was seen and every wheel turned at least MOVED_FRACTION of what was
    asked, else FAIL with what was seen."""
    still = sorted(f"{name} {fraction:.0%}" for name, fraction in figures["wheel_travel_fraction"].items()
                   if fraction < MOVED_FRACTION)
    faults = []
    if figures["emcy_8130"]:
        faults.append(f"{figures['emcy_8130']} EMCY 0x8130 (host heartbeat lost) {figures['emcy_8130_by_wheel']}")
    if figures["launch_exit_status"] is not None:
        faults.append(f"the launch ended (exit status {figures['launch_exit_status']}) before the drive did")
    if not figures["armed"]:
        faults.append(f"not armed: {figures.get('arm_message', 'no /arm reply')}")
    if still:
        faults.append(f"wheels that turned less than {MOVED_FRACTION:.0%} of what /cmd_vel asked: {', '.join(still)}")
    load = f"{figures['busy_loops']} busy loops, {figures['realtime_bursts']} real-time bursts"
    if faults and figures.get("foreign_realtime_threads_max"):
        faults.append(f"beside up to {figures['foreign_realtime_threads_max']} real-time threads of other work at"
                      f" priority {SIM_PRIORITY} or above: more than this run's load")
    if faults:
        return False, f"FAIL ({load}): " + "; ".join(faults)
    least = min(figures["wheel_travel_fraction"].values(), default=0.0)
    return True, f"PASS ({load}): no EMCY 0x8130; {figures['seconds']:g} s driven, every wheel turned >= {least:.1%} of what was asked"


def run(args: argparse.Namespace) -> int:
    shipped = load_config(SHIPPED["rover"])
    channels = {b.name: b.channel for b in shipped.buses}
    wheels = {(channels[d.bus], d.node_id): d.name for d in shipped.drives}
    refused = None if args.no_bursts else realtime_refused()
    if refused:
        print(f"crowded_rover: not root (SCHED_FIFO refused: {refused}): running without the real-time bursts",
              file=sys.stderr, flush=True)
    figures: dict[str, Any] = {"seconds": args.seconds, "cores": len(os.sched_getaffinity(0))}
    with tempfile.TemporaryFile() as log, ExitStack() as stack:
        figures["busy_loops"], figures["realtime_bursts"] = start_load(stack, args.busy_per_core, not (args.no_bursts or refused))
        port = stack.enter_context(simulator("--config", str(SHIPPED["rover"])))
        config = on_port(SHIPPED["rover"], port, stack.enter_context(tempfile.TemporaryDirectory()))
        listeners = {ch: Listener(port, ch) for ch in sorted(set(channels.values()))}
        for listener in listeners.values():
            listener.start()
            stack.callback(listener.close)
        launch = start_launch(stack, config, log)
        figures |= arm_and_drive(args.seconds, args.speed, launch)
        figures["load_average_1min"] = os.getloadavg()[0]
        figures["launch_exit_status"] = launch.poll()
        # the driver's and the simulator's threads under SCHED_FIFO (0: they run ordinary, refused)
        figures["driver_fifo_threads"] = fifo_thread_count(launch.pid, children=True)
        figures["simulator_fifo_threads"] = fifo_thread_count(SIM_PIDS[-1], children=True)
        for listener in listeners.values():
            listener.close()  # idempotent: its frames now
        until = figures.pop("drive_until", time.time())
        drive = (figures.pop("drive_from", until), until)
        figures |= wheel_figures({ch: lst.frames for ch, lst in listeners.items()}, wheels, drive,
                                 asked_counts(shipped, args.speed, drive[1] - drive[0]))
        stack.close()  # the launch's safe stop, the simulator, the load: before its log is read
        figures |= launch_log_figures(log)
        if figures["launch_exit_status"] is not None:  # why, for the reader of a FAIL
            log.seek(0)
            print(*log.read().decode(errors="replace").splitlines()[-20:], sep="\n", file=sys.stderr, flush=True)
    ok, line = verdict(figures)
    print(json.dumps(figures), flush=True)
    print(line, flush=True)
    return 0 if ok else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=180.0, help="how long /cmd_vel drives the rover (180)")
    parser.add_argument("--busy-per-core", type=int, default=2, help="busy loops per core at ordinary priority (2)")
    parser.add_argument("--no-bursts", action="store_true", help="leave out the real-time bursts")
    parser.add_argument("--speed", type=float, default=0.3, help="/cmd_vel forward speed, m/s (0.3)")
    args = parser.parse_args()

    def on_term(signum: int, frame: object) -> None:
        raise KeyboardInterrupt  # the same way out as Ctrl-C: every process started is ended

    signal.signal(signal.SIGTERM, on_term)
    try:
        return run(args)
    except KeyboardInterrupt:
        print("crowded_rover: interrupted; everything it started is stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
