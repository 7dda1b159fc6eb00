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
    held = rover.odom[-1].pose.pose.position.x
    seen = len(rover.odom)
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > seen + 25, "25 more /odom")
    assert all(m.pose.pose.position.x == held for m in rover.odom[seen:])
    assert all(untrusted(m) for m in rover.odom[seen:])
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
