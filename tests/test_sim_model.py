"""The simulated drive's motor and load model, seen through the real driver on the bus:
torque follows inertia x acceleration plus friction, a stall saturates it at 0x6072 and ends
in a following-error fault (EMCY 0x8611), and the servo gains of the sim config shape the
step response that `rovercan step-test` reports."""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest
import yaml

from can_config import GENERIC_EDS, load_drive_od
from can_config.objects import OD, OperationMode
from motor_driver import MotorDriver
from motor_driver.drive import DriveState
from virtual_can.scenario import apply_action
from virtual_can.service import SimService
from virtual_can.sim import SimulatedDrive
from virtual_can.sim.drive import State as SimState

from .conftest import REPO, make_config, rovercan_sim, wait_for
from .drive_states import fault

DriverFactory = Callable[..., tuple[SimService, MotorDriver]]

GEAR = 50.0
ACCEL_DEG_S2 = 2000.0
CRUISE_DEG_S = 360.0
# the simulator's default wheel model (SimModelConfig), motor side
INERTIA_KG_M2 = 1e-4
COULOMB_NM = 0.03
VISCOUS_NM_S_RAD = 2e-5


def wheel_config(**drive: object) -> object:
    return make_config(1, gear_ratio=GEAR, counts_per_rev=4096, max_velocity_deg_s=720.0,
                       profile_velocity_deg_s=CRUISE_DEG_S, profile_acceleration_deg_s2=ACCEL_DEG_S2, **drive)


def record(drive: object, seconds: float) -> list[DriveState]:
    samples: list[DriveState] = []
    end = time.monotonic() + seconds
    last = 0.0
    while time.monotonic() < end:
        s = drive.snapshot()  # type: ignore[attr-defined]
        if s.stamp != last:  # one sample per TPDO set (one per SYNC)
            samples.append(s)
            last = s.stamp
        time.sleep(0.002)
    return samples


