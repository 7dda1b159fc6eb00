"""An operation waiting on a drive ends, with the reason, as soon as the drive stops by itself
(issue 52: a home waited 27 s for a drive whose host watch had stopped it 3 s in, then said
"homing not attained within 30 s").

The drive is made to stop itself the way a stalled host makes it: it stops hearing the driver's
heartbeat (the simulator's ``heartbeat_deaf`` fault), its consumer trips, it quick-stops and
sends EMCY 0x8130. The verdict is the reason named, and that the home ended long before its own
timeout (a bound on the homing, not a stopwatch: the homing would run for minutes)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from can_config.errors import DriveStateError, DriveTimeoutError, RovercanError
from motor_driver import Drive, MotorDriver
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import in_thread, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
#: a homing that searches its index (at 0, the drives start 20 deg away) at 1 deg/s: 20 s; its timeout is 600
SLOW_HOMING = {"homing_method": 1, "homing_speed_deg_s": 1.0, "homing_timeout_s": 600.0}


def test_a_home_ends_when_the_drives_host_watch_stops_it(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1, **SLOW_HOMING))
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(20.0, wait=True)
    started = threading.Event()
    outcome: list[BaseException | None] = []

    def on_point(point: str) -> None:
        if point == "home: start sent":
            started.set()

    def home() -> None:
        try:
            drive.home()
            outcome.append(None)
        except RovercanError as err:
            outcome.append(err)

    drive.channel.set_hook(on_point)
    worker = threading.Thread(target=home, name="test-home")
    worker.start()
    assert started.wait(30.0)
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})
    worker.join(60.0)  # a bound for a hang: homing itself would need 20 s, its timeout is 600 s
    drive.channel.set_hook(None)
    assert not worker.is_alive(), "home() still waits for a drive that stopped itself"
    assert len(outcome) == 1 and isinstance(outcome[0], DriveStateError), outcome
    text = str(outcome[0])
    assert "homing ended" in text and "EMCY 0x8130" in text and "left Operation Enabled" in text, text
    assert not sim.simulator_for(1).drive(1).homing_done


def test_a_drive_that_resets_during_homing_ends_it(driver_factory: DriverFactory) -> None:
    """A drive that power-cycles mid-homing (boot-up, then configured again by the driver, left
    disabled) ends the home at once, naming the state it is in now."""
    sim, driver = driver_factory(make_config(1, **SLOW_HOMING))
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(20.0, wait=True)
    started = threading.Event()
    drive.channel.set_hook(lambda point: started.set() if point == "home: start sent" else None)
    worker, errors = in_thread(drive.home, RovercanError, name="test-home")
    assert started.wait(30.0)
    # homing under way (the drive left 20 deg): its statusword read after the start has been answered
    wait_for(lambda: drive.snapshot().angle_deg < 19.5, 30.0, "homing under way")
    apply_action(sim, {"action": "power_cycle", "node": 1, "off_s": 0.2})
    worker.join(60.0)
    drive.channel.set_hook(None)
    assert not worker.is_alive()
    assert errors and isinstance(errors[0], DriveStateError)
    text = str(errors[0])
    assert "homing ended" in text and ("NMT" in text or "left Operation Enabled" in text), text


def test_a_drive_that_keeps_operation_enabled_homes_as_before(driver_factory: DriverFactory) -> None:
    """The new check does not end a homing that goes well (the check before it, a mutant that
    always ends, fails here)."""
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(10.0, wait=True)
    drive.home()
    assert abs(drive.snapshot().angle_deg) < 0.05


def _waited_move(drive: Drive) -> tuple[threading.Thread, list[BaseException]]:
    return in_thread(lambda: drive.move_to(170.0, wait=True), RovercanError, name="test-move")


def test_a_waited_move_ends_when_the_drive_stops_itself_and_names_why(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1, profile_velocity_deg_s=5.0))  # 170 deg at 5 deg/s: 34 s
    drive = driver.drive("joint1")
    drive.enable()
    worker, errors = _waited_move(drive)
    wait_for(lambda: drive.snapshot().angle_deg > 0.5, 30.0, "the move under way")
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})
    worker.join(60.0)
    assert not worker.is_alive()
    assert errors and "the move ended" in str(errors[0]) and "0x8130" in str(errors[0]), errors


def test_a_waited_move_ended_by_our_own_stop_says_so(driver_factory: DriverFactory) -> None:
    """Our quick stop is not "the drive stopped by itself": the channel's stop is named."""
    _, driver = driver_factory(make_config(1, profile_velocity_deg_s=5.0))
    drive = driver.drive("joint1")
    drive.enable()
    worker, errors = _waited_move(drive)
    wait_for(lambda: drive.snapshot().angle_deg > 0.5, 30.0, "the move under way")
    drive.quick_stop()
    worker.join(60.0)
    assert not worker.is_alive()
    assert errors and "interrupted by quick stop" in str(errors[0]), errors


