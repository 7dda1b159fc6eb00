"""A stop always wins: each interleaving of a stop with enable(), a disable with enable(), and a
mode switch with other commands is forced at a named point of the state machine
(``CommandChannel.set_hook``), not hoped for in a stress run. After a stop returns, the drive is not
Operation Enabled, and the last controlword on the bus is the stop's."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import canopen
import pytest

from can_config import RoverConfig
from can_config.config import GENERIC_EDS
from can_config.errors import CommandRejected, DriveStateError
from can_config.objects import OperationMode
from motor_driver import MotorDriver
from motor_driver.drive import Drive
from virtual_can import SimService

from .conftest import drain, in_thread, make_config, wait_for

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]
RPDO1 = 0x201  # node 1's controlword RPDO

STOPS: dict[str, tuple[Callable[[Drive], None], int, set[str]]] = {
    # name: (the stop, its controlword, the states the drive may end in)
    "quick stop": (Drive.quick_stop, 0x0002, {"SWITCH_ON_DISABLED", "QUICK_STOP_ACTIVE"}),
    "disable": (Drive.disable, 0x0006, {"READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED"}),
    "disable voltage": (Drive.disable_voltage, 0x0000, {"SWITCH_ON_DISABLED"}),
}
ENABLE_POINTS = [f"enable: {when} transition {n}" for n in (2, 3, 4) for when in ("before", "sent")]


def sim_state(sim: SimService) -> str:
    runner = sim.simulators["can0"]
    return str(runner.call(lambda: runner.drive(1).state.name))


def controlwords(frames: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data[:2], "little") for m in frames if m.arbitration_id == RPDO1]


class StopAt:
    """When the drive's thread reaches ``point``, ``action`` runs to completion on another thread
    while that thread waits; what it raised and how long it took are kept."""

    def __init__(self, drive: Drive, point: str, action: Callable[[], None]) -> None:
        self.point, self.action = point, action
        self.fired = False
        self.error: BaseException | None = None
        self.took_s = 0.0
        drive.channel.set_hook(self)

    def __call__(self, point: str) -> None:
        if point != self.point or self.fired:
            return
        self.fired = True

        def run() -> None:
            start = time.monotonic()
            try:
                self.action()
            except BaseException as err:
                self.error = err
            self.took_s = time.monotonic() - start

        other = threading.Thread(target=run)
        other.start()
        other.join(5.0)
        assert not other.is_alive(), f"the interleaved action did not finish at {self.point}"


@pytest.mark.parametrize("stop_name", list(STOPS))
@pytest.mark.parametrize("point", ENABLE_POINTS)
def test_a_stop_during_each_step_of_enable_wins(driver_factory: DriverFactory, listener_factory: ListenerFactory,
                                                point: str, stop_name: str) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    stop, stop_cw, stopped_states = STOPS[stop_name]
    listener = listener_factory(sim)
    at = StopAt(drive, point, lambda: stop(drive))
    with pytest.raises(DriveStateError, match=f"interrupted by {stop_name}"):
        drive.enable()
    assert at.fired and at.error is None, at.error
    frames = drain(listener, 0.4)  # the drive has settled: its last word came in long ago
    words = controlwords(frames)
    wanted = {stop_cw}
    if stop_name == "disable" and "transition 2" in point:  # the drive said Switch On Disabled: Disable Voltage
        # (Shutdown there is transition 2, toward enabled); once transition 2 is sent the drive's
        # answer may be read before the stop, and the stop is then Shutdown
        wanted = {0x0000} if point.startswith("enable: before") else {0x0000, 0x0006}
    assert words and words[-1] in wanted, [hex(w) for w in words]  # nothing of enable() after the stop
    assert sim_state(sim) in stopped_states and drive.cache.state.name in stopped_states, (sim_state(sim), drive.cache.state)
    drive.enable()  # a later enable that asks for it is obeyed
    assert sim_state(sim) == "OPERATION_ENABLED"


def test_a_stop_during_a_mode_switch_wins_and_other_commands_are_refused_at_once(
        driver_factory: DriverFactory, listener_factory: ListenerFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    listener = listener_factory(sim)
    refused: list[tuple[str, float]] = []

    def meanwhile() -> None:
        for command in (lambda: drive.move_to(10.0), lambda: drive.set_velocity(5.0), drive.halt):
            start = time.monotonic()
            try:
                command()
            except CommandRejected as err:
                refused.append((str(err), time.monotonic() - start))
        drive.quick_stop()

    at = StopAt(drive, "mode switch: 0x6060 written", meanwhile)
    with pytest.raises(DriveStateError, match="interrupted by quick stop"):
        drive.set_velocity(30.0)  # asks for a switch to profile velocity, which the stop ends
    assert at.fired and at.error is None, at.error
    assert len(refused) == 3 and all("busy with mode switch" in text and took < 0.05 for text, took in refused), refused
    assert at.took_s < 1.0  # the stop did not wait for the switch's SDO round trips
    frames = drain(listener, 0.4)
    assert not [m for m in frames if m.arbitration_id == 0x401], "a velocity RPDO went out"
    assert controlwords(frames)[-1] == 0x0002
    assert sim_state(sim) != "OPERATION_ENABLED"
    assert drive.snapshot().velocity_deg_s == 0.0


def test_a_motion_command_after_a_stop_sends_nothing(driver_factory: DriverFactory,
                                                     listener_factory: ListenerFactory) -> None:
    """The stop's frame has gone, the drive's next statusword has not come yet: the last
    statusword still says Operation Enabled, and a command must not take it for permission."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    drive.set_velocity(0.0)  # in profile velocity now
    listener = listener_factory(sim)

    def velocity_right_after_the_stop_frame(point: str) -> None:
        if point == "quick stop: sent":
            drive.channel.set_hook(None)
            with pytest.raises((DriveStateError, CommandRejected)):
                drive.set_velocity(20.0)

    drive.channel.set_hook(velocity_right_after_the_stop_frame)
    drive.quick_stop()
    frames = drain(listener, 0.3)
    assert not [m for m in frames if m.arbitration_id == 0x401 and int.from_bytes(m.data[2:6], "little")]
    assert sim_state(sim) in {"SWITCH_ON_DISABLED", "QUICK_STOP_ACTIVE"}


