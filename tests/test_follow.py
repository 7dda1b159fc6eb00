"""motor_driver.follow: a joint trajectory followed on the bus's SYNC clock, against the simulator, with
an independent listener on the bus. Each refusal leaves nothing on the wire; each set-point follows a
SYNC's position sample of the group's clock (by the order of frames) and the set-points are the
sampled spline; tolerances, preemption, cancel and a
drive lost mid-goal, judged by the frames and the simulated drives, never by a clock."""

from __future__ import annotations

import dataclasses
import errno
import itertools
import math
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import can
import pytest

from can_config import RoverConfig
from can_config.errors import TrajectoryRejected
from motor_driver import MotorDriver
from motor_driver.bus.adapters import GuardedNetwork
from motor_driver.follow import GoalRun, Tolerance, TrajectoryCode, TrajectoryGoal, TrajectoryGroup
from motor_driver.follow.trajectory import Spline
from virtual_can import SimService
from virtual_can.scenario import apply_action

from .conftest import IN_PROCESS_STALE_SYNCS, make_config, wait_for
from .drive_states import stale

DriverFactory = Callable[[RoverConfig], tuple[SimService, MotorDriver]]
ListenerFactory = Callable[[SimService], can.BusABC]

#: The arm's joints here: limited to +-90 deg, 180 deg/s at most.
ARM = {"joint": "limited", "min_deg": -90.0, "max_deg": 90.0, "counts_per_rev": 4096, "gear_ratio": 50.0,
       "max_velocity_deg_s": 180.0, "profile_acceleration_deg_s2": 720.0,
       "stale_after_syncs": IN_PROCESS_STALE_SYNCS}
SYNC = 0x080
#: joint1's position TPDO: the group's clock (its first joint's sample after each SYNC)
CLOCK_SAMPLE = 0x281
#: A CSP set-point: RPDO2 of the drive (controlword, target position)
SETPOINT = 0x300
#: Frames that could move a drive or change it: RPDOs and SDO requests to nodes 1-3.
MOTION_IDS = {base + n for base in (0x200, 0x300, 0x400, 0x500, 0x600) for n in (1, 2, 3)}
RESULT_S = 30.0  # hang bound of a run


@dataclass
class Arm:
    sim: SimService
    driver: MotorDriver
    group: TrajectoryGroup
    frames: list[can.Message]  # every frame the listener heard since the arm was ready, in order


@pytest.fixture
def arm(driver_factory: DriverFactory, listener_factory: ListenerFactory) -> Iterator[Arm]:
    """Three limited joints, joint1 and joint2 armed (joint3 not), their group (goals of some of
    its joints allowed), a listener."""
    sim, driver = driver_factory(make_config(3, **ARM))
    for name in ("joint1", "joint2"):
        driver.drive(name).enable()
    (config,) = driver.config.trajectory_groups
    group = TrajectoryGroup(dataclasses.replace(config, allow_partial_joints_goal=True), driver.drives)
    frames: list[can.Message] = []
    notifier = can.Notifier(listener_factory(sim), [frames.append], timeout=0.1)
    yield Arm(sim, driver, group, frames)
    group.close()
    notifier.stop()


def goal(*points: tuple[float, tuple[float, ...]], joints: tuple[str, ...] = ("joint1", "joint2"),
         velocities: bool = True, **kwargs: object) -> TrajectoryGoal:
    """Points (time, positions) at rest (velocities 0) unless ``velocities`` is False."""
    return TrajectoryGoal(joints=joints, times_s=tuple(t for t, _ in points), positions_deg=tuple(p for _, p in points),
                          velocities_deg_s=tuple((0.0,) * len(joints) for _ in points) if velocities else (),
                          **kwargs)  # type: ignore[arg-type]


def frames_after(arm: Arm, since: int = 0, syncs: int = 3) -> list[can.Message]:
    """The frames heard from index ``since`` until ``syncs`` SYNCs after now: whatever the driver
    sent before now reaches the listener before them (one server, frames in order)."""
    mark = len(arm.frames)
    wait_for(lambda: sum(m.arbitration_id == SYNC for m in arm.frames[mark:]) >= syncs, 10.0, f"{syncs} SYNC frames")
    return arm.frames[since:]


def streamed_later(arm: Arm, ids: tuple[int, ...] = (0x301, 0x302)) -> list[can.Message]:
    """Set-points of ``ids`` the bus carried after the second SYNC from now: one sent before now
    may still be on its way to the listener, and reaches it before the SYNC after it."""
    frames = frames_after(arm, len(arm.frames), syncs=6)
    second = [i for i, m in enumerate(frames) if m.arbitration_id == SYNC][1]
    return [m for m in frames[second:] if m.arbitration_id in ids]


