"""The CLI's exit-code rule, against `rovercan sim` in another process: 0 done; 1 the bus or a
drive failed or refused; 2 bad usage, a bad config or input, or a command refused before it was
sent. Drive commands never run on a bus nobody named."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import REPO
from .test_sim_cli import free_port


@pytest.fixture(scope="module")
def sim_port() -> Iterator[int]:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--drives", "2", "--port", str(port)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and "simulated drive" in proc.stdout.readline()
    yield port
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=10)


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60)


def bus(port: int) -> list[str]:
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={port}"]


@pytest.mark.parametrize("args", [["move", "1", "10"], ["jog", "1", "10", "--for", "1"], ["enable", "1"],
                                  ["home", "1"], ["step-test", "1", "--step", "10"], ["disable", "1"]])
def test_a_drive_command_without_a_bus_is_refused_not_run_on_a_virtual_one(args: list[str]) -> None:
    result = run(*args)
    assert result.returncode == 2 and "no bus given: pass -i INTERFACE -c CHANNEL" in result.stderr, result.stderr
    assert "no boot-up" not in result.stderr


def test_nmt_to_a_node_that_is_not_there_fails(sim_port: int) -> None:
    for action in ("start", "stop", "preop", "reset"):
        result = run("nmt", action, "9", *bus(sim_port))
        assert result.returncode == 1 and "node 9: nothing heard from it" in result.stderr, (action, result.stderr)
    for action in ("stop", "start", "preop", "reset", "reset-comm", "start"):
        assert run("nmt", action, "2", *bus(sim_port)).returncode == 0, action
    assert run("nmt", "start", "all", *bus(sim_port)).returncode == 0


def limited_config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "limited.yaml"
    path.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                    f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                    "drives:\n  - {name: joint1, node_id: 1, joint: limited, min_deg: -90, max_deg: 90,"
                    " counts_per_rev: 4096, max_velocity_deg_s: 360}\n")
    return path


def test_commands_refused_before_they_are_sent_exit_2(sim_port: int, tmp_path: Path) -> None:
    config = str(limited_config(tmp_path, sim_port))
    before = run("sdo", "read", "1", "0x6064", *bus(sim_port), "--json").stdout
    for args, says in ((["move", "1", "120"], "above the upper limit max_deg=90"),
                       (["jog", "1", "500", "--for", "1"], "500"),
                       (["move", "1", "10", "--speed", "1000"], "--speed 1000 deg/s: allowed")):
        result = run(*args, "--config", config)
        assert result.returncode == 2 and says in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr
    assert run("sdo", "read", "1", "0x6064", *bus(sim_port), "--json").stdout == before  # nothing moved
    result = run("sim", "--host", "0.0.0.0", "--port", "0")
    assert result.returncode == 2 and "listens on loopback" in result.stderr
