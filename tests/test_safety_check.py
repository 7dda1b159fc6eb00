"""``rovercan safety-check`` reads back, from the bus, what stops each drive when the host is
gone, and the driver runs the same checks after every boot (for /diagnostics)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from can_config import load_config
from motor_driver import MotorDriver, State
from motor_driver.diagnostics.health import ERROR, WARN, drive_health
from motor_driver.protocol.safety import FAIL, PASS
from virtual_can import SimService

from .conftest import REPO, make_config, wait_for
from .drive_states import stale

ROVER = """buses:
  - {{name: can0, interface: socketcand, channel: can0, kwargs: {{host: 127.0.0.1, port: {port}}}}}
drives:
  - {{name: wheel, node_id: 1, gear_ratio: 50, counts_per_rev: 4096}}
  - {{name: arm, node_id: 2, joint: limited, min_deg: -45, max_deg: 120, invert: true, offset_deg: 5,
     gear_ratio: 10, counts_per_rev: 4096, on_host_loss: disable}}
"""


@pytest.fixture
def rover(tmp_path: Path) -> Iterator[tuple[SimService, MotorDriver, Path]]:
    path = tmp_path / "rover.yaml"
    path.write_text(ROVER.format(port=1))
    with SimService.from_config(load_config(path), port=0) as sim:
        path.write_text(ROVER.format(port=sim.port))
        with MotorDriver(load_config(path)).start() as driver:
            yield sim, driver, path


def safety_check(path: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", "safety-check", "--config", str(path), "--json", *extra],
                          cwd=REPO, capture_output=True, text=True, timeout=60)


def test_a_correctly_booted_rover_passes(rover: tuple[SimService, MotorDriver, Path]) -> None:
    _, driver, path = rover
    result = safety_check(path)
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)
    by = {(r["drive"], r["check"]): r for r in rows}
    assert by[("(host)", "host heartbeat on the bus")]["status"] == PASS
    assert by[("wheel", "host watch")]["actual"] == "0x1016:1 = node 127, 150 ms"
    assert by[("arm", "reaction to host loss")]["actual"] == "2"  # disable voltage, as configured
    assert by[("arm", "software limits")]["status"] == PASS
    assert by[("wheel", "software limits")]["status"] == "n/a"
    assert all(r["status"] in (PASS, "n/a") for r in rows), rows
    # the driver's own read-back after boot agrees
    assert all(not c.failed for d in driver for c in d.boot.safety)


def test_a_cleared_consumer_heartbeat_fails_naming_the_object(rover: tuple[SimService, MotorDriver, Path]) -> None:
    _, driver, path = rover
    driver.drive("arm").sdo_write(0x1016, 1, (0).to_bytes(4, "little"))  # behind the driver's back
    result = safety_check(path)
    assert result.returncode == 1
    # the failures are listed in one line; the host's own heartbeat may fail beside it when this
    # process (the driver's host) was starved for two of its periods: a judgement of its own
    assert "safety check failed:" in result.stderr and "arm host watch (0x1016)" in result.stderr
    row = next(r for r in json.loads(result.stdout) if r["drive"] == "arm" and r["check"] == "host watch")
    assert row["status"] == FAIL and row["expected"] == "node 127, 150 ms"


def test_no_host_heartbeat_on_the_bus_fails(tmp_path: Path) -> None:
    path = tmp_path / "rover.yaml"
    path.write_text(ROVER.format(port=1))
    with SimService.from_config(load_config(path), port=0) as sim:
        path.write_text(ROVER.format(port=sim.port))
        result = safety_check(path)  # nothing booted the drives: no watch, no driver
    assert result.returncode == 1
    assert "(host) host heartbeat on the bus (0x77F)" in result.stderr and "wheel host watch (0x1016)" in result.stderr


def test_a_failed_check_is_an_error_in_diagnostics(driver_factory: object) -> None:
    _, driver = driver_factory(make_config(1))  # type: ignore[operator]
    drive = driver.drive("joint1")
    wait_for(lambda: not stale(drive.snapshot()), 1.0, "the first PDOs")
    assert drive.boot.safety and all(c.status in (PASS, "n/a") for c in drive.boot.safety)
    health = drive_health(drive.snapshot(), heartbeat_period_s=0.1, safety=drive.boot.safety)
    assert health.level == 0, health.message
    broken = tuple(c if c.check != "host watch" else type(c)(c.check, c.object, c.expected, "no entry", FAIL)
                   for c in drive.boot.safety)
    health = drive_health(drive.snapshot(), heartbeat_period_s=0.1, safety=broken)
    assert health.level == ERROR and "safety check failed: host watch (0x1016 is no entry" in health.message


def test_a_drive_allowed_without_host_watch_warns_in_diagnostics(driver_factory: object) -> None:
    from .test_host_loss import BLIND_EDS

    if not BLIND_EDS:
        pytest.skip("../shared/eds is absent (only the team's checkout has it)")
    _, driver = driver_factory(make_config(1, eds=str(BLIND_EDS[0]), allow_no_host_watch=True))  # type: ignore[operator]
    drive = driver.drive("joint1")
    drive.enable()
    assert drive.cache.state is State.OPERATION_ENABLED
    health = drive_health(drive.snapshot(), heartbeat_period_s=0.1, safety=drive.boot.safety)
    assert health.level == WARN and "NO drive-side stop on host loss" in health.message