def no_pdo_target_eds(path: Path) -> Path:
    od = canopen.import_od(str(GENERIC_EDS), 1)
    od[0x607A].pdo_mappable = False  # as on the SCHUNK PRL120
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def test_a_parked_target_on_a_drive_without_a_pdo_target_is_never_sent_by_sdo_from_the_receive_thread(
        driver_factory: DriverFactory, tmp_path: Path) -> None:
    _, driver = driver_factory(make_config(1, eds=str(no_pdo_target_eds(tmp_path / "no-pdo-target.eds"))))
    drive = driver.drive("joint1")
    assert drive.plan.rpdo_with(0x607A) is None
    drive.enable()
    threads: list[str] = []
    download = drive.node.sdo.download

    def recording(*args: object, **kwargs: object) -> None:
        threads.append(threading.current_thread().name)
        download(*args, **kwargs)  # type: ignore[arg-type]

    drive.node.sdo.download = recording  # type: ignore[method-assign]
    drive.move_to(5.0)
    drive.move_to(10.0)  # parked until the first is acknowledged and released
    wait_for(lambda: abs(drive.snapshot().angle_deg - 10.0) < 0.2, 5.0, "the parked target reached")
    assert threads and set(threads) == {threading.current_thread().name}, threads


def test_a_streamed_set_point_to_a_stopped_drive_without_a_pdo_target_writes_no_sdo(
        driver_factory: DriverFactory, tmp_path: Path) -> None:
    """Streaming already, a set-point whose target goes by SDO is still checked before that SDO:
    the drive disabled, it is refused and 0x607A is not written."""
    _, driver = driver_factory(make_config(1, eds=str(no_pdo_target_eds(tmp_path / "no-pdo-target.eds"))))
    drive = driver.drive("joint1")
    drive.enable()
    drive.stream_position(drive.snapshot().angle_deg)  # switches to CSP, the target by SDO
    assert drive.snapshot().mode == 8
    written: list[int] = []
    download = drive.node.sdo.download

    def recording(index: int, *args: object, **kwargs: object) -> None:
        written.append(index)
        download(index, *args, **kwargs)  # type: ignore[arg-type]

    drive.node.sdo.download = recording  # type: ignore[method-assign]
    drive.disable()
    with pytest.raises(DriveStateError, match=r"CSP setpoint refused: the drive is \w+; enable\(\) it first"):
        drive.stream_position(drive.snapshot().angle_deg)
    assert 0x607A not in written, [hex(i) for i in written]


