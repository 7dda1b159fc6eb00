"""Tier 1: the odometry counts only usable wheels, judged by their verdicts (nodes/rover/wheels.py's
odometry_sample into motor_driver/rover/odometry.py, pure): a wheel disabled or left out adds nothing,
a wheel silent for less than its staleness bound leaves no heading error (whichever moment it
drops out and whether it is heard again or lost), and samples are ordered by the driver's
monotonic receive time, so a step back of the wall clock does not freeze the odometry.

The wheels are driven as a skid-steer rover drives them: every wheel of a side turns alike, so
the heading the wheels give at each SYNC is known exactly; each wheel's PDO comes every SYNC
(10 ms) and the odometry steps every 20 ms, as the drive system's tick does."""

from __future__ import annotations

import dataclasses
import itertools
import math
import struct
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from motor_driver.drive import DriveState
from motor_driver.drive.verdict import judge
from motor_driver.protocol.cia402 import State
from motor_driver.rover.odometry import WheelOdometry
from nodes.rover.wheels import odometry_sample, odometry_samples

from .drive_states import drive_state
from .test_batch_receive import PLAN, T0, Rig

LEFT, RIGHT = ("fl", "ml", "rl"), ("fr", "mr", "rr")
TRACK_M, RADIUS_M = 0.6, 0.1
SYNC_S, TICK_S = 0.01, 0.02
STALE_S = 5 * SYNC_S  # stale_after_syncs: 5
PERIODS = dict.fromkeys(LEFT + RIGHT, SYNC_S)  # a TPDO every SYNC
BASE_FIELDS: dict[str, object] = dict(
    name="w", node_id=1, angle_deg=0.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0x0637,
    state=State.OPERATION_ENABLED, mode=9, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
    error_code=0, error_text="", stamp=1.0e9, heartbeat_age_s=0.01, target_reached=False,
    data_age_s=0.0, stale=False, foreign_master="", reference=1, rx_monotonic=100.0)


class Rover:
    """Six wheels turning at their side's rate (deg per SYNC); what each last sent, and when."""

    def __init__(self, left_deg: float, right_deg: float) -> None:
        self.rate = {n: left_deg if n in LEFT else right_deg for n in LEFT + RIGHT}
        self.angle = dict.fromkeys(LEFT + RIGHT, 0.0)
        self.sent = {n: (0.0, 0.0, 0) for n in LEFT + RIGHT}  # (angle, receive time, SYNC number)
        self.odometry = WheelOdometry(LEFT, RIGHT, TRACK_M, RADIUS_M)
        self.sync = 0
        self.started = False

    def run_sync(self, silent: frozenset[str] = frozenset()) -> None:
        self.sync += 1
        for n in LEFT + RIGHT:
            self.angle[n] += self.rate[n]
            if n not in silent:
                self.sent[n] = (self.angle[n], 100.0 + self.sync * SYNC_S, self.sync)

    def state(self, name: str, now: float, **changes: object) -> DriveState:
        angle, rx, _ = self.sent[name]
        age = now - rx
        fields: dict[str, object] = {"name": name, "angle_deg": angle, "rx_monotonic": rx, "data_age_s": age,
                                     "stale": age > STALE_S, "enabled": age <= STALE_S, "stamp": 1.0e9 + rx}
        return drive_state(**(BASE_FIELDS | fields | changes))

    def step(self, now: float, changes: dict[str, dict[str, object]] | None = None) -> float:
        changes = changes or {}
        states = {n: self.state(n, now, **changes.get(n, {})) for n in LEFT + RIGHT}
        step = self.odometry.step(odometry_samples(states, (LEFT, RIGHT), PERIODS))
        assert step.trusted or not self.started, step.why_not  # the first step starts every wheel's reference
        self.started = True
        return step.pose.yaw_rad

    def wheels_yaw(self, sync: int, without: str = "") -> float:
        """The heading the wheels give from the first step (SYNC 2) to ``sync`` (every wheel of a
        side alike but ``without``, which stood still)."""
        left = next(self.rate[n] for n in LEFT if n != without)
        right = next(self.rate[n] for n in RIGHT if n != without)
        return math.radians(right - left) * (sync - 2) * RADIUS_M / TRACK_M


