"""A statusword that flickers through FAULT (a hostile or broken drive, a spoofed TPDO) stops
motion: once the driver has seen FAULT since the drive was enabled, every motion command is
refused, even when the next sample says Operation Enabled again, until recover() and enable().
So no motion frame goes out between a FAULT sample and the next good one."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from can_config.errors import DriveStateError
from motor_driver import MotorDriver, State
from motor_driver.drive import Drive
from virtual_can import SimService

from .conftest import drain, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
FAULT_SW = 0x0008


def spoofed_fault(driver: MotorDriver) -> can.Message:
    """TPDO of node 1 that carries the statusword, every field 0 but the statusword FAULT."""
    drive = driver.drive("joint1")
    cob, layout = next((p.cob_id, p) for p in drive.plan.tpdos if 0x6041 in p.indexes)
    values = [FAULT_SW if index == 0x6041 else 0 for index in layout.indexes]
    return can.Message(arbitration_id=cob, data=layout.codec.pack(*values), is_extended_id=False)


Moving = tuple[Drive, can.BusABC, can.Message]


@pytest.fixture
def moving(driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC]) -> Moving:
    """joint1 enabled and turning at 10 deg/s, a second client on its bus (the spoofer), and the
    spoofed FAULT TPDO of it."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(10.0)
    return drive, listener_factory(sim), spoofed_fault(driver)


def test_one_fault_sample_stops_motion_until_recover_and_enable(moving: Moving) -> None:
    drive, spoofer, fault = moving
    spoofer.send(fault)
    wait_for(lambda: drive.cache.fault_seen is not None, 2.0, "the FAULT sample taken")
    wait_for(lambda: drive.cache.state is State.OPERATION_ENABLED, 2.0, "the drive's own next TPDO")
    drain(spoofer, 0.05)
    with pytest.raises(DriveStateError, match=r"reported FAULT \(statusword 0x0008\).*recover\(\) and enable\(\)"):
        drive.set_velocity(30.0)
    rpdo_ids = {0x200 + 1, 0x300 + 1, 0x400 + 1, 0x500 + 1}
    assert not [m for m in drain(spoofer, 0.2) if m.arbitration_id in rpdo_ids], "an RPDO went out after the refusal"
    drive.recover()
    drive.enable()
    drive.set_velocity(30.0)  # asked again: moves again


def test_a_statusword_flipping_every_5_ms_lets_no_velocity_command_through(moving: Moving) -> None:
    drive, spoofer, fault = moving
    stop = threading.Event()

    def flip() -> None:
        while not stop.is_set():
            spoofer.send(fault)  # the simulated drive's own TPDOs say Operation Enabled between
            time.sleep(0.005)

    flipper = threading.Thread(target=flip, daemon=True)
    flipper.start()
    try:
        wait_for(lambda: drive.cache.fault_seen is not None, 2.0, "the first FAULT sample")
        accepted = 0
        for i in range(200):
            try:
                drive.set_velocity(10.0 + i % 5)
                accepted += 1
            except DriveStateError:
                pass
            time.sleep(0.002)
        assert accepted == 0
    finally:
        stop.set()
        flipper.join(timeout=2.0)
