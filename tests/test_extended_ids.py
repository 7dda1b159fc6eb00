"""CANopen (CiA 301) uses 11-bit identifiers only: spoofed 29-bit frames whose low bits look
like a drive's PDOs, NMT or SDO change nothing in the driver or the simulated drives."""

from __future__ import annotations

import time
from collections.abc import Callable

import can

from can_config import RoverConfig
from motor_driver import MotorDriver, State
from virtual_can import SimService

from .conftest import make_config

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def extended(cob: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=True)


def test_spoofed_extended_frames_change_no_state(driver_factory: DriverFactory,
                                                 listener_factory: Callable[[SimService], can.BusABC]) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    runner = sim.simulators["can0"]
    sim_drive = runner.drive(1)
    assert drive.cache.state is State.SWITCH_ON_DISABLED
    sdo = runner.call(lambda: sim_drive.counters["sdo"])
    spoofer = listener_factory(sim)
    seen: list[State] = []
    for _ in range(50):  # statusword 0x0627 "Operation Enabled" on the drive's TPDO ids, extended
        for cob in (0x181, 0x381):
            spoofer.send(extended(cob, b"\x27\x06\x00\x00\x00\x00\x00\x00"))
        seen.append(drive.cache.state)
        time.sleep(0.002)
    spoofer.send(extended(0x000, b"\x81\x00"))  # "reset every node", extended
    spoofer.send(extended(0x601, bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0])))  # an SDO upload, extended
    spoofer.send(extended(0x201, b"\x0f\x00"))  # "enable operation" on RPDO1's id, extended
    # the driver's own SDO read, standard: the drive answers it after it handled every spoof, and the
    # driver's receive thread takes the answer after the spoofs (one bus, one order); the listener
    # hears all the drive said up to that answer
    assert drive.sdo_read(0x1000, 0)
    heard: list[can.Message] = []
    while (msg := spoofer.recv(10.0)) is not None and not (msg.arbitration_id == 0x581 and not msg.is_extended_id):
        heard.append(msg)
    assert msg is not None, "the drive's answer to the driver's SDO read never reached the listener"
    answers = [m for m in heard if m.arbitration_id in (0x581, 0x701) and not m.is_extended_id]
    assert all(state is State.SWITCH_ON_DISABLED for state in seen) and drive.cache.state is State.SWITCH_ON_DISABLED
    assert runner.call(lambda: sim_drive.state.name) == "SWITCH_ON_DISABLED"
    assert runner.call(lambda: sim_drive.counters["sdo"]) == sdo + 1  # no SDO request taken but the driver's read
    assert not [m for m in answers if m.arbitration_id == 0x581]
    assert not [m for m in answers if m.arbitration_id == 0x701 and m.data[:1] == b"\x00"]  # no boot-up: no reset
    assert drive.cache.booted and not drive.watch.foreign_master
