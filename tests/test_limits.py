"""A limited joint stays within its limits on every command path: position targets, velocity,
torque, streamed positions, the bench jog (the ROS topics: tests/test_ros_limits.py), and the
drive's own software limits (0x607D) written at boot. Inverted joints with an offset round-trip.

The joint's true angle is read from the simulated drive (its shaft), not from the driver.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from can_config import RoverConfig
from can_config.errors import CommandRejected, MotorError
from motor_driver import Drive, MotorDriver, State
from motor_driver.drive.constants import LIMIT_ACCEL_MARGIN_S
from virtual_can import SimService
from virtual_can.sim.drive import LIMIT_TOLERANCE_REV

from .conftest import REPO, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
GEAR = 50.0
COUNTS_PER_DEG = 4096 * GEAR / 360.0
LIMITED = {"joint": "limited", "min_deg": -90.0, "max_deg": 90.0, "gear_ratio": GEAR, "counts_per_rev": 4096,
           "max_velocity_deg_s": 720.0, "profile_acceleration_deg_s2": 720.0}


class Extremes:
    """The true joint angle, sampled from the simulated drive every 2 ms in a thread."""

    def __init__(self, sim: SimService, node: int = 1, counts_per_deg: float = COUNTS_PER_DEG) -> None:
        self.sim, self.node, self.k = sim, node, counts_per_deg
        self.low, self.high = float("inf"), float("-inf")
        self.samples = 0  # taken so far (this thread's)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def angle(self) -> float:
        runner = self.sim.simulators["can0"]
        drive = runner.drive(self.node)
        return float(runner.call(lambda: drive.position_counts)) / self.k  # type: ignore[arg-type]

    def _run(self) -> None:
        while not self._stop.is_set():
            a = self.angle()
            self.low, self.high = min(self.low, a), max(self.high, a)
            self.samples += 1
            time.sleep(0.002)

    def after(self, done: Callable[[], bool], what: str) -> tuple[float, float]:
        """Wait for ``done`` (the joint at rest), then for a sample taken after it, and stop: the
        extremes include the joint's whole way to rest, not a span of the clock."""
        wait_for(done, 30.0, what)
        taken = self.samples
        wait_for(lambda: self.samples > taken, 30.0, "a sample of the joint at rest")
        return self.stop()

    def stop(self) -> tuple[float, float]:
        self._stop.set()
        self._thread.join()
        return self.low, self.high


def sim_state(sim: SimService, node: int = 1) -> str:
    runner = sim.simulators["can0"]
    return str(runner.call(lambda: runner.drive(node).state.name))


def drive_until_refused(send: Callable[[], None], seconds: float = 4.0) -> str:
    """Send the same command every 20 ms (a ROS topic, a jog loop) until the driver refuses it."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            send()
        except CommandRejected as err:
            return str(err)
        time.sleep(0.02)
    raise AssertionError("never refused")


@pytest.mark.parametrize("direction", [1.0, -1.0], ids=["toward max", "toward min"])
def test_velocity_toward_a_limit_stops_before_it(driver_factory: DriverFactory, direction: float) -> None:
    sim, driver = driver_factory(make_config(1, **LIMITED))
    drive = driver.drive("joint1")
    drive.enable()
    watch = Extremes(sim)
    # full speed: 720 deg/s could not stop within the 90 deg to the limit at 720 deg/s^2
    with pytest.raises(CommandRejected, match=r"velocity .*720 deg/s refused"):
        drive.set_velocity(direction * 720.0)
    # fast, then creeping on, as a ROS topic or a jog loop would keep sending
    for speed in (200.0, 30.0, 5.0):
        refusal = drive_until_refused(lambda speed=speed: drive.set_velocity(direction * speed))
        wait_for(lambda: abs(drive.snapshot().velocity_deg_s) < 0.5, 2.0, "standstill")
    low, high = watch.stop()
    assert ("max_deg=90" if direction > 0 else "min_deg=-90") in refusal and "it is stopping" in refusal
    assert low >= -90.0 and high <= 90.0, (low, high)
    assert max(-low, high) > 85.0  # and it got close: the guard does not stop it early
    assert sim_state(sim) == "OPERATION_ENABLED"  # the driver's guard stopped it, not the drive's fault
    drive.set_velocity(-direction * 10.0)  # inward goes


def test_a_single_velocity_command_is_stopped_by_the_guard(driver_factory: DriverFactory) -> None:
    """One command and silence (the watchdog is long): the supervisor's guard brakes it."""
    sim, driver = driver_factory(make_config(1, **LIMITED, watchdog_ms=10_000))
    drive = driver.drive("joint1")
    drive.enable()
    watch = Extremes(sim)
    drive.set_velocity(100.0)
    wait_for(lambda: drive.limits.limit_stops > 0, 3.0, "the limit guard")
    _low, high = watch.after(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, "the joint braked to rest")
    assert 80.0 < high <= 90.0 and abs(drive.snapshot().velocity_deg_s) < 1.0


