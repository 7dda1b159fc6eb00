"""Odometry across two buses (issue 70), in a real rclpy graph: the shipped six-wheel config (the
left wheels on can0, the right on can1), the simulator over socketcand, the driver node and the
drive system as rover_driver runs them, a probe on /odom, /tf and /joint_states
(tests/test_odom_truth.py's Rover).

- Samples of the two buses are paired by the moment they measured, not by the tick that reads
  them: with SYNCs of 61 ms on can0 and 89 ms on can1 (every skew between their SYNCs, in turn),
  driving straight on six identical wheels, /odom's heading stays put while the rover cruises,
  and at standstill it is the simulated wheels' own. The drives' physics ticks every 10 ms here:
  a drive that answered a SYNC from its last tick (not the SYNC's moment) sent samples up to a
  tick old, at every age in turn (the SYNC periods are no multiple of the tick), and the heading
  swung by a tick's travel; the driver that stamped a sample when it reached the bus (not at the
  SYNC it answers) paired them by the drives' reply times. While cruising, its median is the
  simulated wheels' own heading (their shafts read with their speeds, moved to one moment).
- One bus answering SYNC late (its simulated drives' ``sim:`` sync_answer_delay_ms: 30 ms after
  each SYNC, or 5-30 ms at random, each drive's frames in order; the data of the SYNC's moment),
  the other at once: /odom's cruise heading is still the wheels' own. A driver that stamped the
  answers when they came, or an odometry that took a wheel's steady lateness for its clocks'
  offset, leans it by a side's travel in the lateness (25 mrad at 30 ms).
- One bus dead while driving (can1 drops every frame for 175 /odom messages, 3.5 s at 50 Hz):
  no /odom with a measured covariance and no /tf stamped past the last can1 measurement, while
  the probe is shown to hear /odom and /joint_states all along; once can1 is back and the rover
  re-armed, it drives again with a measured /odom and /tf.

Counts of messages and states decide; no wall-clock bound."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from can_config.errors import RovercanError
from virtual_can.scenario import apply_action

from .conftest import wait_for
from .test_odom_truth import LEFT, RIGHT, Rover, stamp_s

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from geometry_msgs.msg import Twist  # noqa: E402

from motor_driver.rover.odometry import UNKNOWN_VARIANCE  # noqa: E402

#: SYNC periods whose phases slide past each other: every skew between the buses' SYNCs comes by,
#: and every phase of a SYNC within the drives' physics tick
SKEWED_SYNCS_S = {"can0": 0.061, "can1": 0.089}
#: the simulated drives' physics tick: 10 ms (5 times the simulator's own), so that a sample of a
#: drive's last tick rather than of its SYNC's moment shows beyond the machine's timing
SIM_TICK_S = 0.01
SPEED_M_S = 0.5
#: "yaw 0": the middle half of /odom's headings while cruising straight (25th to 75th percentile)
#: lies within the travel of two milliseconds of pairing error, SPEED_M_S * 2 ms / 0.6 m track =
#: 1.67 mrad: each bus's simulator places its SYNC's moment by the least handling delay it saw, and
#: a loaded machine moves that by up to about a millisecond a bus (0.85 mrad measured beside two
#: busy loops per core; 0.2-0.35 quiet). A sample up to a tick old, or stamped at its reply, spreads
#: it by a tick's travel (8.3 mrad for 10 ms; measured 4.1-7.6 mrad before the fix). The middle half:
#: a simulator starved of the CPU for longer than a SYNC period answers a SYNC after the next one
#: (no real drive does: CiA 301's synchronous window), a sample now and then that the wider spread
#: below still bounds.
CRUISE_YAW_MIDDLE_RAD = SPEED_M_S * 0.002 / 0.6
#: /odom's heading may wander this much (its 10th to 90th percentile) while cruising straight, a
#: simulator starved now and then included. Pairing a can0 sample with a can1 sample of another
#: SYNC swings it by up to SPEED_M_S * 89 ms / 0.6 m = 74 mrad each way (72 mrad measured before
#: that fix)
CRUISE_YAW_SPREAD_RAD = 0.03
STANDSTILL_YAW_TOLERANCE_RAD = 0.002
#: can1's drives answer each SYNC this much late (well inside both SYNC periods), can0's at once.
#: /odom's heading while cruising is then judged by its median against the simulated wheels' own,
#: within CRUISE_YAW_MIDDLE_RAD: samples paired by their reply time rather than their SYNC's moment
#: lean it by SPEED_M_S * 30 ms / 0.6 m = 25 mrad, which a spread bound does not see
LATE_ANSWER_S = 0.03
LOSS_ODOM_MESSAGES = 175  # 3.5 s at odom_rate_hz 50
#: a measured /odom is stamped at most this much past its newest can1 sample: the bus stamp
#: aligned to the receive clock by the least latency seen (about a ms); the defect this catches was
#: a stamp of the other bus's newest, up to 3 s past
STAMP_SLACK_S = 0.005


@pytest.fixture
def skewed() -> Iterator[Rover]:
    rover = Rover("stop", SKEWED_SYNCS_S, sim_tick_s=SIM_TICK_S)
    yield rover
    rover.close()


@pytest.fixture
def rover() -> Iterator[Rover]:
    rover = Rover("stop")
    yield rover
    rover.close()


def yaw(msg: Any) -> float:
    q = msg.pose.pose.orientation
    return 2.0 * math.atan2(q.z, q.w)


def measured(msg: Any) -> bool:
    return bool(msg.pose.covariance[0] < UNKNOWN_VARIANCE)


def sim_wheel_yaw(rover: Rover) -> float:
    """The heading the simulated wheels' own shafts give (the simulator's state, not the driver's)."""
    cfg = rover.config.drive_system
    assert cfg is not None

    def wheel_rad(name: str) -> float:
        drive = next(d for d in rover.config.drives if d.name == name)
        runner = rover.sim.simulator_for(drive.node_id, drive.bus)
        theta = float(runner.call(lambda: runner.drive(drive.node_id).theta))  # type: ignore[arg-type]
        return (-theta if drive.invert else theta) / drive.gear_ratio

    left = sum(wheel_rad(n) for n in LEFT) / len(LEFT)
    right = sum(wheel_rad(n) for n in RIGHT) / len(RIGHT)
    return (right - left) * cfg.wheel_radius_m / cfg.track_width_m


