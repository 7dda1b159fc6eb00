"""deploy/: what can be checked without a Jetson: the files parse, every path the unit, the
image and its entry point use exists in the layout the Dockerfile builds, and the boot-time CAN
settings are the ones `rovercan can-up` applies."""

from __future__ import annotations

import configparser
import os
import re
import shlex
import subprocess
from pathlib import Path

from can_config import load_config
from rovercan.bench import can_up_commands
from rovercan.launch import parse_launch

from .conftest import REPO

DEPLOY = REPO / "deploy"


def ini(path: Path) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # systemd keys are case-sensitive
    parser.read_string(path.read_text())
    return parser


def dockerfile() -> list[tuple[str, str]]:
    """(instruction, arguments) of deploy/Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n\s*", " ", (DEPLOY / "Dockerfile").read_text())
    return [(line.split(None, 1)[0], line.split(None, 1)[1]) for line in text.splitlines()
            if line.strip() and not line.startswith("#")]


def test_the_image_copies_what_exists_and_installs_the_packages() -> None:
    steps = dockerfile()
    assert steps[0] == ("FROM", "ros:jazzy-ros-base")  # multi-arch: linux/arm64 for the Orin
    copied = [args.split() for op, args in steps if op == "COPY"]
    for *sources, _ in copied:
        for source in sources:
            assert (REPO / source).exists(), source
    listed = re.search(r"^packages = \[(.*?)\]", (REPO / "pyproject.toml").read_text(), re.MULTILINE)
    assert listed is not None  # (no tomllib: Python 3.10 is supported)
    packages = [p.strip().strip('"') for p in listed.group(1).split(",")]
    top = {p.split(".")[0] for p in packages}
    assert top <= {s for *sources, _ in copied for s in sources}, top  # every package is in the image
    assert ["deploy/entrypoint.sh", "/opt/rovercan/entrypoint.sh"] in copied
    assert ("ENTRYPOINT", '["/opt/rovercan/entrypoint.sh"]') in steps
    assert any(op == "ENV" and args == "ROVERCAN_CONFIG=/etc/rovercan/rover.yaml" for op, args in steps)


def test_the_entry_point_launches_the_rover_launch_file_of_the_image() -> None:
    entry = DEPLOY / "entrypoint.sh"
    assert os.access(entry, os.X_OK)
    assert subprocess.run(["bash", "-n", str(entry)], capture_output=True).returncode == 0
    text = entry.read_text()
    assert "source /opt/rovercan/install/setup.bash" in text  # the Dockerfile's colcon --install-base
    assert "/opt/rovercan/install" in (DEPLOY / "Dockerfile").read_text()
    launch = re.search(r"ros2 launch rovercan_bringup (\S+) \"config:=\$ROVERCAN_CONFIG\"", text)
    assert launch is not None
    processes = parse_launch(REPO / "ros" / "rovercan_bringup" / "launch" / launch.group(1), {"config": "/x.yaml"})
    assert any("config:=/x.yaml" in p.argv for p in processes)


def test_the_unit_starts_the_image_after_can0_with_the_config_mounted() -> None:
    unit = ini(DEPLOY / "rovercan.service")
    assert "sys-subsystem-net-devices-can0.device" in unit["Unit"]["Requires"]
    assert "sys-subsystem-net-devices-can0.device" in unit["Unit"]["After"]
    start = shlex.split(unit["Service"]["ExecStart"])
    assert start[:3] == ["/usr/bin/docker", "run", "--rm"] and start[-1] == "rovercan:latest"
    assert "--network" in start and start[start.index("--network") + 1] == "host"  # SocketCAN is the host's
    assert "--cap-add" in start and start[start.index("--cap-add") + 1] == "SYS_NICE"  # the driver's SCHED_FIFO
    mount = start[start.index("-v") + 1].split(":")
    assert mount[1] == "/etc/rovercan"  # where ROVERCAN_CONFIG points in the image
    volumes = [start[i + 1].split(":") for i, word in enumerate(start) if word == "-v"]
    incidents = re.search(r"ENV ROVERCAN_INCIDENT_DIR=(\S+)", (DEPLOY / "Dockerfile").read_text())
    assert incidents is not None and [incidents.group(1)] * 2 in volumes  # the flight recorder's files outlive it
    assert unit["Service"]["StateDirectory"] == "rovercan/incidents"
    assert "docker build -f deploy/Dockerfile -t rovercan:latest ." in (DEPLOY / "Dockerfile").read_text()
    assert shlex.split(unit["Service"]["ExecStop"])[:3] == ["/usr/bin/docker", "stop", "--time"]
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_the_boot_time_can_settings_are_the_ones_can_up_applies() -> None:
    network = ini(DEPLOY / "80-can0.network")
    link = ini(DEPLOY / "80-can0.link")
    rover_bitrates = {b.bitrate for b in load_config(REPO / "config" / "rover.yaml").buses}
    assert rover_bitrates == {int(network["CAN"]["BitRate"])}
    ip = [" ".join(c) for c in can_up_commands("can0", int(network["CAN"]["BitRate"]), 100, 1000)]
    assert f"restart-ms {int(network['CAN']['RestartSec'].removesuffix('ms'))}" in ip[1]
    assert "berr-reporting on" in ip[1] and network["CAN"]["BusErrorReporting"] == "yes"
    assert f"txqueuelen {link['Link']['TransmitQueueLength']}" in ip[2]
    assert network["Match"]["Name"] == link["Match"]["OriginalName"] == "can0"
    modules = [m for m in (DEPLOY / "modules-load.conf").read_text().splitlines() if m and not m.startswith("#")]
    assert modules == ["can", "can_raw", "mttcan"]
