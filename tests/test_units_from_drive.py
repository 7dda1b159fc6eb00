"""Units and identity come from the drive, never from a default that happens to fit the
simulator: the unit objects are read by SDO whatever the EDS lists, motion without a known
position resolution is refused, and a drive of another vendor than its EDS fails at boot."""

from __future__ import annotations

import json
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable

from can_config import RoverConfig, with_bus_overrides
from can_config.config import GENERIC_EDS
from can_config.errors import BootError, CommandRejected
from can_config.objects import DataType
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import SHARED_EDS, heard_before_marker, make_config, requires_shared, rovercan_cli, wait_for

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]
EPOS4 = SHARED_EDS / "maxon_epos4_module50_5.eds"
RPM = 0x00B44700  # 0x60A9: 10^0 revolutions per minute (CiA 402 SI unit code)


def crafted_eds(path: Path, *, drop: tuple[int, ...] = (), vendor: int | None = None,
                velocity_unit: int | None = None) -> Path:
    """The generic EDS changed: objects dropped, another vendor, an SI velocity unit added."""
    od = canopen.import_od(str(GENERIC_EDS), 1)
    for index in drop:
        del od[index]
    if vendor is not None:
        od.device_information.vendor_number = vendor
        od.device_information.vendor_name = "another vendor"
        od[0x1018][1].default, od[0x1018][1].default_raw = vendor, str(vendor)
    if velocity_unit is not None:
        unit = ODVariable("SI unit velocity", 0x60A9, 0)
        unit.data_type, unit.access_type = DataType.UNSIGNED32, "rw"
        unit.default, unit.default_raw = velocity_unit, str(velocity_unit)
        od.add_object(unit)
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def rovercan(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return rovercan_cli(*args, timeout=timeout)


def bus_args(sim: SimService) -> list[str]:
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={sim.port}"]


def jog_while_watching(sim: SimService, *args: str) -> tuple[subprocess.CompletedProcess[str], int, int]:
    """`rovercan jog ARGS` against the simulator; the fastest 0x606C the drive itself showed, and
    its position (0x6064) afterwards, both in the drive's own units."""
    drive = sim.simulator_for(1).drive(1)
    peak = [0]
    done = threading.Event()

    def watch() -> None:
        while not done.wait(0.01):
            value = int(sim.simulator_for(1).call(lambda: drive.store.get(0x606C, 0)))  # type: ignore[call-overload]
            peak[0] = max(peak[0], abs(value))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        result = rovercan("jog", *args, *bus_args(sim), "--json")
    finally:
        done.set()
        watcher.join()
    position = int(sim.simulator_for(1).call(lambda: drive.store.get(0x6064, 0)))  # type: ignore[call-overload]
    return result, peak[0], position


def check_jog_in_rpm(sim: SimService) -> None:
    result, rpm, counts = jog_while_watching(sim, "1", "90", "--for", "1", "--counts-per-rev", "4096")
    assert result.returncode == 0, result.stderr
    assert rpm == pytest.approx(15, abs=1), rpm  # 90 deg/s is 15 rpm, in the drive's own unit
    reported = json.loads(result.stdout)["angle_deg"]
    true_angle = counts / 4096 * 360.0
    # the report is taken at the end of the hold; the drive goes on after it (its braking, and as far
    # as a busy machine holds the command meanwhile: 23 deg seen), never back. A position read in
    # the wrong unit would be off by a factor (2x for 2048 counts), never within half to 1x
    assert true_angle > 10.0 and true_angle / 2 < reported <= true_angle + 0.5, (reported, true_angle)
    assert "counts_per_rev looks wrong" not in result.stderr


def test_a_velocity_unit_the_eds_does_not_list_is_read_from_the_drive(tmp_path: Path) -> None:
    """The simulated drive works in rpm (0x60A9); the driver is given the generic EDS, which has
    no 0x60A9: it reads the unit from the drive anyway (the EPOS4 case, without its file)."""
    eds = crafted_eds(tmp_path / "rpm.eds", velocity_unit=RPM, drop=(0x608F,))
    from virtual_can.service import specs_for_count
    with SimService(specs_for_count(1, eds, "can0"), port=0) as sim:
        check_jog_in_rpm(sim)


@requires_shared
def test_jog_without_eds_turns_a_simulated_epos4_at_the_commanded_speed() -> None:
    from virtual_can.service import specs_for_count
    with SimService(specs_for_count(1, EPOS4, "can0"), port=0) as sim:
        check_jog_in_rpm(sim)


def test_motion_without_a_known_resolution_is_refused_naming_counts_per_rev(sim_factory: SimFactory,
                                                                           tmp_path: Path) -> None:
    eds = crafted_eds(tmp_path / "no608f.eds", drop=(0x608F,))
    sim, cfg = sim_factory(make_config(1, eds=str(eds)))
    with MotorDriver(cfg) as driver:
        driver.start()
        drive = driver.drive("joint1")
        drive.enable()  # holding still is not motion
        for command in (lambda: drive.move_to(10.0), lambda: drive.set_velocity(10.0),
                        lambda: drive.set_torque(0.1), lambda: drive.stream_position(1.0),
                        lambda: drive.stream_velocity(1.0), lambda: drive.motion.set_profile_velocity(10.0),
                        drive.home):
            with pytest.raises(CommandRejected, match=r"position resolution is unknown.*Set counts_per_rev"):
                command()
        assert drive.snapshot().velocity_deg_s == 0.0
        truth = sim.simulator_for(1).call(lambda: sim.simulator_for(1).drive(1).store.get(0x6064, 0))
        assert truth == 0  # nothing moved
    # the CLI says the same, exit 2 (refused before anything was sent)
    refused = rovercan("move", "1", "45", "--eds", str(eds), *bus_args(sim))
    assert refused.returncode == 2 and "counts_per_rev" in refused.stderr and "--counts-per-rev" in refused.stderr
    moved = rovercan("move", "1", "45", "--eds", str(eds), "--counts-per-rev", "4096", *bus_args(sim), "--json")
    assert moved.returncode == 0 and json.loads(moved.stdout)["angle_deg"] == pytest.approx(45.0, abs=0.2), moved.stderr


def test_a_drive_with_its_units_reports_them_at_info_once_not_as_warnings(
        sim_factory: SimFactory, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    eds = crafted_eds(tmp_path / "rpm.eds", velocity_unit=RPM)
    _, cfg = sim_factory(make_config(1, eds=str(eds)))
    caplog.set_level("DEBUG", logger="motor_driver.drive")
    with MotorDriver(cfg) as driver:
        driver.start()
        driver.drive("joint1").boot.boot(reset=True)  # a second boot
    notes = [r for r in caplog.records if "(0x60A9)" in r.getMessage()]
    assert [r.levelname for r in notes] == ["INFO", "DEBUG"], [(r.levelname, r.getMessage()) for r in notes]


def test_an_eds_of_another_vendor_fails_at_boot_naming_both_ids(sim_factory: SimFactory, tmp_path: Path,
                                                                listener_factory: Callable[[SimService], can.BusABC]
                                                                ) -> None:
    sim, _ = sim_factory(make_config(1))  # the drive on the bus: the generic one (vendor 0x00524F56)
    eds = crafted_eds(tmp_path / "other.eds", vendor=0x000001A3)  # the config's EDS: another vendor's
    cfg = with_bus_overrides(make_config(1, eds=str(eds)), host=sim.host, port=sim.port)
    listener = listener_factory(sim)
    with MotorDriver(cfg) as driver, pytest.raises(BootError) as err:
        driver.start()
    text = str(err.value)
    assert "identity mismatch: vendor id is 0x00524F56 on the device" in text and "0x000001A3" in text, text
    assert err.value.step == "identity"
    # the driver's connection closed (all it sent on the bus): what the listener heard before a marker
    wait_for(lambda: len(sim.server.clients) == 1, 10.0, "the driver's connection closed")
    requests = [bytes(m.data[:4]) for m in heard_before_marker(listener, sim.engine) if m.arbitration_id == 0x601]
    # before any other object is touched: only uploads of 0x1018:1 went to the drive
    assert requests and set(requests) == {bytes([0x40, 0x18, 0x10, 0x01])}, [r.hex() for r in requests]


@requires_shared
def test_a_config_naming_another_vendors_eds_than_the_simulated_epos4_fails_at_boot(sim_factory: SimFactory) -> None:
    from virtual_can.service import SimDriveSpec
    technosoft = SHARED_EDS / "technosoft_ipos_v1_04_via_ros2_canopen.eds"
    cfg = make_config(1, eds=str(technosoft), counts_per_rev=4096)
    expected = r"vendor id is 0x000000FB on the device, its EDS technosoft_ipos_v1_04_via_ros2_canopen.eds \(Technosoft\)"
    with SimService([SimDriveSpec(1, EPOS4, "can0", "joint1")], port=0) as sim:
        driver = MotorDriver(with_bus_overrides(cfg, host=sim.host, port=sim.port))
        with driver, pytest.raises(BootError, match=expected + r" names 0x000001A3"):
            driver.start()