def test_an_enable_after_the_drive_stopped_itself_unseen_really_enables_it(driver_factory: DriverFactory) -> None:
    """A stalled host's cache still says Operation Enabled while the drive has stopped itself (its
    host watch): here its TPDOs are held back meanwhile, so the driver cannot see the stop. An
    enable judged by the cache returned at once ("armed") and left the drive disabled; the drive's
    state is asked by SDO first, and the enable walks it back to Operation Enabled."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    runner = sim.simulator_for(1)
    # its heartbeat consumer is armed by the first host heartbeat it hears after 0x1016 was written
    wait_for(lambda: bool(runner.call(lambda: dict(runner.drive(1)._consumer_seen))), 30.0, "its host watch armed")
    apply_action(sim, {"action": "tpdos", "node": 1, "on": False})  # the driver hears no statusword now
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1})  # its host watch trips: it stops itself
    wait_for(lambda: runner.call(lambda: runner.drive(1).state.name) != "OPERATION_ENABLED", 30.0,
             "the drive stopped by itself")
    apply_action(sim, {"action": "heartbeat_deaf", "node": 1, "on": False})
    assert drive.cache.state.name == "OPERATION_ENABLED"  # what the driver still believes
    drive.channel.set_hook(lambda point: apply_action(sim, {"action": "tpdos", "node": 1, "on": True})
                           if point.startswith("enable: before transition") else None)
    try:
        drive.enable()
    finally:
        drive.channel.set_hook(None)
        apply_action(sim, {"action": "tpdos", "node": 1, "on": True})
    assert runner.call(lambda: runner.drive(1).state.name) == "OPERATION_ENABLED"


def test_a_heartbeat_sent_before_the_drive_obeyed_nmt_start_ends_no_move(
        driver_factory: DriverFactory, listener_factory: Callable[[SimService], can.BusABC]) -> None:
    """A PRE-OPERATIONAL heartbeat on its way when the NMT start went out, read after it by a
    starved process, stays the drive's NMT state until its next heartbeat (the kernel tier: "the
    move ended: the drive went NMT PRE_OPERATIONAL"). Its PDOs still come, which a drive sends only
    when OPERATIONAL: the move goes on. Staged with a 2 s heartbeat, the stale one sent just after
    the boot; fails on a power.py that takes the heartbeat alone."""
    sim, driver = driver_factory(make_config(1, heartbeat_period_ms=2000, heartbeat_timeout_ms=6000))
    injector = listener_factory(sim)
    heard = threading.Event()
    driver.buses["can0"].network.subscribe(0x701, lambda _cob, data, _t: heard.set() if data[0] == 0x7F else None)
    injector.send(can.Message(arbitration_id=0x701, data=b"\x7f", is_extended_id=False))
    wait_for(heard.is_set, 10.0, "the stale heartbeat taken by the driver")
    drive = driver.drive("joint1")
    assert drive.cache.nmt_state == "PRE_OPERATIONAL"  # what the heartbeat said, until the next one
    drive.enable()
    drive.move_to(10.0, wait=True, timeout_s=30.0)
    assert abs(drive.snapshot().angle_deg - 10.0) < 0.5


def test_a_homing_that_times_out_is_quick_stopped_not_left_searching(driver_factory: DriverFactory) -> None:
    """A homing past its timeout is still searching (its index 20 deg away at 1 deg/s, a 1 s
    timeout): the timeout quick-stops the drive and says so; the drive is not left turning."""
    sim, driver = driver_factory(make_config(1, **SLOW_HOMING))
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(20.0, wait=True)
    with pytest.raises(DriveTimeoutError, match=r"homing not attained within 1 s[^;]*; the drive was quick-stopped"):
        drive.home(timeout_s=1.0)
    peer = sim.simulator_for(1)
    state = peer.call(lambda: peer.drive(1).state.name)
    assert state in ("QUICK_STOP_ACTIVE", "SWITCH_ON_DISABLED"), state
    wait_for(lambda: abs(peer.call(lambda: peer.drive(1).omega)) < 1e-3, 30.0, "the shaft still")  # type: ignore[arg-type]
    assert not peer.call(lambda: peer.drive(1).homing_done)
