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

import pytest

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
    assert 'ROVERCAN_HOME="${ROVERCAN_HOME:-/opt/rovercan}"' in text and "/opt/rovercan/install" in (
        DEPLOY / "Dockerfile").read_text()  # the Dockerfile's colcon --install-base under it
    launch = re.search(r'exec rovercan launch "\$ROVERCAN_HOME/(\S+)" "config:=\$ROVERCAN_CONFIG"', text)
    assert launch is not None
    processes = parse_launch(REPO / launch.group(1), {"config": "/x.yaml"})
    assert any("config:=/x.yaml" in p.argv for p in processes)


def test_the_entry_point_runs_past_ros_s_setup_scripts_to_the_launch(tmp_path: Path) -> None:
    """Run as the image runs it, each path of the image a stand-in: ROS's setup scripts read
    variables they never set (ament_package's AMENT_TRACE_SETUP_FILES, colcon's COLCON_TRACE), which
    ended the script under `set -u` before the launch (every start, exit 1); it reaches the launcher
    with the config and the extra arguments, and the rover's discovery left at ROS's default."""
    home = tmp_path / "opt"
    (home / "install").mkdir(parents=True)
    (home / "venv" / "bin").mkdir(parents=True)
    ros_setup = tmp_path / "setup.bash"
    ros_setup.write_text('if [ -n "$AMENT_TRACE_SETUP_FILES" ]; then echo trace; fi\n')
    (home / "install" / "setup.bash").write_text('if [ -n "$COLCON_TRACE" ]; then echo trace; fi\n')
    launcher = home / "venv" / "bin" / "rovercan"
    launcher.write_text('#!/usr/bin/env bash\necho "$ROS_AUTOMATIC_DISCOVERY_RANGE $*"\n')
    launcher.chmod(0o755)
    config = tmp_path / "rover.yaml"
    config.write_text("")
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_TRACE_SETUP_FILES", "COLCON_TRACE",
                                                             "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    env |= {"ROS_SETUP": str(ros_setup), "ROVERCAN_HOME": str(home), "ROVERCAN_CONFIG": str(config)}
    ran = subprocess.run([str(DEPLOY / "entrypoint.sh"), "arm:=true"], env=env, capture_output=True, text=True)
    assert ran.returncode == 0, ran.stderr
    assert ran.stdout.strip() == (f"SUBNET launch {home}/ros/rovercan_bringup/launch/rover_launch.xml"
                                  f" config:={config} arm:=true"), ran.stdout
    missing = subprocess.run([str(DEPLOY / "entrypoint.sh")], env=env | {"ROVERCAN_CONFIG": str(tmp_path / "no.yaml")},
                             capture_output=True, text=True)
    assert missing.returncode == 2 and "mount the rover config" in missing.stderr, missing


def test_the_unit_starts_the_image_after_can0_with_the_config_mounted() -> None:
    unit = ini(DEPLOY / "rovercan.service")
    for bus in load_config(REPO / "config" / "rover.yaml").buses:  # every bus of the rover, not can0 alone
        assert f"sys-subsystem-net-devices-{bus.channel}.device" in unit["Unit"]["Requires"].split()
        assert f"sys-subsystem-net-devices-{bus.channel}.device" in unit["Unit"]["After"].split()
    assert unit["Service"]["Restart"] == "always"  # a driver that ended (a link not up at boot) starts again
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


@pytest.mark.parametrize("channel", sorted({b.channel for b in load_config(REPO / "config" / "rover.yaml").buses}))
def test_the_boot_time_can_settings_are_the_ones_can_up_applies(channel: str) -> None:
    network = ini(DEPLOY / f"80-{channel}.network")
    link = ini(DEPLOY / f"80-{channel}.link")
    rover_bitrates = {b.bitrate for b in load_config(REPO / "config" / "rover.yaml").buses}
    assert rover_bitrates == {int(network["CAN"]["BitRate"])}
    ip = [" ".join(c) for c in can_up_commands(channel, int(network["CAN"]["BitRate"]), 100, 1000)]
    assert f"restart-ms {int(network['CAN']['RestartSec'].removesuffix('ms'))}" in ip[1]
    assert "berr-reporting on" in ip[1] and network["CAN"]["BusErrorReporting"] == "yes"
    assert f"txqueuelen {link['Link']['TransmitQueueLength']}" in ip[2]
    assert network["Match"]["Name"] == link["Match"]["OriginalName"] == channel
    modules = [m for m in (DEPLOY / "modules-load.conf").read_text().splitlines() if m and not m.startswith("#")]
    assert modules == ["can", "can_raw", "mttcan"]
