"""Config reading is bounded: what is not a config file (a FIFO, a device, a directory, a huge
file, a symlink loop, YAML nested past reason or containing itself) is refused with one line
naming the file, fast, and never blocks, exhausts memory or raises outside the project's tree."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from can_config import load_config, load_od
from can_config.errors import ConfigError, EdsError
from can_config.textfile import TEXT_MAX_BYTES, YAML_MAX_DEPTH
from virtual_can.scenario import load_scenario

from .conftest import REPO, guarded_generic_eds

BUS = "buses: [{name: can0, interface: socketcand, channel: can0}]\n"


def refused(path: Path, *words: str) -> str:
    with pytest.raises(ConfigError) as err:
        load_config(path)
    text = str(err.value)
    assert str(path) in text or path.name in text, text
    for word in words:
        assert word in text, text
    return text


def test_a_fifo_is_refused_not_waited_on(tmp_path: Path) -> None:
    fifo = tmp_path / "rover.yaml"
    os.mkfifo(fifo)
    started = time.monotonic()
    refused(fifo, "a FIFO, not a regular file")
    assert time.monotonic() - started < 1.0


def test_the_cli_refuses_a_fifo_in_one_line(tmp_path: Path) -> None:
    fifo = tmp_path / "rover.yaml"
    os.mkfifo(fifo)
    run = subprocess.run([sys.executable, "-m", "rovercan", "plan", "--config", str(fifo)], capture_output=True,
                         text=True, timeout=60, cwd=REPO)
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and "FIFO" in run.stderr, run.stderr


def test_a_device_is_refused(tmp_path: Path) -> None:
    refused(Path("/dev/zero"), "a device or socket")


def test_a_directory_is_refused(tmp_path: Path) -> None:
    refused(tmp_path, "a directory")


def test_an_oversized_config_is_refused_before_it_is_read(tmp_path: Path) -> None:
    big = tmp_path / "rover.yaml"
    big.write_text(BUS + "# " + "x" * TEXT_MAX_BYTES + "\n")
    started = time.monotonic()
    refused(big, f"over the {TEXT_MAX_BYTES:,}")
    assert time.monotonic() - started < 1.0


def test_a_symlink_loop_as_the_config_is_named(tmp_path: Path) -> None:
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.symlink_to(b)
    b.symlink_to(a)
    refused(a, "symlinks")


def test_a_symlink_loop_as_an_eds_is_named(tmp_path: Path) -> None:
    a, b = tmp_path / "a.eds", tmp_path / "b.eds"
    a.symlink_to(b)
    b.symlink_to(a)
    config = tmp_path / "rover.yaml"
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096, eds: a.eds}]\n")
    with pytest.raises(ConfigError, match=r"a\.eds.*symlinks"):
        load_config(config)


def test_an_eds_that_is_a_fifo_or_a_loop_is_refused(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "drive.eds")
    with pytest.raises(EdsError, match=r"drive\.eds.*FIFO"):
        load_od(tmp_path / "drive.eds")
    (tmp_path / "a.eds").symlink_to(tmp_path / "a.eds")
    with pytest.raises(EdsError, match=r"a\.eds.*symlinks"):
        load_od(tmp_path / "a.eds")


@pytest.mark.parametrize("depth", [YAML_MAX_DEPTH + 1, 5000])
def test_deep_nesting_is_named(tmp_path: Path, depth: int) -> None:
    deep = tmp_path / "rover.yaml"
    deep.write_text(BUS + "drives: " + "[" * depth + "]" * depth + "\n")
    refused(deep, "nests")


def test_a_list_containing_itself_is_refused_not_walked_for_ever(tmp_path: Path) -> None:
    loop = tmp_path / "rover.yaml"
    loop.write_text(BUS + "drives: &d [*d]\n")
    refused(loop, "recursive")


def test_a_scenario_has_the_same_bounds(tmp_path: Path) -> None:
    fifo = tmp_path / "scenario.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="FIFO"):
        load_scenario(fifo)
    deep = tmp_path / "deep.yaml"
    deep.write_text("steps: " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(ConfigError, match="nests"):
        load_scenario(deep)


def check(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", "check", *args], capture_output=True, text=True,
                          timeout=60, cwd=REPO)


@pytest.mark.parametrize("config", ["config/rover.yaml", "can_config/data/default.yaml"])
def test_check_passes_the_shipped_configs(config: str) -> None:
    run = check("--config", config, "--json")
    assert run.returncode == 0, run.stderr
    assert "heartbeat consumer" in run.stdout and "planned load" in run.stdout


def test_check_names_a_missing_eds_and_an_unknown_wheel(tmp_path: Path) -> None:
    config = tmp_path / "rover.yaml"
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096, eds: nowhere.eds}]\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and "nowhere.eds" in run.stderr and run.stderr.count("\n") == 1, run.stderr
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096}]\n"
                      "drive_system: {left: [m], right: [x], track_width_m: 0.5, wheel_radius_m: 0.1,"
                      " max_speed_m_s: 1.0}\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and "'x'" in run.stderr, run.stderr


@pytest.mark.parametrize(("left", "right", "said"), [("[m, n]", "[m]", "drive_system.right: names 'm', also on the left"),
                                                     ("[m, m]", "[n]", "drive_system.left: names 'm' more than once"),
                                                     ("[m]", "[n, n]", "drive_system.right: names 'n' more than once")])
def test_check_refuses_a_wheel_on_both_sides_or_twice(tmp_path: Path, left: str, right: str, said: str) -> None:
    """A wheel on both sides was told the left and the right speed every tick (opposite in a
    spin) and counted on both sides by the odometry; one named twice, its speed sent twice and
    its travel counted twice (an independent review's finding)."""
    config = tmp_path / "rover.yaml"
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096}, {name: n, node_id: 2,"
                      " counts_per_rev: 4096}]\n"
                      f"drive_system: {{left: {left}, right: {right}, track_width_m: 0.5, wheel_radius_m: 0.1,"
                      " max_speed_m_s: 1.0}\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and said in run.stderr and run.stderr.count("\n") == 1, run.stderr


def test_a_host_timeout_is_judged_in_the_whole_milliseconds_the_drive_holds(tmp_path: Path) -> None:
    """host_timeout_ms 50.4 beside the default 50 ms host heartbeat passed as longer, and the drive
    held 50 ms (0x1016 keeps whole milliseconds): it stopped at any jitter (a review's finding)."""
    config = tmp_path / "rover.yaml"
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096, host_timeout_ms: 50.4}]\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and "host_timeout_ms: got 50.4, which the drive holds as 50 ms" in run.stderr, run.stderr
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096, host_timeout_ms: 51}]\n")
    assert check("--config", str(config)).returncode == 0