def test_torque_is_inertia_times_acceleration_plus_friction(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(wheel_config())
    drive = driver.drive("joint1")
    drive.enable()
    drive.move_to(170.0)
    samples = record(drive, 1.2)
    peak = max(range(len(samples)), key=lambda i: samples[i].velocity_deg_s)
    cruise = [s.torque_nm for s in samples if s.velocity_deg_s > 0.98 * CRUISE_DEG_S]
    # the middle of each ramp (the servo needs ~30 ms to settle on a new acceleration)
    ramp_up = [s.torque_nm for s in samples[:peak] if 0.3 * CRUISE_DEG_S < s.velocity_deg_s < 0.7 * CRUISE_DEG_S]
    ramp_down = [s.torque_nm for s in samples[peak:] if 0.3 * CRUISE_DEG_S < s.velocity_deg_s < 0.7 * CRUISE_DEG_S]
    assert len(cruise) >= 10 and len(ramp_up) >= 3 and len(ramp_down) >= 3, (len(cruise), ramp_up, ramp_down)
    inertia_joint = INERTIA_KG_M2 * GEAR**2
    expected = inertia_joint * math.radians(ACCEL_DEG_S2)  # 8.7 Nm at the joint
    friction = statistics.median(cruise)
    up, down = statistics.mean(ramp_up), statistics.mean(ramp_down)
    # same direction, same speeds: friction is the same on both ramps, so half the difference is
    # the torque that accelerates the inertia; each ramp on its own (minus friction) within 20 %
    assert (up - down) / 2 == pytest.approx(expected, rel=0.10)
    assert up - friction == pytest.approx(expected, rel=0.20)
    assert down - friction == pytest.approx(-expected, rel=0.20)
    # at constant speed: Coulomb plus viscous friction, through the gear
    omega_motor = math.radians(CRUISE_DEG_S * GEAR)
    assert friction == pytest.approx((COULOMB_NM + VISCOUS_NM_S_RAD * omega_motor) * GEAR, rel=0.15)


@pytest.mark.parametrize("tick_s", [0.002, 0.01, 0.02])
def test_a_late_simulator_tick_gives_the_same_ramp_torque(tick_s: float) -> None:
    """The simulator's thread runs late on a busy machine (ticks of 10-20 ms instead of 2): the
    profile's set-point must move on within the tick with its acceleration. Stepped once per
    tick, the servo saw a velocity step and then friction, and the torque a TPDO carries (the
    value at the tick's end) was friction alone: 0.030 Nm instead of 0.067 at 20 ms."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.store.values[(OD.MODES_OF_OPERATION_DISPLAY, 0)] = int(OperationMode.PROFILE_VELOCITY)
    drive.store.values[(OD.PROFILE_ACCELERATION, 0)] = 200_000  # counts/s^2 (4096 per motor turn)
    drive.store.values[(OD.TARGET_VELOCITY, 0)] = 400_000
    drive.state = SimState.OPERATION_ENABLED
    now, torques = 0.0, []
    while now < 1.5:
        now += tick_s
        drive.tick(now, tick_s)
        if now > 0.5 and 100_000 < drive.sp_vel < 300_000:  # mid-ramp, the servo settled
            torques.append(drive.torque_nm)
    alpha = 200_000 / 4096 * 2 * math.pi  # rad/s^2 at the motor
    omega = 200_000 / 4096 * 2 * math.pi  # the ramp's middle speed, rad/s
    expected = INERTIA_KG_M2 * alpha + COULOMB_NM + VISCOUS_NM_S_RAD * omega
    assert statistics.mean(torques) == pytest.approx(expected, rel=0.05)


def test_a_stall_saturates_the_torque_at_0x6072_and_faults_with_8611(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(wheel_config())
    drive = driver.drive("joint1")
    drive.enable()
    apply_action(sim, {"node": 1, "action": "load", "stall": True})
    drive.move_to(90.0)
    samples = record(drive, 0.6)
    # 0x6072 = 3000 per mille of the rated 1 Nm: 3 Nm at the motor, 150 Nm at the joint
    torques = [s.torque_nm for s in samples if not fault(s)]
    assert max(torques) == pytest.approx(3.0 * GEAR, rel=0.01)
    assert max(abs(s.angle_deg) for s in samples) < 0.01  # the shaft never turned
    wait_for(lambda: fault(drive.snapshot()), 1.0, "following-error fault")
    state = drive.snapshot()
    assert state.error_code == 0x8611, hex(state.error_code)
    apply_action(sim, {"node": 1, "action": "load", "stall": False})
    drive.recover()
    drive.enable()
    drive.move_to(10.0, wait=True, timeout_s=3.0)  # free again, it moves


def test_a_constant_load_is_held_by_the_servo(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(wheel_config())
    drive = driver.drive("joint1")
    drive.enable()
    apply_action(sim, {"node": 1, "action": "load", "nm": 0.5})  # a slope
    held = pytest.approx(0.5 * GEAR, abs=COULOMB_NM * GEAR * 1.05)
    still: list[float] = []  # stamps of the samples in a row with the shaft still and the torque at the load's

    def settled() -> bool:  # five samples in a row (a turning point of an overshoot is one)
        s = drive.snapshot()
        if s.torque_nm != held or abs(s.velocity_deg_s) >= 0.1:
            still.clear()
        elif not still or s.stamp != still[-1]:
            still.append(s.stamp)
        return len(still) >= 5

    wait_for(settled, 10.0, "the servo settled against the load")
    state = drive.snapshot()
    assert abs(state.angle_deg) < 0.05  # the position loop holds it ...
    assert state.torque_nm == pytest.approx(0.5 * GEAR, abs=COULOMB_NM * GEAR * 1.05)  # ... against the load


def step_test(tmp_path: Path, name: str, sim_model: dict[str, float]) -> dict[str, float]:
    config = tmp_path / f"{name}.yaml"
    config.write_text(yaml.safe_dump({
        "buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                   "kwargs": {"host": "127.0.0.1", "port": 1}}],
        "drives": [{"name": "wheel", "node_id": 1, "gear_ratio": GEAR, "counts_per_rev": 4096,
                    "max_velocity_deg_s": 720.0, "profile_velocity_deg_s": CRUISE_DEG_S,
                    "profile_acceleration_deg_s2": ACCEL_DEG_S2, "sim": sim_model}]}))
    with rovercan_sim("--config", str(config)) as port:
        out = tmp_path / name
        result = subprocess.run([sys.executable, "-m", "rovercan", "step-test", "1", "--step", "90", "--seconds", "1.5",
                                 "--config", str(config), "--out", str(out), "--json", "-i", "socketcand", "-c", "can0",
                                 "--bus-kwargs", "host=127.0.0.1", f"port={port}"],
                                cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    metrics: dict[str, float] = json.loads(result.stdout)
    return metrics


def test_step_test_overshoot_and_settling_follow_the_sim_gains(tmp_path: Path) -> None:
    stiff = step_test(tmp_path, "stiff", {})  # the default tuning: a 50 Hz velocity loop
    soft = step_test(tmp_path, "soft", {"bandwidth_hz": 5.0})  # a detuned drive
    assert stiff["overshoot_pct"] < 0.5, stiff
    assert soft["overshoot_pct"] > 3.0, soft  # ~7 % in the model
    assert soft["settling_time_s"] > stiff["settling_time_s"] + 0.1, (stiff, soft)


def test_a_sync_between_two_ticks_sends_one_instant_of_the_drive() -> None:
    """A SYNC answered between two simulator ticks sends what the object dictionary holds then:
    the mode's statusword bits must change with 0x6061, and 'homing attained' with the new zero.
    They changed a tick later, and a TPDO in between paired the new with the old (CI: a standing
    profile-velocity drive's bits 10 and 12 read as 'attained', then the angle before homing)."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.on_frame(can.Message(arbitration_id=0x000, data=[0x01, 1], is_extended_id=False), 0.0)  # NMT start
    drive.store.values[(OD.MODES_OF_OPERATION_DISPLAY, 0)] = int(OperationMode.PROFILE_VELOCITY)
    drive.store.values[(OD.PROFILE_ACCELERATION, 0)] = drive.store.values[(OD.PROFILE_DECELERATION, 0)] = 200_000
    drive.store.values[(OD.HOMING_METHOD, 0)] = 35  # here: the current position is the zero
    drive.state = SimState.OPERATION_ENABLED
    now = 0.0
    for target in (100_000, 0):  # turn, then stand: a standing PV drive shows bits 10 and 12
        drive.store.values[(OD.TARGET_VELOCITY, 0)] = target
        for _ in range(500):
            now += 0.002
            drive.tick(now, 0.002)

    def objects() -> tuple[int, int]:
        return int(drive.store.get(OD.STATUSWORD, 0)), int(drive.store.get(OD.POSITION_ACTUAL, 0))  # type: ignore[arg-type]

    sw, position = objects()
    assert sw & 0x1400 == 0x1400 and position > 10_000
    sdo = drive.on_frame(can.Message(arbitration_id=0x601, data=[0x2F, 0x60, 0x60, 0, int(OperationMode.HOMING), 0, 0, 0],
                                     is_extended_id=False), now)  # 0x6060 = homing, by SDO
    assert sdo and sdo[0].data[0] == 0x60
    sw, position = objects()
    assert sw & 0x1400 != 0x1400  # homing, not started: not 'attained'
    drive.on_frame(can.Message(arbitration_id=0x201, data=[0x1F, 0x00], is_extended_id=False), now)  # the start, by RPDO
    sw, position = objects()
    assert sw & 0x1400 == 0x1400 and position == 0  # attained, and the new zero, before the next tick


def sdo_write(drive: SimulatedDrive, index: int, size: int, value: int, now: float) -> None:
    """An expedited SDO download of ``value`` (``size`` bytes) to ``index``:0 of node 1."""
    command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = [command, index & 0xFF, index >> 8, 0, *value.to_bytes(4, "little", signed=True)]
    drive.on_frame(can.Message(arbitration_id=0x601, data=data, is_extended_id=False), now)


@pytest.mark.parametrize("syncs_per_tick", [1, 5])
def test_a_csp_stream_at_the_ticks_rate_is_followed_at_its_speed(syncs_per_tick: int) -> None:
    """CSP at 500 Hz (issue 55's arm: a set-point every 2 ms, the simulator's tick): the cyclic
    set-point moved on only in a tick that brought no new one, so streamed every tick it stood
    still while the velocity fed forward grew with the distance left, and the bus-limit run's six
    drives faulted (EMCY 0x8611) within 0.2 s. A late process that takes five SYNCs' set-points
    in one tick must move them at the stream's speed too, not five cycles' way in one."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.on_frame(can.Message(arbitration_id=0x000, data=[0x01, 1], is_extended_id=False), 0.0)  # NMT start
    sdo_write(drive, OD.MODES_OF_OPERATION, 1, int(OperationMode.CYCLIC_SYNC_POSITION), 0.0)
    drive.state = SimState.OPERATION_ENABLED
    cycle, step = 0.002, 57  # counts a cycle: 28,500 counts/s, the bus-limit run's joints at 50 deg/s
    now = bus_time = 0.0
    target, speeds, lags = 0, [], []
    for k in range(1, 1000 // syncs_per_tick):
        for _ in range(syncs_per_tick):  # each SYNC stamped with its bus time, then its set-point
            bus_time += cycle
            drive.on_frame(can.Message(arbitration_id=0x080, timestamp=bus_time, is_extended_id=False), now)
            target += step
            sdo_write(drive, OD.TARGET_POSITION, 4, target, now)
        now += cycle * syncs_per_tick
        drive.tick(now, cycle * syncs_per_tick)
        if k * syncs_per_tick > 200:  # the SYNC period measured, the servo settled
            speeds.append(drive.sp_vel)
            lags.append(target - drive.sp_pos)
    assert drive.state == SimState.OPERATION_ENABLED
    assert statistics.median(speeds) == pytest.approx(step / cycle, rel=0.05)
    assert max(speeds) < 1.5 * step / cycle, max(speeds)
    assert max(lags) <= (syncs_per_tick + 1) * step, max(lags)  # a cycle behind, or the late process's cycles


def test_a_csp_stream_enabled_again_from_quick_stop_goes_on_from_where_the_stop_left_it() -> None:
    """Quick stop with 0x605A = 6 (stay in Quick Stop Active), then within 0.1 s transition 16 back to
    Operation Enabled (no hold of position on the way): the next set-point is interpolated from
    where the quick stop's ramp left the set-point, not from the stream's old path (the set-point
    jumped back over the ramp's distance)."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.on_frame(can.Message(arbitration_id=0x000, data=[0x01, 1], is_extended_id=False), 0.0)  # NMT start

    now = bus_time = 0.0
    sdo_write(drive, OD.QUICK_STOP_OPTION, 2, 6, now)
    sdo_write(drive, OD.MODES_OF_OPERATION, 1, int(OperationMode.CYCLIC_SYNC_POSITION), now)
    drive.state = SimState.OPERATION_ENABLED
    target, steps = 0, []
    for k in range(600):
        if k == 300:
            sdo_write(drive, OD.CONTROLWORD, 2, 0x0002, now)  # quick stop: the set-point ramps down from the stream's speed
        if k == 330:
            assert drive.state == SimState.QUICK_STOP_ACTIVE
            sdo_write(drive, OD.CONTROLWORD, 2, 0x000F, now)  # transition 16: Operation Enabled again
            assert drive.state == SimState.OPERATION_ENABLED
            target = round(drive.sp_pos)  # the stream goes on from where the drive stands
        bus_time += 0.002
        drive.on_frame(can.Message(arbitration_id=0x080, timestamp=bus_time, is_extended_id=False), now)
        if not 300 <= k < 330:
            target += 57
            sdo_write(drive, OD.TARGET_POSITION, 4, target, now)
        before = drive.sp_pos
        now += 0.002
        drive.tick(now, 0.002)
        steps.append(drive.sp_pos - before)
    assert max(abs(step) for step in steps[330:]) < 3 * 57, max(steps[330:], key=abs)


def _furthest_past_the_limit(tick_s: float) -> tuple[float, SimState]:
    """A drive in profile velocity at 400,000 counts/s (98 motor turns a second) towards its
    software limit 100,000 counts ahead, ticked every ``tick_s``: the furthest it went (counts) and
    its state once it stands."""
    drive = SimulatedDrive(1, load_drive_od(GENERIC_EDS, 1))
    drive.store.values[(OD.MODES_OF_OPERATION_DISPLAY, 0)] = int(OperationMode.PROFILE_VELOCITY)
    drive.store.values[(OD.PROFILE_ACCELERATION, 0)] = 2_000_000
    drive.store.values[(OD.QUICK_STOP_DECELERATION, 0)] = 2_000_000  # its fault reaction: 0.2 s from speed
    drive.store.values[(OD.TARGET_VELOCITY, 0)] = 400_000
    drive.store.values[(OD.SOFTWARE_POSITION_LIMIT, 1)] = -100_000
    drive.store.values[(OD.SOFTWARE_POSITION_LIMIT, 2)] = 100_000
    drive.state = SimState.OPERATION_ENABLED
    now, furthest = 0.0, 0.0
    while now < 2.0:
        now += tick_s
        drive.tick(now, tick_s)
        furthest = max(furthest, drive.position_counts)
    assert drive.omega == 0.0 or abs(drive.omega) < 1e-6, drive.omega
    return furthest, drive.state


def test_a_late_simulator_tick_faults_at_the_software_limit_as_one_on_time() -> None:
    """A busy machine runs the simulator's thread late (a tick of 40 ms instead of 2): the drive
    still faults where it crosses its software limit and stops from there. Checked once a tick,
    it went on for the rest of the late tick first (up to 40 ms at 400,000 counts/s, 16,000
    counts; here 2,400 further than on time), and a test of a drive's overshoot judged the CPU."""
    on_time, state = _furthest_past_the_limit(0.002)
    assert state == SimState.FAULT
    late, state = _furthest_past_the_limit(0.04)
    assert state == SimState.FAULT
    assert abs(late - on_time) < 400_000 * 0.002, (late, on_time)  # within one check's travel
