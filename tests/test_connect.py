"""With no bus server, the API, the nodes and the CLI wait for it with back-off: one line per
attempt (python-can's own loop logged ~30,000 lines a second and spun a core for 10 s), then a
clear error naming host:port."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import REPO, requires_ros
from .test_sim_cli import free_port

API_SCRIPT = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
from can_config import parse_config
from motor_driver import MotorDriver
from can_config.errors import BusLostError
config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                   "connect_timeout_ms": 1500, "kwargs": {"host": "127.0.0.1", "port": %d}}],
                       "drives": [{"name": "a", "node_id": 1}]})
try:
    MotorDriver(config)
except BusLostError as err:
    print(f"ERROR {err}", file=sys.stderr)
    sys.exit(3)
"""


def run_counting_cpu(cmd: list[str]) -> tuple[subprocess.CompletedProcess[str], float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return result, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def check_quiet_retries(stderr: str, port: int) -> None:
    lines = stderr.splitlines()
    attempts = [ln for ln in lines if f"socketcand server 127.0.0.1:{port}:" in ln and "attempt" in ln]
    assert 2 <= len(attempts) <= 8, stderr  # back-off 0.1, 0.2, 0.4, 0.8 s within 1.5 s: one line each
    assert not [ln for ln in lines if "Failed to connect to server" in ln], stderr[:2000]
    assert f"127.0.0.1:{port} not reachable" in stderr and "rovercan sim" in stderr


def test_the_api_without_a_bus_server_logs_one_line_per_attempt_and_does_not_spin() -> None:
    port = free_port()
    result, cpu_s = run_counting_cpu([sys.executable, "-c", API_SCRIPT % port])
    assert result.returncode == 3, result.stderr[-2000:]
    check_quiet_retries(result.stderr, port)
    assert cpu_s < 1.5, cpu_s  # interpreter start-up and imports; no busy loop


@requires_ros
def test_the_node_without_a_bus_server_logs_one_line_per_attempt(tmp_path: Path) -> None:
    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0, connect_timeout_ms: 1500,"
                      f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\ndrives:\n  - {{name: a, node_id: 1}}\n")
    result, _ = run_counting_cpu([sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p", f"config:={config}"])
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.splitlines()
    assert not [ln for ln in lines if "Failed to connect to server" in ln], result.stderr[:2000]
    assert f"127.0.0.1:{port} not reachable" in result.stderr


@pytest.mark.parametrize("args", [["scan"], ["sdo", "read", "1", "0x1000"]])
def test_the_cli_without_a_bus_server_names_host_and_port(args: list[str]) -> None:
    port = free_port()
    result = subprocess.run([sys.executable, "-m", "rovercan", *args, "-i", "socketcand", "-c", "can0",
                             "--bus-kwargs", "host=127.0.0.1", f"port={port}"], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 1, result.stderr
    assert f"127.0.0.1:{port} not reachable" in result.stderr and "Traceback" not in result.stderr
    assert "Failed to connect to server" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr  # the attempts are INFO: one line