def ramped_down(arm: Arm, node: int) -> None:
    """The joint's last set-points slow down step by step (a ramp at the stop deceleration), not a
    cut from full speed: the last moving steps shrink, each by about decel x period^2."""
    steps = [b - a for a, b in itertools.pairwise(setpoints(arm.frames, node))]
    moving = [abs(s) for s in steps if s != 0]
    assert len(moving) > 3
    tail = moving[-3:]
    assert tail[0] > tail[1] > tail[2], f"no ramp: the last steps {moving[-6:]} counts"


def refused(arm: Arm, bad: TrajectoryGoal, code: TrajectoryCode, *words: str) -> None:
    mark = len(arm.frames)
    with pytest.raises(TrajectoryRejected) as caught:
        arm.group.follow(bad)
    assert caught.value.code == code, caught.value
    for word in words:
        assert word in str(caught.value), str(caught.value)
    sent = [m for m in frames_after(arm, mark) if m.arbitration_id in MOTION_IDS]
    assert not sent, f"refused, yet on the wire: {sent}"


def angle(arm: Arm, joint: str) -> float:
    return arm.driver.drive(joint).cache.angle_deg


def finished(run: GoalRun, hang_s: float = RESULT_S) -> TrajectoryCode:
    assert run.done.wait(hang_s), "no outcome"
    assert run.outcome is not None
    return run.outcome.code


def test_an_unknown_joint_is_refused_with_nothing_on_the_wire(arm: Arm) -> None:
    refused(arm, goal((1.0, (10.0, 5.0)), joints=("joint1", "elbow")), TrajectoryCode.INVALID_JOINTS,
            "'elbow'", "joint1")
    refused(arm, goal((1.0, (10.0, 5.0)), joints=("joint1", "joint1")), TrajectoryCode.INVALID_JOINTS, "twice")


def test_a_goal_of_some_joints_is_refused_unless_the_config_allows_it(arm: Arm) -> None:
    """joint_trajectory_controller's default (allow_partial_joints_goal false): a goal names every joint."""
    strict = TrajectoryGroup(dataclasses.replace(arm.group.config, allow_partial_joints_goal=False), arm.driver.drives)
    try:
        with pytest.raises(TrajectoryRejected) as caught:
            strict.plan(goal((1.0, (10.0, 5.0))))
        assert caught.value.code == TrajectoryCode.INVALID_JOINTS and "joint3" in str(caught.value), caught.value
    finally:
        strict.close()


def test_tolerances_take_the_controllers_meanings(arm: Arm) -> None:
    """-1 none, 0 the group's default, other negatives refused; the stopped velocity at the goal."""
    plan = arm.group.plan(goal((1.0, (10.0, 5.0)), path_tolerance={"joint1": Tolerance(-1.0, -1.0)},
                               goal_tolerance={"joint2": Tolerance(0.5, 0.0)}))
    cfg = arm.group.config
    assert plan.path == (Tolerance(-1.0, -1.0), Tolerance(cfg.path_tolerance_deg, -1.0))
    assert plan.final == (Tolerance(cfg.goal_tolerance_deg, cfg.stopped_velocity_tolerance_deg_s),
                          Tolerance(0.5, cfg.stopped_velocity_tolerance_deg_s))
    refused(arm, goal((1.0, (10.0, 5.0)), goal_tolerance={"joint2": Tolerance(-0.5, 0.0)}),
            TrajectoryCode.INVALID_GOAL, "joint2", "goal position tolerance -0.5")
    # the goal time: -1 erases the bound (joint_trajectory_controller's resolve_tolerance_source, then
    # 0: no bound in its update()); 0 the group's; any other negative refused
    assert arm.group.plan(goal((1.0, (10.0, 5.0)), goal_time_tolerance_s=-1.0)).goal_time_s == 0.0
    assert arm.group.plan(goal((1.0, (10.0, 5.0)))).goal_time_s == cfg.goal_time_tolerance_s > 0.0
    refused(arm, goal((1.0, (10.0, 5.0)), goal_time_tolerance_s=-0.5), TrajectoryCode.INVALID_GOAL,
            "goal_time_tolerance")


