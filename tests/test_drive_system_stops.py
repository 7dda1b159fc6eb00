"""The drive system reads every stop it hands to its worker: a wheel left out whose quick stop
raises anything (``Boom``, no type the code names) is logged with the cause, counted, said on
/diagnostics (ERROR) and told to stop again. The shipped six-wheel rover on the simulator, the
driver node and the drive system in a real rclpy graph (tests/test_odom_truth.py's rig)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from virtual_can.scenario import apply_action

from .conftest import wait_for

pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from .test_odom_truth import Rover  # noqa: E402

WHEEL = "wheel_front_right"


class Boom(Exception):
    """An exception of a type no code of the driver names."""


@pytest.fixture
def rover() -> Iterator[Rover]:
    rover = Rover("continue")
    yield rover
    rover.close()


def test_a_left_out_wheels_stop_that_raises_is_said_counted_and_tried_again(
        rover: Rover, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    drive = rover.driver.drive(WHEEL)
    calls: list[int] = []

    def quick_stop(*args: Any, **kwargs: Any) -> None:
        calls.append(1)
        raise Boom(f"stop {len(calls)} failed")

    monkeypatch.setattr(drive, "quick_stop", quick_stop)
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.05, "driving")
    apply_action(rover.sim, {"action": "unplug", "node": 1, "channel": "can1"})  # wheel_front_right
    rover.drive_until(0.3, 0.0, lambda: len(calls) >= 3, "its stop tried again after it raised")
    assert rover.system.stop_failures >= 2 and "Boom: stop" in rover.system.stop_failing[WHEEL]

    def said() -> bool:
        return any(st.name == "rovercan: drive_system" and st.level == bytes([2]) and "Boom" in st.message
                   for array in rover.diags for st in array.status)

    wait_for(said, 30.0, "the failed stop on /diagnostics")
    lines = [r for r in caplog.records if "Boom" in r.getMessage() and r.levelno >= logging.ERROR]
    assert 1 <= len(lines) < len(calls)  # said with its cause, repeats held back and counted


def test_a_wheel_whose_stop_waits_holds_no_other_wheels_stop(rover: Rover, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two wheels told to stop: the first one's stop waits for its drive (unconfirmed: up to a
    second each), the second's frame goes out meanwhile and its drive stops. One worker for all
    wheels queued the second behind the first."""
    rover.arm()
    first, second = rover.driver.drive("wheel_front_left"), rover.driver.drive("wheel_rear_left")
    release, waiting = threading.Event(), threading.Event()

    def unconfirmed(*args: Any, **kwargs: Any) -> None:
        waiting.set()
        release.wait(60.0)

    monkeypatch.setattr(first, "quick_stop", unconfirmed)
    try:
        rover.system._tell_to_stop(first.name)
        wait_for(waiting.is_set, 30.0, "the first wheel's stop under way")
        rover.system._tell_to_stop(second.name)
        runner = rover.sim.simulator_for(3, "can0")
        wait_for(lambda: runner.call(lambda: runner.drive(3).state.name) != "OPERATION_ENABLED", 30.0,
                 "the second wheel stopped while the first one's stop waits")
        wait_for(lambda: second.cache.state.name != "OPERATION_ENABLED", 30.0, "the driver seeing it stop")
        assert not release.is_set()  # the first one's stop still waits
    finally:
        release.set()