def same_heading(a: float, b: float) -> bool:
    return abs(math.remainder(a - b, math.tau)) < 1e-9


def test_a_disabled_wheel_adds_nothing_to_odometry() -> None:
    """Back on the bus but disabled (not re-armed), reporting a standing shaft: its zero travel
    must not pull its side's mean while the others drive on."""
    rover = Rover(5.0, 5.0)  # straight
    for k in range(1, 101):
        if k == 20:
            rover.rate["ml"] = 0.0
        rover.run_sync()
        if k % 2 == 0:
            changes: dict[str, dict[str, object]] = \
                {"ml": {"state": State.SWITCH_ON_DISABLED, "enabled": False}} if k >= 20 else {}
            yaw = rover.step(100.0 + k * SYNC_S + 0.001, changes)
            assert same_heading(yaw, 0.0), (k, yaw)


def test_a_wheel_quick_stopped_or_left_out_adds_nothing() -> None:
    for changes in ({"state": State.QUICK_STOP_ACTIVE, "enabled": False}, {"out": True}):
        rover = Rover(4.0, 6.0)  # a turn
        for k in range(1, 61):
            if k == 10:
                rover.rate["fr"] = 0.0  # it stopped (or, out, is dragged: either way not the rover's motion)
            rover.run_sync()
            if k % 2 == 0:
                now = 100.0 + k * SYNC_S + 0.001
                states = {n: rover.state(n, now) for n in LEFT + RIGHT}
                if k >= 10 and "out" in changes:
                    states["fr"] = out_of_the_drive_system(states["fr"])
                elif k >= 10:
                    states["fr"] = rover.state("fr", now, **changes)
                step = rover.odometry.step(odometry_samples(states, (LEFT, RIGHT), PERIODS))
                assert step.trusted or k == 2, step.why_not
                assert same_heading(step.pose.yaw_rad, rover.wheels_yaw(k, without="fr")), (k, changes)


def out_of_the_drive_system(state: DriveState) -> DriveState:
    facts = state.facts._replace(left_out="it was late")
    return dataclasses.replace(state, judged=(facts, judge(facts)))


@settings(max_examples=150, deadline=None)
@given(wheel=st.sampled_from(LEFT + RIGHT), start=st.integers(3, 60), syncs=st.integers(1, 4),
       then_lost=st.booleans(), left=st.floats(-8.0, 8.0), right=st.floats(-8.0, 8.0))
def test_a_silence_shorter_than_the_staleness_bound_leaves_no_heading_error(
        wheel: str, start: int, syncs: int, then_lost: bool, left: float, right: float) -> None:
    """A wheel drops out at a random SYNC for fewer SYNCs than its staleness bound, then is heard
    again or lost for good: at every step /odom's heading is the one the wheels give."""
    rover = Rover(left, right)
    lost_from = start + syncs
    for k in range(1, 100):
        silent = start <= k < start + syncs or (then_lost and k >= lost_from)
        rover.run_sync(frozenset({wheel}) if silent else frozenset())
        if k % 2:
            continue
        changes: dict[str, dict[str, object]] = {wheel: {"lost": True, "fault": True}} \
            if then_lost and k >= lost_from else {}
        yaw = rover.step(100.0 + k * SYNC_S + 0.001, changes)
        assert same_heading(yaw, rover.wheels_yaw(k)), (k, yaw, rover.wheels_yaw(k))


