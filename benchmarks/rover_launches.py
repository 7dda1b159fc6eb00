"""The shipped rover, launched again and again (issue 39): `rover_launch.xml
config:=config/rover.yaml sim:=true arm:=true`, N times in a row on this machine. Each time every
wheel must be armed (its MotorState says OPERATION_ENABLED) and /cmd_vel must drive it (/odom
moves); the launch's log is searched for a late host heartbeat and for drives that stopped
themselves (EMCY 0x8130), and a listener on can0 takes the longest gap between two host
heartbeats on the wire (the margin to the drives' 150 ms consumer time). ``--busy N`` runs N
busy-loop processes beside it: a machine with slower cores, such as the Orin's, as far as this
one can stand in for it. Prints one JSON line per launch and a summary; exit 1 when any failed.

    python benchmarks/rover_launches.py [--runs 10] [--busy 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import rclpy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data
from rovercan_msgs.msg import MotorState

from nodes.process.spinning import SpinThread

REPO = Path(__file__).resolve().parent.parent
LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml"
WHEELS = ["wheel_front_left", "wheel_middle_left", "wheel_rear_left", "wheel_front_right", "wheel_middle_right",
          "wheel_rear_right"]
HANG_S = 90.0
#: The shipped config's host heartbeat on can0 (host node id 127), and where its twin serves.
HOST_HEARTBEAT_ID = 0x700 + 127
SIM_PORT = 29536


class HeartbeatGaps(threading.Thread):
    """The host heartbeats on can0 as the twin's server stamps them; the longest gap between two."""

    def __init__(self) -> None:
        super().__init__(daemon=True, name="heartbeat-gaps")
        self.beats: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        bus = None
        while bus is None and not self.stop.wait(0.2):  # the twin is starting
            try:
                bus = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=SIM_PORT)
            except (can.CanError, OSError):
                bus = None
        if bus is None:
            return
        try:
            while not self.stop.is_set():
                msg = bus.recv(0.1)
                if msg is not None and msg.arbitration_id == HOST_HEARTBEAT_ID:
                    self.beats.append(msg.timestamp)
        finally:
            bus.shutdown()

    def longest_ms(self) -> float | None:
        gaps = [b - a for a, b in zip(self.beats, self.beats[1:], strict=False)]
        return round(max(gaps) * 1000, 1) if gaps else None


def one_launch(index: int) -> dict[str, object]:
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), "config:=config/rover.yaml",
                             "sim:=true", "arm:=true", "--duration", "300"], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    gaps = HeartbeatGaps()
    gaps.start()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node(f"launch_probe_{index}", context=context)
    states: dict[str, str] = {}
    odom: list[float] = []
    for wheel in WHEELS:
        node.create_subscription(MotorState, f"/wheels/{wheel}/motor_state",
                                 lambda m, w=wheel: states.__setitem__(w, m.state), qos_profile_sensor_data)
    node.create_subscription(Odometry, "/odom", lambda m: odom.append(m.pose.pose.position.x), qos_profile_sensor_data)
    cmd_vel = node.create_publisher(Twist, "/cmd_vel", 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spin = SpinThread(executor, f"launch-probe-{index}")
    started = time.monotonic()
    result: dict[str, object] = {"run": index}
    try:
        deadline = started + HANG_S
        while not (len(states) == len(WHEELS) and all(s == "OPERATION_ENABLED" for s in states.values())
                   and odom and cmd_vel.get_subscription_count()):
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
        result["armed"] = sorted(w for w, s in states.items() if s == "OPERATION_ENABLED")
        result["armed_s"] = round(time.monotonic() - started, 2)
        if odom:
            start_x, forward = odom[-1], Twist()
            forward.linear.x = 0.2
            until = time.monotonic() + 2.0
            while time.monotonic() < until:
                cmd_vel.publish(forward)
                time.sleep(0.05)
            result["moved_m"] = round(odom[-1] - start_x, 3)
    finally:
        spin.stop(5.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
        gaps.stop.set()
        gaps.join(5.0)
        proc.terminate()
        out, _ = proc.communicate(timeout=60)
    result["host_heartbeats"] = len(gaps.beats)
    result["longest_heartbeat_gap_ms"] = gaps.longest_ms()
    result["late_heartbeat_lines"] = sum("host heartbeat" in line and "late" in line for line in out.splitlines())
    result["stopped_itself_lines"] = sum("0x8130" in line for line in out.splitlines())
    result["traceback"] = "Traceback" in out
    result["ok"] = (result["armed"] == sorted(WHEELS) and float(result.get("moved_m", 0.0)) > 0.1  # type: ignore[arg-type]
                    and not result["traceback"] and proc.returncode == 0)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--busy", type=int, default=0, help="busy-loop processes beside the launches")
    args = parser.parse_args()
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    try:
        return report([one_launch(i) for i in range(args.runs)], args.busy)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait()


def report(results: list[dict[str, object]], busy: int) -> int:
    for result in results:
        print(json.dumps(result), flush=True)
    ok = sum(bool(r["ok"]) for r in results)
    longest = [float(r["longest_heartbeat_gap_ms"]) for r in results if r["longest_heartbeat_gap_ms"] is not None]  # type: ignore[arg-type]
    print(json.dumps({"launches": len(results), "busy_loops": busy, "armed_and_driven": ok,
                      "late_heartbeat_lines": sum(int(r["late_heartbeat_lines"]) for r in results),  # type: ignore[call-overload]
                      "longest_heartbeat_gap_ms": max(longest, default=None)}), flush=True)
    return 0 if ok == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
