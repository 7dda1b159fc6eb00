"""The simulated drives judge the host's heartbeat on a time their starvation cannot move (issue
73): a bus server's reader thread that has read the host's frames and not yet put them on the bus
(a starved thread of the simulator's process, held behind another real-time burst) does not let
the SYNCs stamped meanwhile convict the host of a silence. The kernel's count of the bytes it
received from the host's connection, against the reader's count of those it put on the bus, bounds
the bus time the drives are judged on. The reader is held by a hook on its handling of a host
heartbeat; the hold lasts until a listener has heard the bus's SYNCs stamped twice the consumer
time past the hold (an order of stamps, not a duration)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService
from virtual_can.client import Client

from .conftest import wait_for
from .test_sim_starved import HANG_S, HOST_NODE, HOST_TIMEOUT_S, enabled_drive, listening

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]


class ReaderHold:
    """Holds the bus server's reader of the host's connection in the handling of a host heartbeat
    it has read (the frames behind it stay in its hand and its socket) once armed, until released."""

    def __init__(self, handle: Callable[[Client, str], None]) -> None:
        self._handle = handle
        self.armed = threading.Event()
        self.holding = threading.Event()
        self.release = threading.Event()
        self.held_at = 0.0  # the bus stamps' clock when the hold began

    def __call__(self, client: Client, line: str) -> None:
        words = line[1:-1].split()
        if (self.armed.is_set() and not self.release.is_set() and words[:1] == ["send"]
                and int(words[1], 16) == 0x700 + HOST_NODE):
            self.held_at = time.time()
            self.holding.set()
            self.release.wait(HANG_S)
        self._handle(client, line)


def test_a_host_heartbeat_held_in_a_starved_reader_does_not_trip_the_drive(
        driver_factory: DriverFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    sim, _, runner = enabled_drive(driver_factory)
    hold = ReaderHold(Client._handle)
    monkeypatch.setattr(Client, "_handle", lambda client, line: hold(client, line))  # noqa: PLW0108 (binds as a method)
    with listening(sim) as listener:
        hold.armed.set()
        try:
            wait_for(hold.holding.is_set, HANG_S, "the host's reader held on a heartbeat")
            beyond = hold.held_at + 2 * HOST_TIMEOUT_S
            wait_for(lambda: any(m.arbitration_id == 0x080 and m.timestamp > beyond for m in list(listener.frames)),
                     HANG_S, "a SYNC stamped twice the consumer time past the hold")
            for _ in range(2):  # the runner has looked at it and ticked (a tick judges the watch)
                runner.call(lambda: None)
            tripped = listener.host_lost_emcy(1)
        finally:
            hold.release.set()
        seen = len(listener.host_beats_after(hold.held_at))
        wait_for(lambda: len(listener.host_beats_after(hold.held_at)) > seen + 2, HANG_S,
                 "the host's heartbeats on the bus again")
        assert not tripped and not listener.host_lost_emcy(1)
    assert not runner.call(lambda: runner.drive(1).faults.heartbeat_deaf)
