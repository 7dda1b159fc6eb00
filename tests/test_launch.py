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

from .conftest import REPO, requires_ros
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
    """The launched graph works end to end: motor_degree -> DDS -> motor_controller -> CANopen.
    Observed on the bus (RPDO set-points that follow the degree ramp), so the check does not
    depend on DDS discovery between the test process and the launched ones."""
    import can

    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                      f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                      "drives:\n  - {name: motor, node_id: 1, counts_per_rev: 4096}\n")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", str(LAUNCH), "sim:=true", "arm:=true",
                             f"config:={config}", "--duration", "60"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    targets: list[int] = []
    try:
        listener = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)  # retries 10 s
        try:
            deadline = time.monotonic() + 40.0  # three Python processes start on two cores
            while time.monotonic() < deadline and len(targets) < 5:
                msg = listener.recv(0.5)
                if msg is not None and msg.arbitration_id == 0x301 and msg.data[0] & 0x10:  # new set-point
                    targets.append(int.from_bytes(msg.data[2:6], "little", signed=True))
        finally:
            listener.shutdown()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert len(targets) >= 5, f"no set-points from the launched graph: {out[-3000:]}"
    assert targets == sorted(targets) and targets[-1] > targets[0]  # following the +0.1 deg ramp
    assert proc.returncode == 0, out[-3000:]