def test_check_says_what_the_boot_would_refuse(tmp_path: Path) -> None:
    """``rovercan check`` said "valid" for an ``sdo:`` entry on an object the driver owns (the boot
    refused it, exit 1), took a channel given in a bus's kwargs (it replaced the bus's channel,
    past the check of two buses on one channel), and called a guarded drive on socketcand "node
    guarding" where the driver arms nothing (a review's findings)."""
    config = tmp_path / "rover.yaml"
    config.write_text(BUS + "drives: [{name: m, node_id: 1, counts_per_rev: 4096, sdo: [{index: 0x6040, value: 15}]}]\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and "sdo entry 0x6040:0 is the driver's own" in run.stderr, run.stderr
    config.write_text("buses: [{name: can0, interface: socketcand, channel: can0, kwargs: {channel: can1}}]\n"
                      "drives: [{name: m, node_id: 1, counts_per_rev: 4096}]\n")
    run = check("--config", str(config))
    assert run.returncode == 2 and "buses[0].kwargs: sets channel, which are the bus's own keys" in run.stderr, run.stderr
    eds = guarded_generic_eds(tmp_path / "guarded.eds")
    for interface, says in (("socketcand", "NONE: node guarding needs remote frames"),
                            ("virtual", "node guarding (0x100C/0x100D)")):
        config.write_text(f"buses: [{{name: can0, interface: {interface}, channel: can0}}]\n"
                          f"drives: [{{name: m, node_id: 1, counts_per_rev: 4096, eds: {eds}}}]\n")
        run = check("--config", str(config), "--json")
        assert run.returncode == 0 and says in json.loads(run.stdout)[0]["host watch"], run.stdout + run.stderr
