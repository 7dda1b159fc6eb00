"""A quiet supervisor wakes when something is due, and at once when something changes.

Its wake-ups, not its checks, were its cost (docs/performance.md): with every drive booted and
nothing live it waits for the next host heartbeat (or a drive's heartbeat timeout, a node guard),
not every SUPERVISOR_PERIOD_S. What it watches every period still gets every period: a live
velocity or torque command (its watchdog and limit guard), a drive lost or booting, another
master's sign. A change wakes it at once: a report handed over, a command going live, another
master's frame. The counts below are the supervisor's own (its periods, its heartbeats sent):
no verdict here depends on the process getting the CPU in time."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can
import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from motor_driver.bus.traffic import FOREIGN_HOLD_S, ForeignTraffic
from motor_driver.runtime.supervisor import BUS_CHECK_S, QUIET_WAIT_MAX_S, SUPERVISOR_PERIOD_S, Supervisor
from virtual_can import SimService

from .conftest import make_config, wait_for
from .test_command_channel import Wire, enabled, make_channel

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


def booted(driver: MotorDriver) -> Supervisor:
    supervisor = driver.supervisor
    wait_for(lambda: all(r.booted for r in supervisor.records.values()), 10.0, "every drive booted")
    wait_for(lambda: all(r.next_beat for r in supervisor.bus.bus_records.values()), 10.0, "a host heartbeat sent")
    # and each drive heard OPERATIONAL: the boot's last change posted (a post wakes the supervisor too)
    wait_for(lambda: all(d.cache.nmt_state == "OPERATIONAL" for d in driver), 10.0, "every drive heard OPERATIONAL")
    return supervisor


def wants_every_period(supervisor: Supervisor) -> bool:
    """What a loaded machine can bring about in a quiet test rover: a drive judged by how far its
    bus's receive thread has read (a starved process), one not booted or lost (each looked at every
    period by design)."""
    return any(r.read_behind or r.lost or r.lost_since or not r.booted for r in supervisor.records.values())


class Periods:
    """The supervisor's periods and the host heartbeats they sent, counted in its own thread, and
    the periods that followed a wait cut short for a reason of :func:`wants_every_period`."""

    def __init__(self, supervisor: Supervisor, bus: str = "can0") -> None:
        self.periods = self.beats = self.excused = 0
        self.enough = threading.Event()
        self._want = 0
        record = supervisor.bus.bus_records[bus]
        period, wait_s = supervisor._period, supervisor.wait_s

        def counted(now: float) -> None:
            before = record.last_beat
            period(now)
            self.periods += 1
            self.beats += record.last_beat != before
            if self._want and self.beats >= self._want:
                self.enough.set()

        def judged(now: float) -> float:
            wait = wait_s(now)
            self.excused += wait == SUPERVISOR_PERIOD_S and wants_every_period(supervisor)
            return wait
        supervisor._period = counted  # type: ignore[method-assign]
        supervisor.wait_s = judged  # type: ignore[method-assign]

    def over(self, beats: int) -> tuple[int, int, int]:
        """(periods, beats, excused) over the next ``beats`` host heartbeats."""
        periods0, beats0, excused0 = self.periods, self.beats, self.excused
        self.enough.clear()
        self._want = beats0 + beats
        assert self.enough.wait(60.0), "the supervisor sent no heartbeats"
        return self.periods - periods0, self.beats - beats0, self.excused - excused0


def test_a_quiet_supervisor_wakes_about_once_a_host_heartbeat(driver_factory: DriverFactory) -> None:
    """Every drive booted, nothing live: a period or two a heartbeat (each bus's beat, a drive's
    timeout), not the five a heartbeat of a 10 ms period (50 ms host heartbeat). A period a loaded
    machine made the supervisor want (a drive read behind) is not held against it."""
    _, driver = driver_factory(make_config(2))
    supervisor = booted(driver)
    periods, beats, excused = Periods(supervisor).over(10)
    assert periods <= 2 * beats + 2 + excused, (periods, beats, excused)


def due(supervisor: Supervisor) -> float:
    """When a quiet supervisor's next period falls due: the host heartbeat, or the buses' look
    (the drives' heartbeat timeouts, 1 s here, are further)."""
    return min(supervisor.bus.bus_records["can0"].next_beat, supervisor._bus_checked + BUS_CHECK_S + SUPERVISOR_PERIOD_S)


def waits(supervisor: Supervisor, before_due_s: float) -> float:
    """``wait_s`` asked on the supervisor's thread (no beat moves its due time meanwhile)."""
    return float(supervisor.call(lambda: supervisor.wait_s(due(supervisor) - before_due_s)))  # type: ignore[arg-type]


def test_a_quiet_supervisor_waits_until_the_next_heartbeat_is_due(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(make_config(1))
    supervisor = booted(driver)
    assert waits(supervisor, 0.03) == pytest.approx(0.03)
    # never longer: the buses are looked at (approx: the wait is (now + QUIET_WAIT_MAX_S) - now,
    # which rounds below the constant for some clock readings: 0.049999999999954525 in a CI run)
    assert waits(supervisor, 1.0) == pytest.approx(QUIET_WAIT_MAX_S, rel=1e-9)
    assert waits(supervisor, 0.0) == SUPERVISOR_PERIOD_S  # never shorter


def test_a_live_velocity_command_gets_every_period(driver_factory: DriverFactory) -> None:
    """The watchdog and the limit guard of a live command look every SUPERVISOR_PERIOD_S, and
    the command's going live woke the supervisor (the channel's on_live is its wake)."""
    _, driver = driver_factory(make_config(1, watchdog_ms=10_000))
    supervisor = booted(driver)
    drive = driver.drive("joint1")
    drive.enable()
    assert waits(supervisor, 0.03) > SUPERVISOR_PERIOD_S  # enabled, nothing live: quiet
    assert drive.channel.on_live == supervisor.wake  # the drive's channel wakes this supervisor
    woken = threading.Event()

    def on_live() -> None:
        woken.set()
        supervisor.wake()
    drive.channel.on_live = on_live
    drive.set_velocity(10.0)
    assert woken.is_set()
    assert waits(supervisor, 0.03) == SUPERVISOR_PERIOD_S
    drive.quick_stop()


@pytest.mark.parametrize("what", ["a lost drive", "another master's frame"])
def test_what_wants_a_look_every_period_gets_it(driver_factory: DriverFactory, what: str) -> None:
    sim, driver = driver_factory(make_config(1))
    supervisor = booted(driver)
    assert waits(supervisor, 0.03) > SUPERVISOR_PERIOD_S
    if what == "a lost drive":  # (on the supervisor's thread, the record's one writer)
        supervisor.call(lambda: setattr(supervisor.records["joint1"], "lost_since", time.monotonic()))
    else:
        bench = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        try:
            bench.send(can.Message(arbitration_id=0x000, data=bytes([0x80, 1]), is_extended_id=False))
            handle = supervisor.handles["can0"]
            wait_for(lambda: handle.foreign.newest > 0.0, 10.0, "the other master's NMT read")
        finally:
            bench.shutdown()
    assert waits(supervisor, 0.03) == SUPERVISOR_PERIOD_S


def never_by_time(supervisor: Supervisor) -> None:
    """The supervisor waits an hour (it then sends no heartbeat): only a wake brings a period."""
    supervisor.wait_s = lambda now: 3600.0  # type: ignore[method-assign]
    supervisor.wake()  # its current wait ends; the next has no end


def test_a_call_wakes_a_supervisor_waiting_an_hour(driver_factory: DriverFactory) -> None:
    _, driver = driver_factory(make_config(1))
    supervisor = booted(driver)
    never_by_time(supervisor)
    for _ in range(3):  # each call is applied at a period of its own wake
        answer: list[object] = []
        thread = threading.Thread(target=lambda answer=answer: answer.append(supervisor.call(lambda: "applied")),
                                  daemon=True)
        thread.start()
        thread.join(60.0)
        assert answer == ["applied"]


def test_another_masters_frame_wakes_a_supervisor_waiting_an_hour(driver_factory: DriverFactory) -> None:
    sim, driver = driver_factory(make_config(1))
    supervisor = booted(driver)
    drive = driver.drive("joint1")
    never_by_time(supervisor)
    bench = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    try:  # an SDO write to the drive from another client: only another master sends one
        bench.send(can.Message(arbitration_id=0x601, data=bytes([0x2B, 0x40, 0x60, 0, 0x06, 0, 0, 0]),
                               is_extended_id=False))
        wait_for(lambda: bool(drive.watch.foreign_master), 30.0, "the drive marked another master's")
    finally:
        bench.shutdown()


def test_the_channel_wakes_the_supervisor_when_a_command_goes_live() -> None:
    wire = Wire()
    channel = make_channel(wire)
    lives: list[int] = []
    channel.on_live = lambda: lives.append(1)
    enabled(channel)
    for live in (True, True, False, True):
        with channel.command("velocity command") as frames:
            frames.velocity(10 if live else 0, live=live)
    assert len(lives) == 2  # going live twice, not once a command



def test_a_flood_of_another_masters_frames_wakes_the_supervisor_once_a_hold() -> None:
    """The first sign after FOREIGN_HOLD_S without one wakes it; within the hold it looks every
    period anyway (wait_s), so a 1 kHz SYNC of another master's is not 1000 wake-ups a second."""
    traffic = ForeignTraffic(127, (1,))
    wakes: list[int] = []
    traffic.set_wake(lambda: wakes.append(1))
    for when in (100.0, 100.001, 100.2, 100.5, 100.5 + FOREIGN_HOLD_S + 0.001, 100.6):
        traffic.newest = when
    assert len(wakes) == 2