def cruise_yaws(rover: Rover, each: Callable[[], object] = lambda: None) -> list[float]:
    """Drive 2.5 m straight (``each()`` at every /odom); /odom's measured headings from 0.5 m on
    (accelerated: cruising), sorted. A measured /odom comes with new samples from both sides: at
    least at can1's SYNC rate (89 ms: 45 over the 4 s of cruise), at most at the step's (50 Hz)."""
    rover.drive_until(SPEED_M_S, 0.0, lambda: each() or rover.odom[-1].pose.pose.position.x > 2.5, "2.5 m straight")
    cruise = [yaw(m) for m in rover.odom if 0.5 < m.pose.pose.position.x <= 2.5 and measured(m)]
    assert len(cruise) > 30, len(cruise)
    return sorted(cruise)


def sim_cruise_yaw(rover: Rover) -> float:
    """The heading the simulated wheels' shafts give while cruising (every wheel at a steady speed):
    each read on its simulator's thread with its speed and the moment its physics is of, and moved
    on at that speed to one common moment (the two buses' simulators are read one after the other)."""
    cfg = rover.config.drive_system
    assert cfg is not None
    read: dict[str, tuple[float, float, float]] = {}
    for drive in rover.config.drives:
        runner = rover.sim.simulator_for(drive.node_id, drive.bus)
        read[drive.name] = runner.call(runner.drive(drive.node_id).shaft)  # type: ignore[assignment]
    common = max(at for _, _, at in read.values())

    def wheel_rad(name: str) -> float:
        drive = next(d for d in rover.config.drives if d.name == name)
        theta, omega, at = read[name]
        theta += omega * (common - at)
        return (-theta if drive.invert else theta) / drive.gear_ratio

    left = sum(wheel_rad(n) for n in LEFT) / len(LEFT)
    right = sum(wheel_rad(n) for n in RIGHT) / len(RIGHT)
    return (right - left) * cfg.wheel_radius_m / cfg.track_width_m