def test_a_side_late_beyond_a_bridge_starts_anew_and_the_pose_never_jumps() -> None:
    """The right side's TPDOs stop (its SYNC stopped, its heartbeats on: late, never lost) while
    the rover turns, then come back in the same reference. For 0.3 s its next samples bridge the
    gap: the heading is the wheels' at the end. For 1 s (beyond MAX_BRIDGED_GAP_S) the gap's
    travel of both sides was one straight step, a chord (a ten-second circle put /odom metres
    off, trusted); now the late wheels start anew: no step moves the pose further than a step's
    travel, and the travel not measured is counted as estimated (the covariance's)."""
    most_m = math.radians(8.0) * 2 * RADIUS_M * 1.001  # a step (two SYNCs) of the faster side
    for gap, bridged in ((range(40, 70), True), (range(40, 140), False)):
        rover = Rover(4.0, 8.0)
        poses = []
        for k in range(1, 200):
            rover.run_sync(frozenset(RIGHT) if k in gap else frozenset())
            if k % 2 == 0:
                now = 100.0 + k * SYNC_S + 0.001
                step = rover.odometry.step(odometry_samples({n: rover.state(n, now) for n in LEFT + RIGHT},
                                                            (LEFT, RIGHT), PERIODS))
                poses.append(step.pose)
        moved = [math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) for a, b in itertools.pairwise(poses)]
        if bridged:
            assert same_heading(poses[-1].yaw_rad, rover.wheels_yaw(198)), gap
            assert step.estimated_m == 0.0
        else:
            assert max(moved) <= most_m, (max(moved), most_m)
            assert step.trusted and step.estimated_m >= math.radians(4.0) * 100 * RADIUS_M, step  # the left side over the gap


def test_a_step_back_of_the_wall_clock_does_not_freeze_odometry() -> None:
    """The frames' stamps (CLOCK_REALTIME) step back 30 s (chrony at boot); the receive times
    (monotonic) go on: the odometry goes on counting."""
    rover = Rover(5.0, 5.0)
    x = []
    for k in range(1, 41):
        rover.run_sync()
        if k % 2 == 0:
            now = 100.0 + k * SYNC_S + 0.001
            wall = 1.0e9 + k * SYNC_S - (30.0 if k > 20 else 0.0)
            states = {n: rover.state(n, now, stamp=wall) for n in LEFT + RIGHT}
            step = rover.odometry.step(odometry_samples(states, (LEFT, RIGHT), PERIODS))
            x.append(step.pose.x_m)
    assert all(b > a for a, b in itertools.pairwise(x[1:])), x  # it never stood still (the first starts)
    assert math.isclose(x[-1], math.radians(5.0 * (40 - 2)) * RADIUS_M, rel_tol=1e-9)  # from the first sample


def test_a_tpdo_without_a_position_is_no_new_sample_of_it(tmp_path: Path) -> None:
    """A drive answers each SYNC with its position TPDO (0x281) and then its torque and statusword
    (0x381), and sends a statusword on change (0x181): only the first carries a position. The wheel
    sample the odometry reads is the position's own (its TPDO's receive time and SYNC stamp), so a
    step between the two TPDOs and a step after them read one sample, not two: stamped by the
    newest frame, the same position came as a new one (kept twice, published as a new measurement)."""
    rig = Rig(tmp_path)
    try:
        by_cob = {p.cob_id: p for p in PLAN.tpdos}
        position = next(p for p in PLAN.tpdos if 0x6064 in p.indexes)
        others = [p for p in PLAN.tpdos if 0x6064 not in p.indexes]
        assert position.cob_id == 0x281 and {p.cob_id for p in others} == {0x181, 0x381}, by_cob
        rig.network.notify(0x080, bytearray(), T0)
        rig.network.notify(position.cob_id, bytearray(struct.pack("<ii", 1000, 0)), T0 + 0.0005)
        first = rig.cache.snapshot()
        samples = [odometry_sample(first, SYNC_S)]
        for layout in others:
            rig.network.notify(layout.cob_id, bytearray(layout.codec.size), T0 + 0.001)
            later = rig.cache.snapshot()
            assert later.rx_monotonic > first.rx_monotonic  # a newer frame...
            samples.append(odometry_sample(later, SYNC_S))
    finally:
        rig.close()
    assert first.position_stamp == T0 and first.position_rx == first.rx_monotonic  # the SYNC it answers
    assert {(s.stamp, s.bus_stamp, s.angle_rad) for s in samples} == {(samples[0].stamp, T0, samples[0].angle_rad)}