def no_pdo_velocity_eds(path: Path) -> Path:
    od = canopen.import_od(str(GENERIC_EDS), 1)
    od[0x60FF].pdo_mappable = False  # the target velocity only by SDO
    canopen.export_od(od, str(path), doc_type="eds")
    return path


def settled_controlwords(listener: can.BusABC) -> list[int]:
    """Every controlword of node 1 on the wire until the bus has been quiet of them a while."""
    return controlwords(drain(listener, 0.4))


@pytest.mark.parametrize("point", ["mode switch: 0x6060 written", "home: parameters written", "home: start sent"])
def test_a_stop_during_homings_sdo_writes_wins_and_nothing_of_homing_follows(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, point: str) -> None:
    """Homing's enable runs under homing's operation: a stop that lands during homing's own SDO
    writes ends it before any controlword of it (the landed code enabled the drive here)."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    listener = listener_factory(sim)
    at = StopAt(drive, point, drive.quick_stop)
    with pytest.raises(DriveStateError, match="interrupted by quick stop"):
        drive.home()
    assert at.fired and at.error is None, at.error
    words = settled_controlwords(listener)
    assert words and words[-1] == 0x0002, [hex(w) for w in words]
    assert 0x000F not in words[words.index(0x0002):], [hex(w) for w in words]
    assert sim_state(sim) != "OPERATION_ENABLED" and drive.channel.busy is None


@pytest.mark.parametrize("point", ENABLE_POINTS)
def test_a_stop_during_enable_leaves_no_busy_mark(driver_factory: DriverFactory, point: str) -> None:
    """After an enable a stop interrupted, every command from another thread is taken again and
    the watchdog's stop runs (the landed code kept 'busy with enable' for ever)."""
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    StopAt(drive, point, drive.quick_stop)
    with pytest.raises(DriveStateError):
        drive.enable()
    drive.channel.set_hook(None)
    assert drive.channel.busy is None
    assert drive.limits.stop_velocity()  # the watchdog is not locked out
    other: list[BaseException] = []

    def enable_and_move() -> None:
        try:
            drive.enable()
            drive.set_velocity(5.0)
        except BaseException as err:
            other.append(err)

    thread = threading.Thread(target=enable_and_move)
    thread.start()
    thread.join(10.0)
    assert not other, other
    assert drive.channel.velocity_commanded


def test_a_stop_does_not_wait_behind_a_velocity_target_written_by_sdo(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, tmp_path: Path) -> None:
    """0x60FF only by SDO, on a drive that answers SDO in 200 ms: a stop issued while that write
    waits for its answer reaches the wire before the answer does (the landed code held the
    drive's lock across the SDO, and the stop waited for it)."""
    sim, driver = driver_factory(make_config(1, eds=str(no_pdo_velocity_eds(tmp_path / "no-pdo-velocity.eds"))))
    drive = driver.drive("joint1")
    assert drive.plan.rpdo_with(0x60FF) is None
    drive.enable()
    drive.set_velocity(0.0)  # in profile velocity now
    runner = sim.simulators["can0"]
    runner.call(lambda: setattr(runner.drive(1).faults, "sdo_delay_s", 0.2))
    listener = listener_factory(sim)
    thread, _ = in_thread(lambda: drive.set_velocity(20.0))
    frames: list[can.Message] = []
    while not any(m.arbitration_id == 0x601 and bytes(m.data[1:3]) == b"\xff\x60" for m in frames):
        msg = listener.recv(5.0)
        assert msg is not None, "the 0x60FF write never went out"
        frames.append(msg)
    drive.quick_stop()
    thread.join(10.0)
    frames += drain(listener, 0.4)
    order = [("stop" if m.arbitration_id == RPDO1 and m.data[0] == 0x02 else "answer")
             for m in frames if m.arbitration_id == 0x581 or (m.arbitration_id == RPDO1 and m.data[0] == 0x02)]
    assert order and order[0] == "stop", order  # the stop before the write's answer
    assert controlwords(frames)[-1] == 0x0002
    assert sim_state(sim) != "OPERATION_ENABLED"