def test_a_point_beyond_a_limit_is_refused_naming_the_joint_and_the_limit(arm: Arm) -> None:
    refused(arm, goal((1.0, (10.0, 5.0)), (2.0, (10.0, 95.0))), TrajectoryCode.INVALID_GOAL,
            "joint2", "point 1", "max_deg=90")
    refused(arm, TrajectoryGoal(("joint1", "joint2"), (1.0,), ((10.0, 5.0),), ((200.0, 0.0),)),
            TrajectoryCode.INVALID_GOAL, "joint1", "point 0", "max_velocity_deg_s=180")
    # the points are within the limits, the cubic between them is not: from 80 deg at 170 deg/s to
    # 89 deg at rest in 0.5 s it passes 95 deg
    overshoot = TrajectoryGoal(("joint1",), (1.0, 1.5), ((80.0,), (89.0,)), ((170.0,), (0.0,)))
    refused(arm, overshoot, TrajectoryCode.INVALID_GOAL, "joint1", "max_deg=90", "between its points")
    # 80 deg in 0.2 s: 400 deg/s, beyond 180
    refused(arm, goal((0.2, (80.0, 0.0)), velocities=False), TrajectoryCode.INVALID_GOAL, "joint1",
            "max_velocity_deg_s=180")


def test_a_goal_ending_at_a_joint_s_limit_is_taken(arm: Arm) -> None:
    """A point exactly at min_deg or max_deg is allowed (the points' own check); the check between
    the points must not refuse it for the rounding of its polynomial at the end (an ulp past 90)."""
    for end in (90.0, -90.0):
        for duration in (1.3, 1.7, 2.2, 3.1):
            for velocities, accelerations in (((), ()), (((0.0,),), ()), (((0.0,),), ((0.0,),))):
                arm.group.plan(TrajectoryGoal(("joint1",), (duration,), ((end,),), velocities, accelerations))


def test_a_segment_shorter_than_a_sync_period_is_judged_too(arm: Arm) -> None:
    """10 deg in 8 ms between points 1.001 s and 1.009 s (1,250 deg/s, beyond 180): no SYNC sample of a
    10 ms period falls inside that segment, and a check at the samples let it through; the group then
    samples where its clock says, and the drive would have been asked for the jump."""
    dash = goal((1.0, (0.0, 0.0)), (1.001, (0.0, 0.0)), (1.009, (10.0, 0.0)), (2.0, (10.0, 0.0)), velocities=False)
    refused(arm, dash, TrajectoryCode.INVALID_GOAL, "joint1", "max_velocity_deg_s=180", "at 1.00")


