"""On a machine without the ROS wheels (aarch64 without /opt/ros, a core-only install) the
suite skips its ROS tests with a reason and errors nowhere, and the demo says what is missing.
Simulated here: a sitecustomize that makes every ROS package unimportable, for pytest and
every process it starts."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from .conftest import REPO

ROS_PACKAGES = ("rclpy", "rovercan_msgs", "std_msgs", "sensor_msgs", "geometry_msgs", "nav_msgs", "diagnostic_msgs",
                "std_srvs", "rcl_interfaces", "builtin_interfaces", "action_msgs")


def without_ros(tmp_path: Path) -> dict[str, str]:
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(f"import sys\nfor name in {ROS_PACKAGES!r}:\n    sys.modules[name] = None\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (str(site), os.environ.get("PYTHONPATH")))))


def test_the_ros_tests_skip_cleanly_without_ros(tmp_path: Path) -> None:
    env = without_ros(tmp_path)
    assert subprocess.run([sys.executable, "-c", "import rclpy"], env=env, capture_output=True).returncode != 0
    collected = subprocess.run([sys.executable, "-m", "pytest", "-q", "--collect-only", "-p", "no:cacheprovider"],
                               cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert collected.returncode == 0 and "error" not in collected.stdout.splitlines()[-1], collected.stdout[-2000:]
    # every test that touches rclpy, the nodes or the interface package, run: they must skip
    files = ["tests/test_ros_interface.py", "tests/test_ros_graph.py", "tests/test_ros_limits.py",
             "tests/test_shutdown.py", "tests/test_lifecycle.py", "tests/test_sim_cli.py::test_demo_runs_and_exits_zero",
             "tests/test_connect.py::test_the_node_without_a_bus_server_logs_one_line_per_attempt",
             "tests/test_launch.py::test_rovercan_launch_runs_the_graph"]
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *files], cwd=REPO,
                            env=env, capture_output=True, text=True, timeout=300)
    summary = result.stdout.strip().splitlines()[-1]
    assert result.returncode == 0 and "skipped" in summary and "passed" not in summary, result.stdout[-3000:]
    assert "error" not in summary and "failed" not in summary
    assert "rclpy / rovercan_msgs not installed (run ./dev setup)" in result.stdout


def test_the_demo_without_ros_names_what_is_missing(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, "-m", "rovercan", "demo", "--duration", "1"], cwd=REPO,
                            env=without_ros(tmp_path), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "the demo runs ROS 2 nodes" in result.stderr and "./dev setup" in result.stderr
    assert "Traceback" not in result.stderr