def test_a_stop_while_homings_method_write_waits_on_a_slow_drive_wins(
        driver_factory: DriverFactory, listener_factory: ListenerFactory) -> None:
    """Public API and the wire only: the stop is issued once the listener sees homing's 0x6098
    write out, while a 200 ms drive has not answered it. The landed code's homing then enabled
    the drive with a fresh operation of its own (0x2, 0x6, 0x7, 0xF after the stop)."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    runner = sim.simulators["can0"]
    runner.call(lambda: setattr(runner.drive(1).faults, "sdo_delay_s", 0.2))
    listener = listener_factory(sim)
    thread, errors = in_thread(lambda: drive.home(timeout_s=5.0))
    frames: list[can.Message] = []
    while not any(m.arbitration_id == 0x601 and bytes(m.data[1:3]) == b"\x98\x60" for m in frames):
        msg = listener.recv(10.0)
        assert msg is not None, "homing's 0x6098 write never went out"
        frames.append(msg)
    drive.quick_stop(timeout_s=3.0)
    thread.join(20.0)
    assert errors and "interrupted by quick stop" in str(errors[0]), errors
    words = controlwords(frames + drain(listener, 0.6))
    assert words and words[-1] == 0x0002, [hex(w) for w in words]
    assert sim_state(sim) != "OPERATION_ENABLED" and drive.channel.busy is None


def test_a_stop_whose_wait_outlives_the_enable_it_ended_leaves_no_busy_mark(driver_factory: DriverFactory) -> None:
    """The enable ends (interrupted) while the stop still waits for the drive: the landed code's
    stop then restored 'busy with enable' for a thread that had finished, for ever."""
    _, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    enable_done = threading.Event()
    stopper, stop_errors = in_thread(drive.quick_stop, start=False)

    def hook(point: str) -> None:
        if point == "enable: sent transition 3" and not stopper.is_alive() and not enable_done.is_set():
            stopper.start()  # the stop runs on its own thread; this enable goes on
        elif point == "quick stop: sent":
            assert enable_done.wait(10.0), "the enable did not end"  # the stop's wait outlives it

    drive.channel.set_hook(hook)
    with pytest.raises(DriveStateError, match="interrupted by quick stop"):
        drive.enable()
    enable_done.set()
    stopper.join(10.0)
    drive.channel.set_hook(None)
    assert not stop_errors, stop_errors
    assert drive.channel.busy is None, drive.channel.busy
    drive.enable()  # from here: commands are taken again
    drive.set_velocity(5.0)


HELD = "the test's owner is inactive: activate it"
#: A controlword that enables (the walk to Operation Enabled: transitions 2, 3, 4).
ENABLING = {0x0006, 0x0007, 0x000F}
#: Every way to move the drive, each refused while motion is held.
HELD_ENTRIES: dict[str, Callable[[Drive], object]] = {
    "enable": Drive.enable, "recover": Drive.recover, "home": Drive.home,
    "set_mode (the mode it is in)": lambda d: d.set_mode(OperationMode.PROFILE_POSITION),
    "set_mode": lambda d: d.set_mode(OperationMode.PROFILE_VELOCITY),
    "move_to": lambda d: d.move_to(10.0), "set_velocity": lambda d: d.set_velocity(5.0),
    "stream_position": lambda d: d.stream_position(0.0), "set_torque": lambda d: d.set_torque(0.1),
    "halt released": lambda d: d.halt(False), "SDO write": lambda d: d.sdo.write_checked(0x6065, 0, 1000),
}


#: The fence's SDO upload request: 0x1000 (device type), which nothing but a boot reads.
FENCE = b"\x40\x00\x10\x00"


def frames_until_fence(listener: can.BusABC, drive: Drive) -> list[can.Message]:
    """Every frame up to the driver's SDO read of the device type, sent after anything the test
    did before (one connection, frames in order)."""
    drive.sdo.read(0x1000, 0)
    frames: list[can.Message] = []
    deadline = time.monotonic() + 10.0  # a hang bound
    while not frames or not (frames[-1].arbitration_id == 0x601 and bytes(frames[-1].data[:4]) == FENCE):
        assert time.monotonic() < deadline, "the fence never came"
        msg = listener.recv(0.5)
        if msg is not None:
            frames.append(msg)
    return frames


@pytest.mark.parametrize("point", ENABLE_POINTS)
def test_motion_held_during_each_step_of_enable_ends_it_and_nothing_enables_until_allowed(
        driver_factory: DriverFactory, listener_factory: ListenerFactory, point: str) -> None:
    """The lifecycle node's deactivate (the driver's hold_motion, then its safe stop) at each step
    of an enable ends it with the hold's reason; held, every motion entry is refused with it and
    nothing enabling or moving reaches the bus (a stop and a halt are still taken); allowed again,
    an enable asked for is obeyed."""
    sim, driver = driver_factory(make_config(1, counts_per_rev=4096))
    drive = driver.drive("joint1")
    listener = listener_factory(sim)
    at = StopAt(drive, point, lambda: (driver.hold_motion(HELD), driver.safe_stop()))
    with pytest.raises(CommandRejected, match=HELD):
        drive.enable()
    assert at.fired and at.error is None, at.error
    wrong = []
    for what, entry in HELD_ENTRIES.items():
        try:
            entry(drive)
            wrong.append(f"{what}: taken")
        except CommandRejected as err:
            if HELD not in str(err):
                wrong.append(f"{what}: {err}")
    assert not wrong, wrong
    drive.halt(True)  # stops are taken
    drive.quick_stop()
    frames = frames_until_fence(listener, drive)
    stops = [i for i, m in enumerate(frames) if m.arbitration_id == RPDO1 and controlwords([m])[0] in (0x0000, 0x0002)]
    assert stops, [(hex(m.arbitration_id), m.data.hex()) for m in frames]  # the safe stop's frame
    after = frames[stops[0]:]
    assert not ENABLING & set(controlwords(after)), [hex(w) for w in controlwords(frames)]
    assert not [m for m in after if m.arbitration_id in (0x301, 0x401, 0x501)], "a set-point went out"
    assert not [m for m in after if m.arbitration_id == 0x601 and m.data[0] >> 5 == 1], "an SDO write went out"
    assert sim_state(sim) == "SWITCH_ON_DISABLED" and driver.motion_held == HELD
    driver.allow_motion()
    drive.enable()
    assert sim_state(sim) == "OPERATION_ENABLED"


def test_a_stop_while_an_arm_asks_whether_it_is_armed_already_wins(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    """An enable of a drive armed already sends nothing (it is counted, not walked); a quick stop
    that lands while it looks (a hook at its look, outside the lock) wins: the enable is refused,
    not walked again from the stop, and the drive stays stopped."""
    sim, driver = driver_factory(make_config(1))
    drive = driver.drive("joint1")
    drive.enable()
    stopped: list[str] = []

    def stop_in_the_look(point: str) -> None:
        if point == "enable: armed already?" and not stopped:
            stopped.append(point)
            drive.quick_stop()

    drive.channel.set_hook(stop_in_the_look)
    try:
        with pytest.raises(DriveStateError, match="refused: stopped since it was asked"):
            drive.enable()
    finally:
        drive.channel.set_hook(None)
    assert stopped and drive.channel.stopped_by
    assert sim_state(sim) in STOPS["quick stop"][2]  # the stop was confirmed before the enable went on