def test_torque_toward_a_limit_is_stopped(driver_factory: DriverFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each push is stopped by the limit guard, at or before the limit while the guard looks on
    time (its margin covers the gap to its next look and a SYNC: 35 ms). A process held longer lets a
    torque-driven joint gain about 115 deg/s per 50 ms before the guard looks again, which no host
    guard can take back (the drive's own 0x607D is the backstop): then only a bound of gross
    failure is checked. Which case held is read from the guard's own looks (a hook that calls it),
    so the verdict never depends on the process getting the CPU."""
    sim, driver = driver_factory(make_config(1, **LIMITED, watchdog_ms=10_000))
    drive = driver.drive("joint1")
    looks: list[float] = []
    guard = drive.limits.guard_limits

    def looked() -> None:
        looks.append(time.monotonic())
        guard()

    monkeypatch.setattr(drive.limits, "guard_limits", looked)
    drive.enable()
    watch = Extremes(sim)
    for push in range(1, 7):  # pushed again and again from where it stopped
        try:
            drive.set_torque(12.0)  # accelerates the joint toward +90 at about 2300 deg/s^2
        except CommandRejected as err:  # it stands where no push may start: refused, braked, nothing else
            assert "could not stop before its limit max_deg=90" in str(err) and push > 1, err
            break
        wait_for(lambda push=push: drive.limits.limit_stops >= push, 3.0, "the limit guard")
        wait_for(lambda: sim_state(sim) == "SWITCH_ON_DISABLED", 1.0, "quick stop done")  # a torque loop has no brake
        drive.enable()
    _low, high = watch.stop()
    worst_gap = max(b - a for a, b in itertools.pairwise(looks))
    on_time = worst_gap + drive.cache.sync_period_s <= LIMIT_ACCEL_MARGIN_S  # the next look, then a SYNC
    assert 80.0 < high <= (90.0 if on_time else 95.0), (high, f"the guard's worst gap between looks: {worst_gap:.3f} s")


def test_streamed_positions_are_refused_beyond_a_limit(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1, **LIMITED))
    drive = driver.drive("joint1")
    drive.enable()
    watch = Extremes(sim)
    angle = 0.0
    with pytest.raises(CommandRejected, match="above the upper limit max_deg=90"):
        while True:
            angle += 1.0
            drive.stream_position(angle)
            time.sleep(drive.cache.sync_period_s)
    # the servo's overshoot settled: the drive's own velocity (its TPDO) near zero
    _low, high = watch.after(lambda: abs(drive.snapshot().velocity_deg_s) < 1.0, "the joint at rest")
    # the stream stops dead from 100 deg/s at 90: the servo overshoots a little (the simulated
    # drive's model: about 0.1 motor rev), less than its limit tolerance, so it does not fault
    assert angle == 91.0 and high <= 90.0 + LIMIT_TOLERANCE_REV * 360.0 / GEAR
    assert drive.cache.state is State.OPERATION_ENABLED


def test_the_drive_gets_its_limits_and_faults_beyond_them_by_itself(driver_factory: DriverFactory) -> None:
    """0x607D is written at boot in drive counts; the drive stops a joint pushed past it even if the
    driver's own guard were not there (here: an SDO-written velocity the driver never saw)."""
    sim, driver = driver_factory(make_config(1, **LIMITED))
    runner = sim.simulators["can0"]
    sim_drive = runner.drive(1)
    limits = runner.call(lambda: (sim_drive.store.get(0x607D, 1), sim_drive.store.get(0x607D, 2)))
    assert limits == (round(-90 * COUNTS_PER_DEG), round(90 * COUNTS_PER_DEG))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_mode(3)  # profile velocity
    drive.sdo_write(0x60FF, 0, int(360 * COUNTS_PER_DEG).to_bytes(4, "little", signed=True))  # behind the driver's back
    wait_for(lambda: drive.cache.state is State.FAULT, 3.0, "the drive's own limit fault")
    assert drive.snapshot().error_code == 0x8612  # reference limit
    # within its limit tolerance and quick-stop distance
    assert Extremes(sim).stop()[1] < 90.0 + LIMIT_TOLERANCE_REV * 360.0 / GEAR + 360.0 * 360.0 / (2 * 4 * 720.0) + 1.0


@pytest.mark.parametrize("invert", [False, True], ids=["plain", "inverted"])
def test_inverted_joint_with_offset_round_trips(driver_factory: DriverFactory, invert: bool) -> None:
    sim, driver = driver_factory(make_config(1, **{**LIMITED, "min_deg": 0.0, "max_deg": 100.0},
                                             invert=invert, offset_deg=10.0))
    runner = sim.simulators["can0"]
    sim_drive = runner.drive(1)
    drive = driver.drive("joint1")
    assert drive.snapshot().angle_deg == pytest.approx(10.0, abs=0.01)  # drive at 0 counts = joint at the offset
    lo, hi = runner.call(lambda: (sim_drive.store.get(0x607D, 1), sim_drive.store.get(0x607D, 2)))
    sign = -1 if invert else 1
    assert sorted([lo, hi]) == sorted([round(sign * -10 * COUNTS_PER_DEG), round(sign * 90 * COUNTS_PER_DEG)])
    drive.enable()
    drive.move_to(30.0, wait=True)
    counts = float(runner.call(lambda: sim_drive.position_counts))  # type: ignore[arg-type]
    assert counts == pytest.approx(sign * 20.0 * COUNTS_PER_DEG, abs=0.2 * COUNTS_PER_DEG)  # negative when inverted
    assert drive.snapshot().angle_deg == pytest.approx(30.0, abs=0.2)
    for _ in range(20):
        drive.set_velocity(20.0)
        time.sleep(0.02)
    state = drive.snapshot()
    assert state.velocity_deg_s == pytest.approx(20.0, abs=1.0) and state.angle_deg > 30.0
    drive_velocity = float(runner.call(lambda: sim_drive.store.get(0x606C, 0)))  # type: ignore[arg-type]
    assert drive_velocity * sign > 0
    drive.set_velocity(0.0)
    with pytest.raises(CommandRejected, match="below the lower limit min_deg=0"):
        drive.move_to(-5.0)


def test_jog_cli_toward_a_limit_stops_before_it(tmp_path: Path) -> None:
    config = make_config(1, **LIMITED)
    with SimService.from_config(config, port=0) as sim:
        path = tmp_path / "limited.yaml"
        path.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                        f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}\n"
                        "drives:\n  - {name: joint1, node_id: 1, joint: limited, min_deg: -90, max_deg: 90,"
                        " gear_ratio: 50, counts_per_rev: 4096, max_velocity_deg_s: 720,"
                        " profile_acceleration_deg_s2: 720}\n")
        watch = Extremes(sim)
        result = subprocess.run([sys.executable, "-m", "rovercan", "jog", "1", "300", "--for", "3", "--config", str(path)],
                                cwd=REPO, capture_output=True, text=True, timeout=60)
        _low, high = watch.stop()
        state = sim_state(sim)
    assert result.returncode == 1, result.stderr
    assert "velocity 300 deg/s refused" in result.stderr and "max_deg=90" in result.stderr
    assert "Traceback" not in result.stderr
    assert high <= 90.0, high
    assert state == "SWITCH_ON_DISABLED"  # the bench leaves nothing armed


def test_limit_guard_is_per_drive(driver_factory: DriverFactory) -> None:
    """A continuous joint beside a limited one is never braked by the guard."""
    config = make_config(2, watchdog_ms=10_000)
    _, driver = driver_factory(config)
    drive: Drive = driver.drive("joint1")
    drive.enable()
    start = drive.snapshot().angle_deg
    drive.set_velocity(360.0)
    # > 500 deg on: far past any limit a limited joint could have; then the guard shown to have
    # looked at it there (two host heartbeats later: a supervisor period, guard included, between
    # them), not a span of the clock in which a held supervisor looks at nothing
    wait_for(lambda: abs(drive.snapshot().angle_deg - start) > 500.0, 30.0, "the joint 500 deg on")
    handle = driver.buses["can0"]
    beats = handle.beats_sent()
    wait_for(lambda: handle.beats_sent() >= beats + 2, 30.0, "a supervisor period with the joint 500 deg on")
    assert drive.limits.limit_stops == 0 and drive.snapshot().velocity_deg_s == pytest.approx(360.0, rel=0.05)
    with pytest.raises(MotorError):
        driver.drive("joint2").set_velocity(10.0)  # not enabled: refused as before
