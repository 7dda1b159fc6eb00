"""The drive system drives only measured wheels and /tf states only measured poses, in a real
rclpy graph (the shipped six-wheel rover on the simulator, as tests/test_odom_truth.py runs it):

- ``on_wheel_loss: continue``, the left wheels' TPDOs silenced while /cmd_vel keeps asking 0.3 m/s
  (their heartbeats go on: late, not lost): every wheel stops, read from the simulated drives,
  /diagnostics names the side, /odom stands still, and once the TPDOs are back the rover drives
  again after /arm;
- while the odometry is not trusted, no /tf is stamped later than the last trusted /odom.

Every wait is on a condition with a hang bound; nothing is decided by the clock."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from virtual_can.scenario import apply_action

from .conftest import wait_for
from .test_odom_truth import LEFT, RIGHT, Rover, stamp_s

pytestmark = pytest.mark.ros


@pytest.fixture
def rover(request: pytest.FixtureRequest) -> Iterator[Rover]:
    rover = Rover(getattr(request, "param", "stop"))
    yield rover
    rover.close()


def silence_left(rover: Rover, on: bool) -> None:
    for node in (1, 2, 3):  # the left wheels, can0
        apply_action(rover.sim, {"action": "tpdos", "node": node, "channel": "can0", "on": on})


def tf_stamps(rover: Rover, since: int) -> list[float]:
    return [stamp_s(t) for m in rover.tf[since:] for t in m.transforms]


def untrusted(msg: Any) -> bool:
    return bool(msg.pose.covariance[0] >= 1e6)


@pytest.mark.parametrize("rover", ["continue"], indirect=True)
def test_in_continue_a_late_side_stops_every_wheel_and_is_named(rover: Rover) -> None:
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.1 and rover.tf, "0.1 m straight")
    tf_before = max(tf_stamps(rover, 0))
    tf_from = len(rover.tf)
    silence_left(rover, on=False)
    # /cmd_vel keeps coming: the right wheels must stop all the same
    rover.drive_until(0.3, 0.0, lambda: rover.sim_stopped(RIGHT) and rover.sim_stopped(LEFT), "every wheel stopped")
    assert "the left side has no usable wheel" in rover.system.halted, rover.system.halted
    rover.drive_until(0.3, 0.0, lambda: rover.said("the left side has no usable wheel"), "the side on /diagnostics")
    # judged from the first /odom that says it is not trusted (the newest one held may be older)
    rover.drive_until(0.3, 0.0, lambda: untrusted(rover.odom[-1]), "/odom not trusted")
    seen = next(i for i in range(len(rover.odom) - 1, -1, -1) if not untrusted(rover.odom[i])) + 1
    held = rover.odom[seen].pose.pose.position.x
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > seen + 25, "25 more /odom")
    after = [(m.pose.pose.position.x, untrusted(m), stamp_s(m)) for m in rover.odom[seen:]]
    assert all(x == held and not_trusted for x, not_trusted, _ in after), (held, after)
    # /tf: nothing stamped later than what was measured (the silence's first PDO periods at most)
    assert all(t <= tf_before + 0.5 for t in tf_stamps(rover, tf_from)), (tf_before, tf_stamps(rover, tf_from))
    silence_left(rover, on=True)
    wait_for(lambda: all(not rover.driver.drive(n).cache.data_stale() for n in LEFT), 30.0, "the left side heard")
    rover.arm()  # /arm: the left wheels, stopped as told, are enabled again and taken back
    x = rover.odom[-1].pose.pose.position.x
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > x + 0.1, "driving again after /arm")


def test_tf_is_not_advanced_while_odometry_is_not_trusted(rover: Rover) -> None:
    rover.arm()
    rover.drive_until(0.3, 0.0, lambda: len(rover.tf) > 5 and rover.odom[-1].pose.pose.position.x > 0.05, "/tf")
    silence_left(rover, on=False)
    rover.drive_until(0.3, 0.0, lambda: untrusted(rover.odom[-1]), "/odom not trusted")
    trusted = [stamp_s(m) for m in rover.odom if not untrusted(m)]
    tf_from = len(rover.tf)
    seen = len(rover.odom)
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > seen + 50, "50 more /odom")
    assert all(untrusted(m) for m in rover.odom[seen:])
    late = [t for t in tf_stamps(rover, tf_from) if t > max(trusted)]
    assert not late, f"/tf stamped after the last trusted /odom ({max(trusted)}): {late[:5]}"
    silence_left(rover, on=True)


@pytest.mark.parametrize("rover", ["continue"], indirect=True)
def test_a_wheel_taken_back_is_not_stopped_between_operation_enabled_and_the_enable_counted(rover: Rover) -> None:
    """``on_wheel_loss: continue``: a wheel out whose data is back is stopped as told; its /arm
    then reaches Operation Enabled (usable) a moment before the enable is counted. A hook holds the
    enable in that moment, right after its last transition, until the drive shows Operation
    Enabled and two drive-system ticks have run while the book still has the wheel out: none of
    them tells it to stop, and the enable ends armed (a loaded CI saw "interrupted by quick stop")."""
    wheel = LEFT[0]
    drive = rover.driver.drive(wheel)
    rover.arm()
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.05, "0.05 m straight")
    apply_action(rover.sim, {"action": "tpdos", "node": 1, "channel": "can0", "on": False})
    assert rover.system.wheels_out is not None
    book = rover.system.wheels_out
    rover.drive_until(0.3, 0.0, lambda: wheel in book.out and rover.sim_stopped([wheel]), f"{wheel} out and stopped")
    apply_action(rover.sim, {"action": "tpdos", "node": 1, "channel": "can0", "on": True})
    wait_for(lambda: not drive.cache.data_stale(), 30.0, f"{wheel} heard again")
    # the drive system's stop of it done (sent while it was unheard, it failed and is tried again):
    # an /arm meanwhile is refused, "busy with quick stop"
    system = rover.system
    wait_for(lambda: wheel not in system.stop_failing and drive.channel.busy is None
             and ((stop := system._stops.get(wheel)) is None or stop.done()), 30.0, f"{wheel}'s stop done")
    held: list[tuple[int, bool, bool]] = []  # (ticks run in the window, out all along, usable)

    def hold_in_the_window(point: str) -> None:
        if point != "enable: sent transition 4":
            return
        wait_for(lambda: drive.snapshot().verdict.usable, 30.0, f"{wheel} Operation Enabled, usable")
        ticks = rover.system._ticks
        wait_for(lambda: rover.system._ticks >= ticks + 2, 30.0, "two drive-system ticks in the window")
        held.append((rover.system._ticks - ticks, wheel in book.out, drive.snapshot().verdict.usable))

    drive.channel.set_hook(hold_in_the_window)
    try:
        drive.enable()  # raises "interrupted by quick stop" where a tick in the window told it to stop
    finally:
        drive.channel.set_hook(None)
    assert held and held[0][0] >= 2 and held[0][1] and held[0][2], held  # the window was reached and held
    wait_for(lambda: wheel not in book.out, 30.0, f"{wheel} back in the drive system")
    x = rover.odom[-1].pose.pose.position.x
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > x + 0.05, "driving on with it")
    assert wheel not in book.out and not rover.sim_stopped([wheel])
