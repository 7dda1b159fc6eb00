"""The XML launch file: it parses, names only executables that exist, and `rovercan launch`
runs the same graph (separate processes) where the ros2 CLI is absent."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from can_config import ConfigError
from rovercan.launch import EXECUTABLES, parse_launch

from .conftest import HAVE_ROS, REPO, requires_ros
from .test_sim_cli import free_port

LAUNCH = REPO / "ros" / "rovercan_bringup" / "launch" / "motor_launch.xml"
BRINGUP = REPO / "ros" / "rovercan_bringup"


def test_launch_file_names_only_existing_executables() -> None:
    processes = parse_launch(LAUNCH, {"sim": "true"})
    names = [p.name for p in processes]
    assert names[1:] == ["motor_controller", "motor_degree"]
    for exe in EXECUTABLES:
        script = BRINGUP / "scripts" / exe
        assert script.is_file() and os.access(script, os.X_OK)
        assert f"from nodes.{exe} import main" in script.read_text()
        assert (REPO / "nodes" / f"{exe}.py").is_file()
    assert "scripts/motor_controller scripts/motor_degree scripts/rover_driver" in (BRINGUP / "CMakeLists.txt").read_text()
    rover = parse_launch(BRINGUP / "launch" / "rover_launch.xml", {"config": "config/rover.yaml", "sim": "true"})
    assert [p.name for p in rover] == ["python", "rovercan_driver"]
    assert "nodes.rover_driver" in rover[1].argv and "config:=config/rover.yaml" in rover[1].argv


def test_unknown_launch_argument_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"unknown launch argument\(s\) \['speed'\]"):
        parse_launch(LAUNCH, {"speed": "1"})


@requires_ros
def test_rovercan_launch_runs_the_graph(tmp_path: Path) -> None:
    if HAVE_ROS:
        import rclpy
        from rovercan_msgs.msg import MotorState

        from nodes.qos import STATE_QOS
    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                      "drives:\n  - {name: motor, node_id: 1}\n")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), "sim:=true", "arm:=true",
                             f"config:={config}", "--duration", "40"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # the same range as the launched nodes
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("launch_probe", context=context)
    states: list[MotorState] = []
    node.create_subscription(MotorState, "/motor_state", states.append, STATE_QOS)
    try:
        deadline = time.monotonic() + 30.0  # three Python processes start on two cores
        while time.monotonic() < deadline and not (len(states) > 20 and states[-1].angle > 0.5):
            _spin(node, context)
        assert states, "no /motor_state from the launched graph"
        assert states[-1].state == "OPERATION_ENABLED"
        assert states[-1].angle > 0.5  # following motor_degree's ramp
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out


def _spin(node: object, context: object) -> None:
    import rclpy.executors
    executor = rclpy.executors.SingleThreadedExecutor(context=context)  # type: ignore[arg-type]
    executor.add_node(node)  # type: ignore[arg-type]
    executor.spin_once(timeout_sec=0.1)
    executor.remove_node(node)  # type: ignore[arg-type]
    executor.shutdown()
