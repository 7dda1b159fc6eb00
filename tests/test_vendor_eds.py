"""Every CiA 402 EDS in ../shared/eds: a drive simulated from it boots, enables and moves
through the driver; the python-canopen sample (not a drive) is refused."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from can_config import EdsError, RoverConfig
from can_config.errors import CommandRejected
from motor_driver import MotorDriver, State
from virtual_can import SimService

from .conftest import SHARED_EDS, make_config, requires_shared, wait_for
from .test_host_loss import can_watch_host

DRIVES = sorted(p.name for p in SHARED_EDS.glob("*.eds") if p.name != "python_canopen_sample.eds") \
    if SHARED_EDS.is_dir() else []


@requires_shared
@pytest.mark.parametrize("eds", DRIVES)
def test_vendor_drive_boots_enables_moves(eds: str, driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    # a drive that cannot watch the host is armed here on the explicit override (test_host_loss
    # shows the refusal without it)
    # counts_per_rev: the simulated motor's encoder (most of these files have no 0x608F to say it)
    _, driver = driver_factory(make_config(1, eds=str(SHARED_EDS / eds), counts_per_rev=4096,
                                           allow_no_host_watch=not can_watch_host(SHARED_EDS / eds)))
    drive = driver.drive("joint1")
    drive.enable()
    assert drive.cache.state is State.OPERATION_ENABLED
    # a move acts on the state as read: it waits for the drive's first SYNC's TPDOs (the bus
    # daemon's SYNC timer starts in a process of its own, late on a loaded machine; a move before
    # them is refused, "no data for ever", as it should be)
    wait_for(lambda: drive.snapshot().verdict.usable, 10.0, "the drive's first whole data")
    if eds == "schunk_prl120.eds":
        # its 0x6502 = 0x60 lists only homing and interpolated position: profile position is
        # refused, clearly; it moves by streamed IP set-points (0x60C1:1 in its second RPDO)
        with pytest.raises(CommandRejected, match=r"PROFILE_POSITION is not supported by node 1 \(0x6502 = 0x00000060\)"):
            drive.move_to(30.0)
        assert [(i, s) for i, s, _ in driver.drive("joint1").plan.rpdos[1].objects] == [(0x6040, 0), (0x60C1, 1)]
        for i in range(1, 61):
            drive.stream_position(i * 0.5)
            time.sleep(0.01)
        wait_for(lambda: abs(drive.snapshot().angle_deg - 30.0) < 0.2, 2.0, "IP to 30 deg")
        assert drive.snapshot().mode == 7 and drive.cache.received.statusword & 0x1000  # ip mode active
        with pytest.raises(CommandRejected, match=r"this drive has no homing mode \(no 0x6098 in its EDS\)"):
            drive.home()
        return
    drive.move_to(30.0, wait=True)
    # "target reached" holds within the position window (2 counts = 0.18 deg at 4096 counts/rev)
    assert drive.snapshot().angle_deg == pytest.approx(30.0, abs=0.2)


@requires_shared
def test_sample_eds_refused() -> None:
    with pytest.raises(EdsError, match=r"python_canopen_sample\.eds: not a usable CiA 402 drive"):
        MotorDriver(make_config(1, eds=str(SHARED_EDS / "python_canopen_sample.eds")))


@requires_shared
def test_epos4_velocity_in_rpm_is_converted(driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    # EPOS4 reports velocity in rpm (0x60A9); 90 deg/s at the joint with gear 4 is 60 rpm at the motor
    sim, driver = driver_factory(make_config(1, eds=str(SHARED_EDS / "maxon_epos4_module50_5.eds"), gear_ratio=4.0,
                                             counts_per_rev=4096))  # the EPOS4 has no 0x608F to say it
    drive = driver.drive("joint1")
    drive.enable()
    for _ in range(60):
        drive.set_velocity(90.0)
        time.sleep(0.02)
    velocity = drive.snapshot().velocity_deg_s
    # whole rpm at the motor are 1.5 deg/s at the joint: the factor is exact, and the simulated
    # servo is within one rpm of 60 (its speed ripples by a count under load)
    assert velocity / 1.5 == pytest.approx(round(velocity / 1.5), abs=1e-9)
    assert abs(velocity - 90.0) <= 1.5 + 1e-9
    rpm = sim.simulator_for(1).call(lambda: sim.simulator_for(1).drive(1).store.get(0x606C, 0))
    assert rpm == pytest.approx(60, abs=1)