def test_straight_on_two_buses_with_skewed_syncs_keeps_the_heading(skewed: Rover) -> None:
    rover = skewed
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    start = sim_wheel_yaw(rover)
    cruise = cruise_yaws(rover)
    truth = sim_cruise_yaw(rover) - start
    n = len(cruise)
    assert abs(cruise[n // 2] - truth) < CRUISE_YAW_MIDDLE_RAD, (cruise[n // 2], truth)
    low, high = cruise[n // 10], cruise[-1 - n // 10]  # the 10th and 90th percentiles
    assert high - low < CRUISE_YAW_SPREAD_RAD, (low, high, cruise[0], cruise[-1])
    middle = cruise[3 * n // 4] - cruise[n // 4]  # the 25th to 75th percentile
    assert middle < CRUISE_YAW_MIDDLE_RAD, (middle, low, high)
    rover.cmd.publish(Twist())
    rover.stand_still()
    seen = len(rover.odom)
    wait_for(lambda: len(rover.odom) > seen + 5 and measured(rover.odom[-1]), 30.0, "/odom at standstill")
    truth = sim_wheel_yaw(rover) - start
    assert abs(yaw(rover.odom[-1]) - truth) < STANDSTILL_YAW_TOLERANCE_RAD, (yaw(rover.odom[-1]), truth)


def arm_when_back(rover: Rover) -> None:
    """Every wheel enabled once it is configured again: an enable refused meanwhile (its
    re-configuration under way, an SDO unanswered on a crowded machine) is tried again."""
    for name in LEFT + RIGHT:
        drive = rover.driver.drive(name)

        def armed(drive: Any = drive) -> bool:
            if drive.snapshot().verdict.usable:
                return True
            if not drive.cache.booted or drive.cache.lost:
                return False
            try:
                drive.enable()
            except RovercanError:
                return False
            return bool(drive.snapshot().verdict.usable)

        wait_for(armed, 60.0, f"{name} armed again")


def newest_can1_stamp(rover: Rover) -> float:
    return max(rover.driver.drive(n).snapshot().stamp for n in RIGHT)


def test_a_dead_bus_publishes_nothing_measured_and_the_rover_drives_again(rover: Rover) -> None:
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2 and len(rover.tf) > 2, 30.0, "/odom and /tf")
    rover.drive_until(0.3, 0.0, lambda: rover.odom[-1].pose.pose.position.x > 0.2, "0.2 m")
    odom_from, tf_from, joints_from = len(rover.odom), len(rover.tf), len(rover.joints)
    apply_action(rover.sim, {"action": "frames", "channel": "can1", "drop": 1.0})
    rover.drive_until(0.3, 0.0, lambda: len(rover.odom) > odom_from + LOSS_ODOM_MESSAGES, "the loss")
    last_can1 = newest_can1_stamp(rover)  # nothing of can1 measured after this
    odom_to, tf_to, joints_to = len(rover.odom), len(rover.tf), len(rover.joints)
    apply_action(rover.sim, {"action": "frames", "channel": "can1", "drop": 0.0})

    loss = rover.odom[odom_from:odom_to]
    assert joints_to > joints_from and any(not measured(m) for m in loss)  # the probe heard all along
    late = [(stamp_s(m) - last_can1, m.pose.covariance[0]) for m in loss
            if measured(m) and stamp_s(m) > last_can1 + STAMP_SLACK_S]
    assert not late, f"{len(late)} of {len(loss)} /odom in the loss measured, past can1's last sample by: {late[:5]}"
    tf_late = [stamp_s(t) - last_can1 for m in rover.tf[tf_from:tf_to] for t in m.transforms
               if stamp_s(t) > last_can1 + STAMP_SLACK_S]
    assert not tf_late, f"/tf stamped past can1's last sample by {tf_late[:5]}"

    arm_when_back(rover)  # can1's wheels configured again, disabled: armed again, as after any loss
    x = rover.odom[-1].pose.pose.position.x
    tf_back = len(rover.tf)
    rover.drive_until(0.3, 0.0, lambda: measured(rover.odom[-1]) and rover.odom[-1].pose.pose.position.x > x + 0.2,
                      "0.2 m more, measured")
    wait_for(lambda: len(rover.tf) > tf_back, 30.0, "/tf again")
    assert stamp_s(rover.tf[-1].transforms[0]) > last_can1


class AnswerLag:
    """How late each bus's answers came: the median time between a wheel's SYNC (its state's stamp,
    the bus's clock) and the state's arrival (the receive thread's clock), over every look (not the
    least: a state whose newest frame is an event-driven TPDO carries that frame's own stamp)."""

    def __init__(self, rover: Rover) -> None:
        self.rover = rover
        self.seen_s: dict[str, list[float]] = {"can0": [], "can1": []}

    def look(self) -> None:
        wall_minus_mono = time.time() - time.monotonic()
        for bus, names in (("can0", LEFT), ("can1", RIGHT)):
            for name in names:
                state = self.rover.driver.drive(name).snapshot()
                self.seen_s[bus].append(state.rx_monotonic + wall_minus_mono - state.stamp)

    def median_s(self, bus: str) -> float:
        seen = sorted(self.seen_s[bus])
        return seen[len(seen) // 2]


@pytest.fixture
def late_can1(request: pytest.FixtureRequest) -> Iterator[Rover]:
    """The skewed rover whose can1 drives answer each SYNC late from their start: (delay, jitter)."""
    rover = Rover("stop", SKEWED_SYNCS_S, sim_tick_s=SIM_TICK_S, sync_answer_s={"can1": request.param})
    yield rover
    rover.close()


@pytest.mark.parametrize("late_can1", [(LATE_ANSWER_S, 0.0), (0.005, 0.025)], ids=["fixed", "random_in_order"],
                         indirect=True)
def test_one_bus_answering_sync_late_leaves_the_heading_straight(late_can1: Rover) -> None:
    """can1's drives answer each SYNC late (30 ms; or 5-30 ms at random, their frames in order),
    can0's at once: /odom's heading while cruising is the simulated wheels' own (its median), and
    as steady as with prompt answers."""
    rover = late_can1
    rover.arm()
    wait_for(lambda: len(rover.odom) > 2, 30.0, "/odom")
    start = sim_wheel_yaw(rover)
    lag = AnswerLag(rover)
    cruise = cruise_yaws(rover, lag.look)
    truth = sim_cruise_yaw(rover) - start
    lag0, lag1 = lag.median_s("can0"), lag.median_s("can1")
    n = len(cruise)
    median, low, high = cruise[n // 2], cruise[n // 10], cruise[-1 - n // 10]
    said = (f"/odom's cruise heading: median {median * 1e3:.2f} mrad, 10th-90th percentile {low * 1e3:.2f} to"
            f" {high * 1e3:.2f}; the wheels' {truth * 1e3:.2f} mrad; median answer lag can0 {lag0 * 1e3:.1f} ms,"
            f" can1 {lag1 * 1e3:.1f} ms")
    assert abs(median - truth) < CRUISE_YAW_MIDDLE_RAD, said
    assert high - low < CRUISE_YAW_SPREAD_RAD, said
    delay = rover.sim.simulator_for(1, "can1").drive(1).faults.sync_delay_s
    assert lag1 - lag0 > 0.6 * delay, said  # can1's answers came late, can0's did not