def test_a_trajectory_s_check_does_not_grow_with_its_duration(arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    """A point 2e9 s away (a client's nanoseconds written in ``sec``) is judged without sampling its
    time: a check of a sample a SYNC period held the executor, and every cancel, for ever. A counter on
    the spline's sampling fails the test where the check samples the plan's time."""
    calls: list[float] = []

    def counted(self: Spline, t: float) -> tuple[tuple[float, float, float], ...]:
        calls.append(t)
        if len(calls) > 1000:
            raise AssertionError("the check samples the plan's time")
        return original(self, t)

    original = Spline.sample
    monkeypatch.setattr(Spline, "sample", counted)
    plan = arm.group.plan(goal((2e9, (0.0, 0.0))))
    assert plan.times_s == (2e9,)


def test_times_that_do_not_increase_are_refused(arm: Arm) -> None:
    refused(arm, goal((1.0, (5.0, 5.0)), (1.0, (6.0, 6.0))), TrajectoryCode.INVALID_GOAL, "point 1", "strictly increasing")
    refused(arm, goal((-0.5, (5.0, 5.0))), TrajectoryCode.INVALID_GOAL, "point 0")
    refused(arm, goal((0.0, (0.0, 0.0))), TrajectoryCode.INVALID_GOAL, "no time to move")
    refused(arm, TrajectoryGoal(("joint1", "joint2"), (1.0,), ((5.0,),)), TrajectoryCode.INVALID_GOAL, "one finite value")
    refused(arm, TrajectoryGoal(("joint1", "joint2"), (1.0,), ((5.0, math.nan),)), TrajectoryCode.INVALID_GOAL,
            "one finite value")


def test_a_trajectory_ending_in_motion_is_refused_unless_the_group_allows_it(arm: Arm) -> None:
    """joint_trajectory_controller's validate_trajectory_msg: a last point with a velocity (over float
    epsilon) is rejected unless allow_nonzero_velocity_at_trajectory_end; nothing follows the last
    set-point, so the joints would stop dead from that velocity within one SYNC."""
    moving = TrajectoryGoal(("joint1", "joint2"), (1.0, 2.0), ((10.0, 5.0), (20.0, 5.0)), ((10.0, 0.0), (30.0, 0.0)))
    refused(arm, moving, TrajectoryCode.INVALID_GOAL, "joint1", "30 deg/s", "allow_nonzero_velocity_at_trajectory_end")
    refused(arm, dataclasses.replace(moving, velocities_deg_s=((10.0, 0.0), (0.0, 1e-5))), TrajectoryCode.INVALID_GOAL,
            "joint2")
    at_rest = dataclasses.replace(moving, velocities_deg_s=((10.0, 0.0), (0.0, 1e-6)))  # below epsilon: at rest
    assert arm.group.plan(at_rest).times_s == (1.0, 2.0)
    allowing = TrajectoryGroup(dataclasses.replace(arm.group.config, allow_nonzero_velocity_at_trajectory_end=True),
                               arm.driver.drives)
    try:
        assert allowing.plan(moving).times_s == (1.0, 2.0)
    finally:
        allowing.close()


def test_a_joint_not_armed_is_refused(arm: Arm) -> None:
    refused(arm, goal((1.0, (5.0, 5.0, 5.0)), joints=("joint1", "joint2", "joint3")), TrajectoryCode.INVALID_GOAL,
            "joint3", "not armed")


def test_a_stale_joint_is_refused(arm: Arm) -> None:
    apply_action(arm.sim, {"action": "tx_dead", "node": 2})
    drive = arm.driver.drive("joint2")
    wait_for(lambda: stale(drive.snapshot()), 10.0, "joint2 stale")
    mark = len(arm.frames)
    with pytest.raises(TrajectoryRejected) as caught:
        arm.group.follow(goal((1.0, (5.0, 5.0))))
    assert caught.value.code == TrajectoryCode.INVALID_GOAL
    assert "joint2: late" in str(caught.value) or "joint2: lost" in str(caught.value)
    # (a lost joint2 is told to stop on its own ids by the supervisor: not a motion of the goal)
    sent = [m for m in frames_after(arm, mark) if m.arbitration_id in MOTION_IDS - {0x202, 0x602}]
    assert not sent, sent


def test_a_start_far_from_the_joints_is_refused(arm: Arm) -> None:
    refused(arm, goal((0.0, (0.0, 12.0)), (1.0, (5.0, 12.0))), TrajectoryCode.INVALID_GOAL, "joint2",
            "start_tolerance_deg=2")


def setpoints(frames: list[can.Message], node: int) -> list[int]:
    return [struct.unpack_from("<i", m.data, 2)[0] for m in frames if m.arbitration_id == SETPOINT + node]


def syncs_between(frames: list[can.Message], node: int) -> list[int]:
    """For each set-point of ``node`` after its first: the SYNCs the bus carried since the one
    before it (by the order of frames; 1 where the group's thread kept pace)."""
    counts: list[int] = []
    syncs: int | None = None
    for msg in frames:
        if msg.arbitration_id == SYNC and syncs is not None:
            syncs += 1
        elif msg.arbitration_id == SETPOINT + node:
            if syncs is not None:
                counts.append(syncs)
            syncs = 0
    return counts


def test_setpoints_follow_the_sync_and_are_the_sampled_trajectory(arm: Arm) -> None:
    drives = [arm.driver.drive(j) for j in ("joint1", "joint2")]
    for drive in drives:
        drive.motion.start_stream()  # CSP, holding where it stands: the spline's start
    scale = drives[0].cache.scale
    start = tuple((scale.counts_to_deg(d.channel.target_counts), 0.0, 0.0) for d in drives)
    mark = len(arm.frames)
    target = goal((0.0, (0.0, 0.0)), (0.6, (20.0, -10.0)), (1.0, (25.0, -10.0)))
    run = arm.group.follow(target)
    assert finished(run) == TrajectoryCode.SUCCESSFUL, run.outcome
    # the k-th set-point of each joint answers the k-th new position sample of the group's clock
    # (joint1's TPDO 0x281, one a SYNC): it never comes before k samples were on the bus (k - 1:
    # the first may have passed the listener before it was marked)
    frames = [m for m in frames_after(arm, mark) if m.arbitration_id in (CLOCK_SAMPLE, 0x301, 0x302)]
    samples, sent = 0, {0x301: 0, 0x302: 0}
    for i, m in enumerate(frames):  # i: the frame's place, for the message
        if m.arbitration_id == CLOCK_SAMPLE:
            samples += 1
        else:
            sent[m.arbitration_id] += 1
            assert sent[m.arbitration_id] <= samples + 1, f"set-point {m.arbitration_id:03X} (frame {i}) ahead of the SYNCs"
    period = arm.group.period_s
    wire = [[scale.counts_to_deg(c) for c in setpoints(frames, n)] for n in (1, 2)]
    spline = Spline((0.0, 0.6, 1.0), (start, ((20.0, 0.0, None), (-10.0, 0.0, None)),
                                      ((25.0, 0.0, None), (-10.0, 0.0, None))))
    # each set-point is the spline at a time of the plan (the next SYNC's, on the clock from the
    # goal's start: a SYNC missed does not stretch it): joint1 rises on it, so its set-point says
    # the time; joint2's is the spline at that same time; the times only go forward; the last is the end
    times = [when(spline, p) for p in wire[0]]
    assert times == sorted(times) and len(times) <= math.ceil(1.0 / period) + 1
    for t, p in zip(times, wire[1], strict=True):
        assert abs(spline.sample(t)[1][0] - p) < 0.01, (t, p)
    assert wire[0][-1] == pytest.approx(25.0, abs=0.002) and wire[1][-1] == pytest.approx(-10.0, abs=0.002)


def when(spline: Spline, position_deg: float) -> float:
    """The time at which joint1 (rising on ``spline``) is at ``position_deg``: bisection."""
    low, high = 0.0, spline.end_s
    for _ in range(60):
        mid = (low + high) / 2
        low, high = (mid, high) if spline.sample(mid)[0][0] < position_deg else (low, mid)
    return high


def test_a_path_tolerance_violated_aborts_and_the_group_ramps_down(arm: Arm) -> None:
    tight = {"joint1": Tolerance(position_deg=1e-4), "joint2": Tolerance(position_deg=1e-4)}
    run = arm.group.follow(goal((2.0, (40.0, -40.0)), path_tolerance=tight))
    assert finished(run) == TrajectoryCode.PATH_TOLERANCE_VIOLATED
    assert run.outcome is not None and "path tolerance" in run.outcome.message
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")
    assert not streamed_later(arm), "streamed after the ramp"
    assert abs(angle(arm, "joint1")) < 20.0  # stopped well before the goal


def test_a_goal_tolerance_violated_aborts(arm: Arm) -> None:
    # 10.0009 deg is 5689.4 counts (568.89 counts a degree): every whole count the joint can end on
    # is at least 0.0007 deg from it (10.0001 was 5688.95 counts: the count it rounds to lies within
    # 1e-4 deg, and a joint that settled exactly there met the tolerance)
    exact = {"joint1": Tolerance(position_deg=1e-4), "joint2": Tolerance(position_deg=1e-4)}
    run = arm.group.follow(goal((0.5, (10.0009, 0.0)), goal_tolerance=exact, goal_time_tolerance_s=0.1))
    assert finished(run) == TrajectoryCode.GOAL_TOLERANCE_VIOLATED
    assert run.outcome is not None and "joint1" in run.outcome.message and "goal tolerance" in run.outcome.message


def jammed_hold(arm: Arm, node: int) -> tuple[float, float]:
    """(where joint ``node`` stands, its last set-point on the wire), in deg, once the group's ramp is done."""
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")
    drive = arm.driver.drive(f"joint{node}")
    last = setpoints(frames_after(arm), node)[-1]
    return drive.cache.angle_deg, drive.cache.scale.counts_to_deg(last)


def test_a_jammed_joint_s_abort_holds_it_where_it_stands_not_at_its_set_point(arm: Arm) -> None:
    """joint1's shaft blocked from the start, under a 5 deg path tolerance (more than the stream's step
    guard, 180 deg/s over two SYNC periods: 3.6 deg at 100 Hz): the goal aborts and joint1 is held where
    it stands, as joint_trajectory_controller holds the measured state; its set-point ramped on from
    5 deg ahead, and the drive pushed against what blocks it (and jumped there once freed)."""
    apply_action(arm.sim, {"action": "load", "node": 1, "stall": True})
    try:
        tolerance = {n: Tolerance(position_deg=5.0) for n in ("joint1", "joint2")}
        run = arm.group.follow(goal((2.0, (40.0, 0.0)), path_tolerance=tolerance))
        assert finished(run) == TrajectoryCode.PATH_TOLERANCE_VIOLATED
        assert run.outcome is not None and "joint1" in run.outcome.message, run.outcome
        stands, held = jammed_hold(arm, 1)
        assert abs(held - stands) < 0.2, f"joint1 stands at {stands:.3f} deg, held at {held:.3f} deg"
    finally:
        apply_action(arm.sim, {"action": "load", "node": 1, "stall": False})


def test_a_goal_tolerance_missed_by_a_jammed_joint_holds_it_where_it_stands(arm: Arm) -> None:
    """joint1 blocked, no path tolerance: the plan runs to its end, the goal tolerance is missed after
    the goal time, and joint1 is then held where it stands, not left pushing toward the goal."""
    apply_action(arm.sim, {"action": "load", "node": 1, "stall": True})
    try:
        none = {n: Tolerance(position_deg=-1.0) for n in ("joint1", "joint2")}
        run = arm.group.follow(goal((0.5, (10.0, 0.0)), path_tolerance=none, goal_time_tolerance_s=0.1))
        assert finished(run) == TrajectoryCode.GOAL_TOLERANCE_VIOLATED
        stands, held = jammed_hold(arm, 1)
        assert abs(held - stands) < 0.2, f"joint1 stands at {stands:.3f} deg, held at {held:.3f} deg"
    finally:
        apply_action(arm.sim, {"action": "load", "node": 1, "stall": False})


def test_a_new_goal_preempts_the_old_at_its_setpoint_without_a_jump(arm: Arm) -> None:
    first = arm.group.follow(goal((4.0, (60.0, 0.0))))
    wait_for(lambda: first.progress is not None and first.progress.time_s > 1.5, 20.0, "the first goal half way")
    here = angle(arm, "joint1")
    second = arm.group.follow(goal((0.0, (here, 0.0)), (2.0, (0.0, 0.0))))
    # as joint_trajectory_controller (jazzy >= 4.41.0): the older goal ABORTED with INVALID_GOAL and its words
    assert finished(first) == TrajectoryCode.INVALID_GOAL and first.outcome is not None
    assert not first.outcome.canceled and first.outcome.message == "Current goal preempted by new incoming action."
    assert finished(second) == TrajectoryCode.SUCCESSFUL, second.outcome
    scale = arm.driver.drive("joint1").cache.scale
    frames = frames_after(arm)
    path = [scale.counts_to_deg(c) for c in setpoints(frames, 1)]
    steps = [b - a for a, b in itertools.pairwise(path)]
    assert max(abs(s) for s in steps) <= 180.0 * arm.group.period_s  # never faster than the joint may go
    # the new plan is joined at the set-point with its velocity: joint1 slows down into its peak (the
    # second spline's deceleration, under 100 deg/s^2), it is not cut there from full speed. Judged
    # per SYNC the bus carried between two set-points (a SYNC the busy host let go is caught up in
    # the next set-point: its step spans them)
    rates = [step / max(n, 1) for step, n in zip(steps, syncs_between(frames, 1), strict=True)]
    peak = path.index(max(path))
    into = rates[peak - 5:peak]
    assert len(into) == 5 and max(abs(r) for r in into) < 0.3 * max(abs(r) for r in rates), (into, max(rates))
    assert path[-1] == pytest.approx(0.0, abs=0.01)


def test_a_goal_stamped_ahead_that_preempts_holds_where_the_ramp_ended(arm: Arm) -> None:
    """A goal stamped ahead preempts a fast one: the old goal's joints ramp down, then the new goal
    holds them where the ramp ended (not at the preempted goal's last set-point, from before the
    ramp: a jump back of the whole ramp's travel, refused by the step guard, aborted the new goal)
    and its plan joins from there. No set-point steps further than the joint's max velocity over one
    SYNC period (the drive takes it within one)."""
    first = arm.group.follow(goal((1.5, (80.0, 0.0))))
    wait_for(lambda: first.progress is not None and first.progress.time_s > 0.6, 20.0, "the first goal at speed")
    second = arm.group.follow(goal((1.0, (40.0, 0.0)), start_delay_s=1.0))  # the ramp (about 0.3 s) ends first
    assert finished(first) == TrajectoryCode.INVALID_GOAL
    assert finished(second) == TrajectoryCode.SUCCESSFUL, second.outcome
    drive = arm.driver.drive("joint1")
    path = [drive.cache.scale.counts_to_deg(c) for c in setpoints(frames_after(arm), 1)]
    limit = drive.config.max_velocity_deg_s * arm.group.period_s
    steps = [abs(b - a) for a, b in itertools.pairwise(path)]
    assert max(steps) <= limit + 1e-3, f"a step of {max(steps):.3f} deg; max velocity x period {limit:.3f} deg"
    assert path[-1] == pytest.approx(40.0, abs=0.01)


def test_a_newer_goal_cancelled_before_the_group_took_it_still_preempts_the_older(arm: Arm) -> None:
    """joint_trajectory_controller aborts the goal running when a newer one is accepted; a cancel of
    the newer one then leaves the joints holding. Here the group's thread takes a newer goal at its
    next turn: a cancel that came first (the hook below, at the thread's take) ends the newer goal
    and the older one too, whose joints ramp down and hold; it went on moving before."""
    first = arm.group.follow(goal((4.0, (60.0, 0.0))))
    wait_for(lambda: first.progress is not None and first.progress.time_s > 1.0, 20.0, "the first goal under way")
    take = arm.group._start

    def cancelled_first(run: GoalRun) -> None:
        run.cancel()  # the client's cancel, come before the group's thread took the goal
        take(run)

    arm.group._start = cancelled_first  # type: ignore[method-assign]
    second = arm.group.follow(goal((0.0, (angle(arm, "joint1"), 0.0)), (2.0, (0.0, 0.0))))
    assert finished(second) == TrajectoryCode.SUCCESSFUL and second.outcome is not None and second.outcome.canceled
    assert finished(first) == TrajectoryCode.INVALID_GOAL, first.outcome
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")
    assert not streamed_later(arm), "streamed after the ramp"
    ramped_down(arm, 1)
    assert 2.0 < angle(arm, "joint1") < 59.0


def test_cancel_ramps_the_group_down_and_it_holds(arm: Arm) -> None:
    run = arm.group.follow(goal((3.0, (60.0, -60.0))))
    wait_for(lambda: run.progress is not None and run.progress.time_s > 1.0, 20.0, "the goal under way")
    run.cancel()
    assert finished(run) == TrajectoryCode.SUCCESSFUL and run.outcome is not None and run.outcome.canceled
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")  # the result comes at once, the ramp after
    assert not streamed_later(arm), "streamed after the ramp"
    ramped_down(arm, 1)
    ramped_down(arm, 2)
    runner = arm.sim.simulators["can0"]
    wait_for(lambda: runner.call(lambda: max(abs(runner.drive(n).omega) for n in (1, 2))) < 1e-3,  # type: ignore[arg-type]
             10.0, "both shafts at rest")
    assert 5.0 < angle(arm, "joint1") < 59.0 and -59.0 < angle(arm, "joint2") < -5.0


def test_a_drive_lost_mid_goal_aborts_and_stops_the_group(arm: Arm) -> None:
    run = arm.group.follow(goal((4.0, (60.0, -60.0))))
    wait_for(lambda: run.progress is not None and run.progress.time_s > 1.0, 20.0, "the goal under way")
    apply_action(arm.sim, {"action": "tx_dead", "node": 2})
    assert finished(run) == TrajectoryCode.PATH_TOLERANCE_VIOLATED
    assert run.outcome is not None and "joint2" in run.outcome.message
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")
    assert not streamed_later(arm, (0x301,)), "joint1 streamed after its ramp"
    ramped_down(arm, 1)
    runner = arm.sim.simulators["can0"]
    wait_for(lambda: abs(runner.call(lambda: runner.drive(1).omega)) < 1e-3, 10.0, "joint1 at rest")  # type: ignore[arg-type]
    assert angle(arm, "joint1") < 55.0


def test_a_failed_write_of_a_syncs_set_points_ends_the_goal_naming_the_bus(arm: Arm) -> None:
    """A SYNC's set-points go out in one write a bus (GuardedNetwork.one_write): that write failing
    (a hook on it: the socket's error) ends the goal as a set-point refused does, naming the bus;
    not an internal error of the group, whose thread goes on."""
    network = arm.driver.drive("joint1").network
    assert isinstance(network, GuardedNetwork)
    run = arm.group.follow(goal((4.0, (60.0, -60.0))))
    wait_for(lambda: run.progress is not None and run.progress.time_s > 0.5, 20.0, "the goal under way")
    bus, direct = network._sender
    assert direct is not None

    def write(payload: bytes) -> None:
        raise OSError(errno.EPIPE, "Broken pipe")
    network._sender = (bus, direct._replace(write=write))
    try:
        assert finished(run) == TrajectoryCode.PATH_TOLERANCE_VIOLATED
    finally:
        network._sender = (bus, direct)
    assert run.outcome is not None and "bus can0: set-points not sent" in run.outcome.message, run.outcome
    assert arm.group.errors == 0 and arm.group.alive
    wait_for(lambda: not arm.group.ramping, RESULT_S, "the ramp done")


def test_a_held_group_thread_catches_up_within_the_drives_step_guard(arm: Arm) -> None:
    """The group's thread held for 30 SYNCs mid-goal (inside its set-point call: a starved host):
    the plan catches up after at the joint's limit, and no set-point steps further than its max
    velocity over one SYNC period (a CSP drive takes a set-point within one period). A catch-up by
    the SYNCs that passed would have asked joint1 for a jump of many degrees; one held to the
    drive's guard (two periods' travel), for 1.6 times its max velocity; none, for a goal ending
    the hold's 30 SYNCs late."""
    drive = arm.driver.drive("joint1")
    calls = itertools.count()
    real = drive.stream_position

    def held(angle_deg: float, **kwargs: object) -> None:
        if next(calls) == 20:  # mid-goal: the thread waits for the bus to carry 30 SYNCs
            mark = len(arm.frames)
            wait_for(lambda: sum(m.arbitration_id == SYNC for m in arm.frames[mark:]) >= 30, 30.0, "30 SYNC frames")
        real(angle_deg, **kwargs)  # type: ignore[arg-type]

    drive.stream_position = held  # type: ignore[method-assign]
    mark = len(arm.frames)
    free = {"joint1": Tolerance(position_deg=-1.0), "joint2": Tolerance(position_deg=-1.0)}  # none: the lag after a hold is not judged here
    run = arm.group.follow(goal((1.5, (80.0, 0.0)), path_tolerance=free))
    assert finished(run) == TrajectoryCode.SUCCESSFUL, run.outcome
    assert next(calls) > 21, "the hold came before the goal ended"
    scale = drive.cache.scale
    path = [scale.counts_to_deg(c) for c in setpoints(frames_after(arm, mark), 1)]
    limit = drive.config.max_velocity_deg_s * arm.group.period_s
    steps = [abs(b - a) for a, b in itertools.pairwise(path)]
    assert max(steps) <= limit + 1e-3, f"a step of {max(steps):.3f} deg; max velocity x period {limit:.3f} deg"
    assert arm.group.stretched_s > 0.0, "the hold did not make the plan late"
    # caught up at the limit: steps at it (the plan's own peak is about 0.8 deg a period)
    assert max(steps) > 0.95 * limit, f"no catch-up: the largest step {max(steps):.3f} deg"


def test_a_group_thread_late_at_every_sync_still_ends_its_goal_at_the_joints_limit(arm: Arm) -> None:
    """The group's thread sends each set-point 10 SYNCs after the last (a host starved all along):
    every step is within joint1's max velocity over one period, so the plan runs late (stretched),
    but each set-point catches up as far as that allows and the goal ends SUCCESSFUL in about half
    the set-points a plan held to the SYNCs' pace would take (150 at 100 Hz over 1.5 s)."""
    drive = arm.driver.drive("joint1")
    calls = itertools.count()
    real = drive.stream_position

    def late(angle_deg: float, **kwargs: object) -> None:
        next(calls)
        mark = len(arm.frames)
        wait_for(lambda: sum(m.arbitration_id == SYNC for m in arm.frames[mark:]) >= 10, 30.0, "10 SYNC frames")
        real(angle_deg, **kwargs)  # type: ignore[arg-type]

    drive.stream_position = late  # type: ignore[method-assign]
    mark = len(arm.frames)
    free = {"joint1": Tolerance(position_deg=-1.0), "joint2": Tolerance(position_deg=-1.0)}  # the lag is the input
    run = arm.group.follow(goal((1.5, (80.0, 0.0)), path_tolerance=free))
    assert finished(run, 120.0) == TrajectoryCode.SUCCESSFUL, run.outcome
    sent = next(calls)
    assert 20 < sent < 90, f"{sent} set-points: the plan did not catch up as far as the limit lets it"
    assert arm.group.stretched_s > 0.0
    path = [drive.cache.scale.counts_to_deg(c) for c in setpoints(frames_after(arm, mark), 1)]
    limit = drive.config.max_velocity_deg_s * arm.group.period_s
    assert max(abs(b - a) for a, b in itertools.pairwise(path)) <= limit + 1e-3
    assert path[-1] == pytest.approx(80.0, abs=0.01)
