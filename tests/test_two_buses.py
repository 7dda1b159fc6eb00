"""The rover as configured, on two buses (issue 41). A six-wheel config written from the
documented keys only: the left wheels on can0, the right wheels on can1, mounted mirrored
(``invert: true``), node ids 1-3 on each bus, each bus on a socketcand port of its own.

- ``rovercan sim --config`` serves both ports (one server per port);
- a bench command picks the drive a name names, or (with -c BUS) the node id on that bus, and
  takes every setting (invert, gear, resolution) from that drive: ``jog wheel_front_right`` and
  ``jog 1 -c can1`` turn can1's node 1 forward (its motor backwards: it is inverted) and leave
  can0's node 1 where it was;
- a node id on both buses with no bus named is refused, naming both drives.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from .conftest import REPO
from .test_sim_cli import free_port

SIDES = {"can0": ("left", False), "can1": ("right", True)}
WHEEL = {"counts_per_rev": 4096, "gear_ratio": 50.0, "max_velocity_deg_s": 720}


def six_wheels(port0: int, port1: int) -> dict[str, object]:
    """The rover of docs/configuration.md's keys: buses, drives, drive system."""
    ports = {"can0": port0, "can1": port1}
    buses = [{"name": bus, "interface": "socketcand", "channel": bus, "kwargs": {"host": "127.0.0.1", "port": port}}
             for bus, port in ports.items()]
    drives = [{"name": f"wheel_{place}_{side}", "namespace": "wheels", "node_id": node, "bus": bus,
               **({"invert": True} if invert else {}), **WHEEL}
              for bus, (side, invert) in SIDES.items() for node, place in enumerate(("front", "middle", "rear"), 1)]
    return {"buses": buses, "drives": drives,
            "drive_system": {"left": [d["name"] for d in drives[:3]], "right": [d["name"] for d in drives[3:]],
                             "track_width_m": 0.6, "wheel_radius_m": 0.1}}


@dataclass
class Rover:
    config: Path
    ports: dict[str, int]

    def bus(self, channel: str) -> list[str]:
        return ["-i", "socketcand", "-c", channel, "--bus-kwargs", "host=127.0.0.1", f"port={self.ports[channel]}"]


def rovercan(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def rover(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rover]:
    ports = {"can0": free_port(), "can1": free_port()}
    path = tmp_path_factory.mktemp("rover") / "six_wheels.yaml"
    path.write_text(yaml.safe_dump(six_wheels(ports["can0"], ports["can1"])))
    assert rovercan("check", "--config", str(path)).returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--config", str(path)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        served = [proc.stdout.readline() for _ in range(4)]  # per server: its line and one channel's
        for channel, port in ports.items():
            assert any(f"-c {channel} --bus-kwargs host=127.0.0.1 port={port}" in line for line in served), served
        yield Rover(path, ports)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)


def position(rover: Rover, channel: str, node: int) -> int:
    """0x6064 (position actual value, counts) of ``node`` on ``channel``, read by SDO."""
    read = rovercan("sdo", "read", str(node), "0x6064", "--json", *rover.bus(channel))
    assert read.returncode == 0, read.stderr
    return int(json.loads(read.stdout)["value"])


def test_a_config_with_two_ports_is_served_on_both(rover: Rover) -> None:
    for channel in ("can0", "can1"):
        scan = rovercan("scan", "--json", "--listen", "0.5", *rover.bus(channel))
        assert scan.returncode == 0, scan.stderr
        assert [row["node"] for row in json.loads(scan.stdout)] == [1, 2, 3]


@pytest.mark.parametrize("pick", [("wheel_front_right",), ("1", "-c", "can1")], ids=["by-name", "by-bus-and-node"])
def test_jog_turns_the_named_drive_forward_and_leaves_the_other_bus_alone(rover: Rover, pick: tuple[str, ...]) -> None:
    before = {channel: position(rover, channel, 1) for channel in ("can0", "can1")}
    jog = rovercan("jog", pick[0], "30", "--for", "0.5", "--config", str(rover.config), *pick[1:], "--json")
    assert jog.returncode == 0, jog.stderr
    assert json.loads(jog.stdout)["velocity_deg_s"] > 0  # forward, in the joint's own terms
    after = {channel: position(rover, channel, 1) for channel in ("can0", "can1")}
    assert after["can0"] == before["can0"]  # can0's node 1 never moved
    # inverted: the joint forward is the motor backwards; 30 deg/s x 0.5 s x 50 = 750 motor deg
    assert after["can1"] - before["can1"] < -4096 // 2, (before, after)


def test_a_node_id_on_both_buses_needs_a_bus_or_a_name(rover: Rover) -> None:
    both = rovercan("jog", "1", "30", "--for", "0.5", "--config", str(rover.config))
    assert both.returncode == 2
    assert "wheel_front_left on can0" in both.stderr and "wheel_front_right on can1" in both.stderr
    assert "Traceback" not in both.stderr
    wrong_bus = rovercan("jog", "wheel_front_left", "30", "--for", "0.5", "--config", str(rover.config), "-c", "can1")
    assert wrong_bus.returncode == 2 and "is on bus can0, not can1" in wrong_bus.stderr
    unknown = rovercan("info", "wheel_nowhere", "--config", str(rover.config))
    assert unknown.returncode == 2 and "wheel_front_right (node 1 on can1)" in unknown.stderr


def test_safety_check_covers_every_bus_by_its_name(rover: Rover) -> None:
    check = rovercan("safety-check", "--config", str(rover.config), "--json", "--listen", "0.3")
    # no driver runs, so the host heartbeat is missing on each bus: the check fails, on both buses
    assert check.returncode == 1, check.stderr
    drives = {row["drive"] for row in _json_rows(check.stdout)}
    assert {"wheel_front_left", "wheel_front_right", "wheel_rear_right"} <= drives


def _json_rows(text: str) -> list[dict[str, object]]:
    """Every row of the JSON arrays ``emit`` printed, one array per bus."""
    decoder, rows, at = json.JSONDecoder(), [], 0
    while at < len(text):
        if text[at].isspace():
            at += 1
            continue
        value, at = decoder.raw_decode(text, at)
        rows += value
    return rows
