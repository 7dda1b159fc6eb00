"""The shipped rover, launched again and again (issue 39): `rover_launch.xml
config:=config/rover.yaml sim:=true arm:=true`, N times in a row on this machine. Each time every
wheel must be armed (its MotorState says OPERATION_ENABLED) and /cmd_vel must drive it (/odom
moves); the launch's log is searched for a late host heartbeat and for drives that stopped
themselves (EMCY 0x8130). Prints one JSON line per launch and a summary; exit 1 when any failed.

    python benchmarks/rover_launches.py [--runs 10]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data
from rovercan_msgs.msg import MotorState

from nodes.runtime import SpinThread

REPO = Path(__file__).resolve().parent.parent
LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "rover_launch.xml"
WHEELS = ["wheel_front_left", "wheel_middle_left", "wheel_rear_left", "wheel_front_right", "wheel_middle_right",
          "wheel_rear_right"]
HANG_S = 90.0


def one_launch(index: int) -> dict[str, object]:
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), "config:=config/rover.yaml",
                             "sim:=true", "arm:=true", "--duration", "300"], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
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
        proc.terminate()
        out, _ = proc.communicate(timeout=60)
    result["late_heartbeat_lines"] = sum("host heartbeat" in line and "late" in line for line in out.splitlines())
    result["stopped_itself_lines"] = sum("0x8130" in line for line in out.splitlines())
    result["traceback"] = "Traceback" in out
    result["ok"] = (result["armed"] == sorted(WHEELS) and float(result.get("moved_m", 0.0)) > 0.1  # type: ignore[arg-type]
                    and not result["traceback"] and proc.returncode == 0)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    args = parser.parse_args()
    results = []
    for i in range(args.runs):
        results.append(one_launch(i))
        print(json.dumps(results[-1]), flush=True)
    ok = sum(bool(r["ok"]) for r in results)
    print(json.dumps({"launches": len(results), "armed_and_driven": ok,
                      "late_heartbeat_lines": sum(int(r["late_heartbeat_lines"]) for r in results)}), flush=True)  # type: ignore[call-overload]
    return 0 if ok == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
