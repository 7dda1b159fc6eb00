"""``/arm_controller/follow_joint_trajectory`` on a real rclpy graph: the driver's process as its entry
point assembles it (nodes/assembly.py), the arm on the simulator, and an independent client of the
standard type (rclpy's ActionClient of control_msgs/action/FollowJointTrajectory, in a context of
its own). A half-sine of two joints is tracked and succeeds; a cancel leaves the joints still; a goal
beyond a limit is refused with its code and nothing reaches the bus. Tracking is measured on the
controller's own error (a measure of the simulated plant, at each SYNC); the figures of a 500 Hz
arm beside the wheels are the benchmark's (benchmarks/follow_trajectory.py)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import re
import signal
import statistics
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from can_config import with_bus_overrides
from motor_driver import MotorDriver
from virtual_can import SimService, VirtualBus
from virtual_can.scenario import apply_action

from .conftest import (
    HAVE_ROS,
    IN_PROCESS_HEARTBEAT_TIMEOUT_MS,
    IN_PROCESS_HOST_TIMEOUT_MS,
    IN_PROCESS_STALE_SYNCS,
    MARKER_COB,
    REPO,
    in_process_stale_after_syncs,
    make_config,
    requires_ros,
    wait_for,
)

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectoryPoint

    from nodes.assembly import Assembly
    from nodes.process import spinning
    from nodes.process.qos import STATE_QOS
    from nodes.process.spinning import SpinThread, make_executor

ListenerFactory = Callable[[SimService], can.BusABC]
ARM = {"joint": "limited", "min_deg": -90.0, "max_deg": 90.0, "counts_per_rev": 4096, "gear_ratio": 50.0,
       "max_velocity_deg_s": 180.0, "profile_acceleration_deg_s2": 720.0,
       "stale_after_syncs": IN_PROCESS_STALE_SYNCS}
ACTION = "/arm_controller/follow_joint_trajectory"
SYNC, SETPOINTS = 0x080, (0x301, 0x302)
HANG_S = 30.0
MARKERS = itertools.count(1)


@dataclass
class Rig:
    sim: SimService
    assembly: Any
    client: Any  # ActionClient
    states: list[Any]  # /joint_states as the client hears them
    domain: int | None = None  # the graph's ROS domain where it has one of its own


@pytest.fixture
def rig(monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest) -> Iterator[Rig]:
    monkeypatch.setattr(spinning, "IDLE_POLL_S", 600.0)  # the idle executors never poll: a goal's pause wakes them
    param = dict(getattr(request, "param", {}))  # indirect: the drives' settings changed, or the SYNC's
    sync_s = param.pop("sync_period_s", None)
    group_keys = param.pop("group", {})  # the trajectory group's settings changed
    config = make_config(2, **ARM | param)
    config = dataclasses.replace(config, trajectory_groups=tuple(dataclasses.replace(g, **group_keys)
                                                                 for g in config.trajectory_groups))
    if sync_s is not None:  # the arm's bus at another SYNC rate, the drives' staleness bound in time kept
        config = dataclasses.replace(config, buses=tuple(dataclasses.replace(b, sync_period_s=sync_s) for b in config.buses),
                                     drives=tuple(dataclasses.replace(d, stale_after_syncs=in_process_stale_after_syncs(sync_s))
                                                  for d in config.drives))
    sim = SimService.from_config(config, port=0)
    # a domain of its own where the suite's worker has none (a run beside other graphs on this
    # machine: their /joint_states of joints named alike would be heard here)
    domain = None if os.environ.get("ROS_DOMAIN_ID") else 150 + os.getpid() % 80
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    hot = make_executor("events", context)
    assembly = Assembly(MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)), hot, context=context,
                        overrides=[Parameter("arm", value=True), Parameter("state_rate_hz", value=100.0)])
    assembly.build()
    assembly.start()
    spin = SpinThread(hot, "test-hot")
    theirs = rclpy.Context()  # the client: another participant, as MoveIt would be
    rclpy.init(context=theirs, domain_id=domain)
    node = rclpy.create_node("trajectory_client", context=theirs)
    states: list[Any] = []
    node.create_subscription(JointState, "/joint_states", states.append, STATE_QOS)
    client = ActionClient(node, FollowJointTrajectory, ACTION)
    executor = SingleThreadedExecutor(context=theirs)
    executor.add_node(node)
    client_spin = SpinThread(executor, "test-client")
    try:
        assert client.wait_for_server(timeout_sec=HANG_S), f"{ACTION} not served"
        wait_for(lambda: all(d.snapshot().verdict.usable for d in assembly.driver), HANG_S, "the arm armed")
        yield Rig(sim, assembly, client, states, domain)
    finally:
        client_spin.stop(5.0)
        client.destroy()  # a failed test's traceback holds the client: its node and DDS participant
        node.destroy_node()  # then lingered in the worker's graph (test_launch saw three)
        rclpy.shutdown(context=theirs)
        spin.stop(5.0)
        assembly.close()
        rclpy.shutdown(context=context)
        sim.close()


def half_sine(amplitude_deg: float, duration_s: float, points: int = 41) -> Any:
    """joint1 up and back, joint2 down and back, over ``duration_s``: positions and velocities, the
    last point at rest (a trajectory ending with a velocity is rejected, as the controller does)."""
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = ["joint1", "joint2"]
    a, w = math.radians(amplitude_deg), math.pi / duration_s
    for k in range(points):
        t = duration_s * k / (points - 1)
        p, v = a * math.sin(w * t), a * w * math.cos(w * t) if k < points - 1 else 0.0
        seconds = int(t)
        goal.trajectory.points.append(JointTrajectoryPoint(
            positions=[p, -p], velocities=[v, -v], time_from_start=Duration(sec=seconds, nanosec=int((t - seconds) * 1e9))))
    return goal


def send(rig: Rig, goal: Any, feedback: list[Any] | None = None) -> Any:
    sent = rig.client.send_goal_async(goal, feedback_callback=(lambda f: feedback.append(f.feedback))
                                      if feedback is not None else None)
    wait_for(sent.done, HANG_S, "the goal answered")
    return sent.result()


def result_of(handle: Any) -> Any:
    future = handle.get_result_async()
    wait_for(future.done, HANG_S, "the result")
    return future.result()


def positions(rig: Rig) -> tuple[float, float]:
    msg = rig.states[-1]
    return math.degrees(msg.position[0]), math.degrees(msg.position[1])


def test_a_half_sine_of_two_joints_is_tracked_and_succeeds(rig: Rig) -> None:
    from action_msgs.msg import GoalStatus

    feedback: list[Any] = []
    handle = send(rig, half_sine(30.0, 4.0), feedback)
    assert handle.accepted
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    assert done.result.error_code == FollowJointTrajectory.Result.SUCCESSFUL
    assert len(feedback) >= 10 and all(list(f.joint_names) == ["joint1", "joint2"] for f in feedback)
    times = [f.desired.time_from_start.sec + f.desired.time_from_start.nanosec * 1e-9 for f in feedback]
    assert times == sorted(times) and 2.0 < times[-1] <= 4.0  # through the run, on the trajectory's clock
    errors = [math.degrees(e) for f in feedback for e in f.error.positions]
    rms = math.sqrt(sum(e * e for e in errors) / len(errors))
    assert rms <= 0.5 and max(abs(e) for e in errors) <= 1.5, (rms, max(abs(e) for e in errors))
    n = len(rig.states)
    wait_for(lambda: len(rig.states) > n + 2, HANG_S, "/joint_states after the result")
    assert max(abs(p) for p in positions(rig)) <= 0.3, positions(rig)


def test_an_arm_again_while_a_goal_runs_leaves_it_running(rig: Rig) -> None:
    """/arm (every drive's enable) while a goal streams to its joints: they are armed already, so
    nothing is sent and nothing is refused meanwhile, and the goal succeeds. A loaded CI saw a
    second /arm abort a goal ("CSP setpoint refused: the drive is busy with enable"): the enable
    of an armed drive registered an operation for its SDO read, and a set-point fell in it."""
    from action_msgs.msg import GoalStatus

    feedback: list[Any] = []
    handle = send(rig, half_sine(30.0, 4.0), feedback)
    assert handle.accepted
    ended = handle.get_result_async()
    wait_for(lambda: ended.done() or bool(feedback), HANG_S, "the goal under way")
    enables = 0
    counted = [drive.channel.enables for drive in rig.assembly.driver]
    while not ended.done() and enables < 40:  # /arm again and again while it runs
        for drive in rig.assembly.driver:
            drive.enable()
        enables += 1
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, (enables, done.result.error_string)
    assert enables >= 10, enables  # the enables did fall while it ran
    # each counted as an enable (the drive system takes a wheel back on one), nothing walked again
    assert [drive.channel.enables - n for drive, n in zip(rig.assembly.driver, counted, strict=True)] == [enables] * 2


def silence_and_mark(rig: Rig) -> list[int]:
    """Both joints' TPDOs silenced (heartbeats on); then a marker frame put on the bus and handed
    on by the driver's receive thread: every sample the drives sent before the silence was handed on
    too (one wire, one order; a starved thread was 2-3 samples behind). Each joint's sample count then."""
    for node in (1, 2):
        apply_action(rig.sim, {"action": "tpdos", "node": node, "on": False})
    token = next(MARKERS).to_bytes(4, "little")
    marked = threading.Event()
    rig.assembly.driver.buses["can0"].network.subscribe(
        MARKER_COB, lambda cob, data, stamp: marked.set() if bytes(data) == token else None)
    with VirtualBus("can0", engine=rig.sim.engine) as marker:
        marker.send(can.Message(arbitration_id=MARKER_COB, data=token, is_extended_id=False))
    wait_for(marked.is_set, HANG_S, "the marker handed on by the driver's receive thread")
    return [d.cache.position_seq for d in rig.assembly.driver]


def seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def lag(rig: Rig, start_s: float, amplitude_deg: float, duration_s: float) -> float:
    """How late (s) /joint_states (by their stamps: when measured) are against the half-sine timed from
    ``start_s`` (node clock): the median over the run of each sample's error over the plan's velocity,
    where it moves (a median: a sample published late on a busy host does not move it)."""
    w = math.pi / duration_s
    lags = []
    for msg in list(rig.states):
        t = seconds(msg.header.stamp) - start_s
        velocity = amplitude_deg * w * math.cos(w * t)
        at = dict(zip(msg.name, msg.position, strict=False))  # a joint whose data are not fresh is absent
        if 0.0 <= t <= duration_s and abs(velocity) > 0.3 * amplitude_deg * w and {"joint1", "joint2"} <= set(at):
            plan = amplitude_deg * math.sin(w * t)
            lags += [(plan - math.degrees(at["joint1"])) / velocity, (math.degrees(at["joint2"]) + plan) / velocity]
    assert len(lags) > 20 * duration_s, len(lags)
    return statistics.median(lags)


def test_the_plan_runs_from_its_acceptance(rig: Rig) -> None:
    """Measured against the plan timed from the goal's acceptance (header stamp 0, as
    joint_trajectory_controller reads it), not from the driver's hand-over after its checks and
    mode switches (it ran about 0.1 s late): the joints lag it by the drive's response and a SYNC."""
    from action_msgs.msg import GoalStatus

    handle = send(rig, half_sine(30.0, 4.0))
    assert handle.accepted
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    late = lag(rig, seconds(handle.stamp), 30.0, 4.0)
    assert -0.02 < late < 0.06, late


#: joint_trajectory_controller's promise as issue 70 judges it: the measured positions against the
#: plan timed from the goal's acceptance, over the run, within this RMS and this maximum (deg)
TRACKING_RMS_DEG, TRACKING_MAX_DEG = 0.5, 1.5


#: a silence (the listener heard no set-point of joint1, or no SYNC) long enough for a drive holding
#: its last target to stray this far from the plan at its fastest is a starved host's (16 ms: 8 SYNC
#: periods at 500 Hz, 4 at 250 Hz); shorter ones are the pace kept (a switch of the interpreter's
#: lock is 5 ms) and judged
SILENT_STRAY_DEG = TRACKING_MAX_DEG / 4
#: no verdict when fewer of the plan's /joint_states than this share lie outside the silences' reach
JUDGED_SHARE_MIN = 0.8
#: the drive's own following after a silence (s): its measurements that long after it are the host's too
FOLLOWING_S = 0.02


def silences(frames: list[can.Message], silent_s: float, since: float) -> list[tuple[float, float, str]]:
    """(from, to, what) of each span of bus time of ``silent_s`` or longer after ``since`` (the
    plan's start) in which the listener heard no set-point of joint1 between two of them (the
    group's thread held) or no SYNC, from ``since`` on (its producer held, the bus's timer and not
    this driver's thread: a CSP drive takes its set-point at a SYNC, so without one it holds its
    last target as well). A first set-point late while SYNCs came is not one: it is judged."""
    out = []
    last: dict[int, float | None] = {SYNC: since, SETPOINTS[0]: None}
    for msg in frames:
        if msg.arbitration_id not in last or msg.timestamp <= since:
            continue
        before = last[msg.arbitration_id]
        if before is not None and msg.timestamp - before >= silent_s:
            out.append((before, msg.timestamp, "SYNC" if msg.arbitration_id == SYNC else "set-point"))
        last[msg.arbitration_id] = msg.timestamp
    return sorted(out)


def tracking_errors(rig: Rig, start_s: float, amplitude_deg: float, duration_s: float,
                    unjudged: Sequence[tuple[float, float]] = ()) -> tuple[list[float], int, float]:
    """Each /joint_states position (stamped when measured: its SYNC, on the bus's clock) against the
    half-sine timed from ``start_s`` (the node's clock), over the plan's whole time but within the
    ``unjudged`` spans (bus stamps); how many of the plan's /joint_states were in them; and the
    plan's time of the worst (s, to say where it was)."""
    w = math.pi / duration_s
    errors: list[float] = []
    worst_at, worst = 0.0, -1.0
    skipped = 0
    for msg in list(rig.states):
        stamp = seconds(msg.header.stamp)
        t = stamp - start_s
        at = dict(zip(msg.name, msg.position, strict=False))
        if 0.0 <= t <= duration_s and {"joint1", "joint2"} <= set(at):
            if any(a < stamp <= b for a, b in unjudged):
                skipped += 1
                continue
            plan = amplitude_deg * math.sin(w * t)
            errors += [math.degrees(at["joint1"]) - plan, math.degrees(at["joint2"]) + plan]
            if max(abs(errors[-1]), abs(errors[-2])) > worst:
                worst_at, worst = t, max(abs(errors[-1]), abs(errors[-2]))
    return errors, skipped, worst_at


@pytest.mark.parametrize("rig", [{"sync_period_s": 0.004}, {"sync_period_s": 0.002}], indirect=True,
                         ids=["250Hz", "500Hz"])
def test_a_trajectory_is_tracked_against_the_plan_from_acceptance(
        rig: Rig, listener_factory: Callable[[SimService], can.BusABC]) -> None:
    """At 250 and 500 Hz (the bus's SYNC), a 4 s half-sine to +-30 deg and back: the joints'
    measured positions against the plan timed from the goal's acceptance (header stamp 0), as a
    MoveIt user measures it: within 0.5 deg RMS and 1.5 deg at most (issue 70: 1.0-1.7 deg RMS,
    2.2-3.5 deg max, the plan run from the driver's hand-over after its checks and mode switches).
    Judged by the measurements' own stamps (their SYNC), not by when anything was received.

    A starved host holds the group's thread now and then, or the SYNC's producer (the wire shows
    it: no set-point between two, or no SYNC, for as long as the plan at its fastest moves
    SILENT_STRAY_DEG): the drives then hold their last target while the plan runs on, and the group
    catches up within the joints' max velocity (180 deg/s, the plan's peak 23.6). The measurements
    from a silence's start to as long again after its end (and 20 ms at least: the drive's own
    following) are the host's, not the tracking's, and are left out. A SYNC silent from acceptance
    (the bus's timer starved: evidence this driver's thread cannot make) leaves out those up to the
    plan's first knot and the drive's following, 0.12 s: the plan's peak speed is at its start, and
    the group joins it from the joints at rest by then. A first set-point late while SYNCs came is
    judged: it is the group's own (issue 70's plan run from the hand-over). (Beside two busy loops
    per core: the SYNC silent for 30 ms from acceptance, the worst error then 1.64 deg at 83 ms; a
    first set-point 22-27 ms late with SYNCs on time, 1.1 deg at most, within the bound.)
    Everything else is judged, and a plan timed late, or stretched by a silence, stays wrong beyond
    them. No verdict where less than 80 % is left to judge, or where the simulator counted its own
    thread held (its drives' physics late): the listener's record and the simulator decide, not the
    group's own counters."""
    from action_msgs.msg import GoalStatus

    runner = rig.sim.simulators["can0"]
    holds = runner.clock.holds
    frames: list[can.Message] = []
    notifier = can.Notifier(listener_factory(rig.sim), [frames.append], timeout=0.1)
    try:
        handle = send(rig, half_sine(30.0, 4.0))
        assert handle.accepted
        done = result_of(handle)
    finally:
        notifier.stop()
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    assert any(m.arbitration_id == SETPOINTS[0] for m in frames), "the listener heard no set-point"
    (group,) = rig.assembly.trajectories.values()
    peak_step_deg = 30.0 * math.pi / 4.0 * group.period_s  # the half-sine's fastest travel in one period
    accepted = seconds(handle.stamp)
    gaps = silences(frames, math.ceil(SILENT_STRAY_DEG / peak_step_deg) * group.period_s, accepted)
    first_knot_s = 4.0 / 40  # half_sine's points
    unjudged = [(a, max(b + max(b - a, FOLLOWING_S),
                        # no SYNC from acceptance: the group joins the plan by its first knot (TrajectoryGroup._join)
                        accepted + first_knot_s + FOLLOWING_S if a == accepted else 0.0)) for a, b, _ in gaps]
    errors, skipped, worst_at = tracking_errors(rig, accepted, 30.0, 4.0, unjudged)
    judged = len(errors) // 2
    assert judged + skipped > 20 * 4.0, (judged, skipped)  # /joint_states heard all along
    rms, worst = math.sqrt(sum(e * e for e in errors) / len(errors)), max(abs(e) for e in errors)
    said = (f"RMS {rms:.2f} deg, max {worst:.2f} deg at {worst_at * 1e3:.0f} ms over {judged} /joint_states; {skipped}"
            f" left out near {len(gaps)} silence(s) (no set-point or no SYNC; they may overlap), the longest"
            f" {max((b - a for a, b, _ in gaps), default=0.0) * 1e3:.0f} ms; (from ms, ms long, of what):"
            f" {[(round((a - accepted) * 1e3), round((b - a) * 1e3), what) for a, b, what in gaps]}")
    if judged < JUDGED_SHARE_MIN * (judged + skipped):
        pytest.skip(f"no verdict: a starved host ({said})")
    if runner.clock.holds > holds:  # the simulated drives' physics, not the driver, ran late
        pytest.skip(f"no verdict: the simulator's thread was held {runner.clock.holds - holds} time(s) ({said})")
    assert rms <= TRACKING_RMS_DEG and worst <= TRACKING_MAX_DEG, said


def test_a_plan_stamped_ahead_waits_then_tracks(rig: Rig) -> None:
    """A header stamp 1 s after now: nothing moves before it, then the plan is tracked from it."""
    from action_msgs.msg import GoalStatus

    goal = half_sine(30.0, 2.0)
    now = rig.assembly.node.get_clock().now().nanoseconds * 1e-9 + 1.0
    goal.trajectory.header.stamp.sec, goal.trajectory.header.stamp.nanosec = int(now), int(now % 1 * 1e9)
    handle = send(rig, goal)
    assert handle.accepted
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    before = [m for m in rig.states if seconds(handle.stamp) < seconds(m.header.stamp) < now - 0.05]
    assert len(before) > 20 and max(abs(math.degrees(p)) for m in before for p in m.position) < 0.2
    late = lag(rig, now, 30.0, 2.0)
    assert -0.02 < late < 0.06, late


def test_a_plan_stamped_in_the_past_runs_from_its_acceptance(rig: Rig) -> None:
    """A header stamp 1 s before now (the client's clock behind the driver's): the plan runs from
    acceptance, whole, as if stamped 0; it was joined 1 s in and caught up at the joints' limit from
    rest (joint_trajectory_controller jumps into it)."""
    from action_msgs.msg import GoalStatus

    goal = half_sine(30.0, 4.0)
    then = rig.assembly.node.get_clock().now().nanoseconds * 1e-9 - 1.0
    goal.trajectory.header.stamp.sec, goal.trajectory.header.stamp.nanosec = int(then), int(then % 1 * 1e9)
    handle = send(rig, goal)
    assert handle.accepted
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    late = lag(rig, seconds(handle.stamp), 30.0, 4.0)
    assert -0.02 < late < 0.06, late


def test_a_cancel_as_the_goal_ends_on_its_own_leaves_its_outcome(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """The group reached the goal; a cancel accepted before the server's next look does not turn that
    into CANCELED (MoveIt reads CANCELED as preempted): the controller cancels only a goal still active.
    The group's thread is held as it ends the goal until the cancel was answered."""
    from action_msgs.msg import GoalStatus

    from motor_driver.follow.goal import GoalRun

    ending, answered = threading.Event(), threading.Event()
    finish = GoalRun.finish

    def held(self: GoalRun, outcome: Any) -> None:
        if not outcome.canceled and not ending.is_set():
            ending.set()
            answered.wait(HANG_S)
        finish(self, outcome)

    monkeypatch.setattr(GoalRun, "finish", held)
    handle = send(rig, half_sine(10.0, 0.5))
    assert handle.accepted
    assert ending.wait(HANG_S), "the goal never ended"
    cancel = handle.cancel_goal_async()
    wait_for(cancel.done, HANG_S, "the cancel answered")
    answered.set()
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, (done.status, done.result.error_string)
    assert done.result.error_code == FollowJointTrajectory.Result.SUCCESSFUL


def test_a_cancelled_goal_leaves_the_joints_still(rig: Rig) -> None:
    from action_msgs.msg import GoalStatus

    feedback: list[Any] = []
    handle = send(rig, half_sine(40.0, 4.0), feedback)
    ended = handle.get_result_async()
    wait_for(lambda: ended.done() or (bool(feedback) and feedback[-1].desired.time_from_start.sec >= 1), HANG_S,
             "the goal under way")
    assert not ended.done(), ended.result().result.error_string
    cancel = handle.cancel_goal_async()
    wait_for(cancel.done, HANG_S, "the cancel answered")
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_CANCELED
    # the joints settle where the ramp left them (no set-point follows the result: tests/test_follow.py)
    # and stay: 50 /joint_states in a row (half a second at 100 a second) within 0.01 deg
    def still() -> bool:
        last = [math.degrees(s.position[0]) for s in rig.states[-50:]]
        return len(last) == 50 and max(last) - min(last) < 0.01
    wait_for(still, HANG_S, "joint1 still")
    assert 10.0 < positions(rig)[0] < 40.0  # stopped on its way, not at the end


def test_a_fault_of_the_server_mid_goal_aborts_it_and_the_joints_stop(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in the goal's follow loop (here its feedback raises once under way): rclpy would abort
    the goal with a default result (error_code 0, SUCCESSFUL) and the joints would move on to the
    trajectory's end. The goal ends INVALID_GOAL naming the fault, and the motion is ramped down."""
    from action_msgs.msg import GoalStatus

    from nodes.actions import follow_trajectory

    fill = follow_trajectory.fill_feedback
    calls: list[int] = []

    def failing_once_under_way(feedback: Any, progress: Any) -> Any:
        filled = fill(feedback, progress)
        if not calls and filled.desired.time_from_start.sec >= 1:  # a second into the plan: joint1 near 28 deg
            calls.append(1)
            raise RuntimeError("a bug in the feedback")
        return filled

    monkeypatch.setattr(follow_trajectory, "fill_feedback", failing_once_under_way)
    done = result_of(send(rig, half_sine(40.0, 4.0)))
    assert done.status == GoalStatus.STATUS_ABORTED
    assert done.result.error_code == FollowJointTrajectory.Result.INVALID_GOAL
    assert "failed unexpectedly (RuntimeError: a bug in the feedback)" in done.result.error_string

    def still() -> bool:
        last = [math.degrees(s.position[0]) for s in rig.states[-50:]]
        return len(last) == 50 and max(last) - min(last) < 0.01
    wait_for(still, HANG_S, "joint1 still")
    assert 10.0 < positions(rig)[0] < 40.0  # stopped on its way, not carried on to the end (0 deg)


@pytest.mark.parametrize("rig", [{"sdo_timeout_ms": 10000}], indirect=True)
def test_the_server_answers_while_a_goals_switch_to_streaming_waits_on_the_drive(rig: Rig) -> None:
    """A goal's switch of its joints to a streamed mode (SDO: it waits on the drive) happens in the
    goal callback, before acceptance, so that it never shifts the plan: with joint1's SDO answers
    held 5 s (below its 10 s SDO timeout), another goal (an unknown joint) is answered, rejected, while
    the switch still waits; the first is accepted once the drive answered, and succeeds."""
    from action_msgs.msg import GoalStatus

    sim = rig.sim.simulator_for(1)
    answered = sim.call(lambda: sim.drive(1).counters["sdo"])
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 5.0})
    first = rig.client.send_goal_async(half_sine(20.0, 2.0))
    wait_for(lambda: sim.call(lambda: sim.drive(1)._delayed_sdo is not None), HANG_S, "the switch's SDO at the drive")
    unknown = half_sine(10.0, 1.0)
    unknown.trajectory.joint_names = ["joint1", "knee"]
    assert not send(rig, unknown).accepted
    assert sim.call(lambda: sim.drive(1)._delayed_sdo is not None and sim.drive(1).counters["sdo"] == answered), \
        "the other goal was answered only after the drive answered the switch"
    assert not first.done(), "accepted before its joints could stream"
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 0.0})
    wait_for(first.done, HANG_S, "the first goal answered")
    handle = first.result()
    assert handle.accepted
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string


@pytest.mark.parametrize("rig", [{"sdo_timeout_ms": 10000}], indirect=True)
def test_move_joint_answers_a_cancel_while_its_start_waits_on_the_drive(rig: Rig) -> None:
    """move_joint's start writes the profile speed by SDO: with joint1's answers held 5 s, the
    cancel is answered while the write still waits, and nothing moves (the move is never sent)."""
    from action_msgs.msg import GoalStatus
    from rovercan_msgs.action import MoveJoint

    client = ActionClient(rig.client._node, MoveJoint, "move_joint")
    assert client.wait_for_server(timeout_sec=HANG_S), "move_joint not served"
    sim = rig.sim.simulator_for(1)
    answered = sim.call(lambda: sim.drive(1).counters["sdo"])
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 5.0})
    sent = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=30.0, speed_deg_s=20.0))
    wait_for(sent.done, HANG_S, "the goal answered")
    handle = sent.result()
    wait_for(lambda: sim.call(lambda: sim.drive(1)._delayed_sdo is not None), HANG_S, "the speed's SDO at the drive")
    cancel = handle.cancel_goal_async()
    wait_for(cancel.done, HANG_S, "the cancel answered")
    assert sim.call(lambda: sim.drive(1)._delayed_sdo is not None and sim.drive(1).counters["sdo"] == answered), \
        "the cancel was answered only after the drive answered the write"
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 0.0})
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_CANCELED and done.result.message == "canceled before it moved", \
        done.result.message
    client.destroy()


def test_move_joint_gives_up_after_its_overall_timeout(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """A joint whose shaft is blocked never gets to its target: move_joint halts it and aborts,
    naming how far it is, after the move's own time and a margin (it waited for ever)."""
    from action_msgs.msg import GoalStatus
    from rovercan_msgs.action import MoveJoint

    from nodes.actions import driver_actions as actions

    monkeypatch.setattr(actions, "MOVE_MARGIN_S", 0.5)
    client = ActionClient(rig.client._node, MoveJoint, "move_joint")
    assert client.wait_for_server(timeout_sec=HANG_S), "move_joint not served"
    apply_action(rig.sim, {"action": "load", "node": 1, "stall": True})
    sent = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=30.0, speed_deg_s=60.0))
    wait_for(sent.done, HANG_S, "the goal answered")
    done = result_of(sent.result())
    apply_action(rig.sim, {"action": "load", "node": 1, "stall": False})
    assert done.status == GoalStatus.STATUS_ABORTED and not done.result.success
    assert "joint1: not at 30.00 deg" in done.result.message and "short" in done.result.message, done.result.message
    client.destroy()


def moving(rig: Rig, target_deg: float, speed_deg_s: float = 20.0) -> tuple[Any, Any]:
    """A move_joint client, and its goal for joint1 (at 20 deg/s) under way past 2 deg."""
    from rovercan_msgs.action import MoveJoint

    client = ActionClient(rig.client._node, MoveJoint, "move_joint")
    assert client.wait_for_server(timeout_sec=HANG_S), "move_joint not served"
    sent = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=target_deg, speed_deg_s=speed_deg_s))
    wait_for(sent.done, HANG_S, "the move answered")
    drive = rig.assembly.driver.drive("joint1")
    wait_for(lambda: drive.snapshot().angle_deg > 2.0, HANG_S, f"joint1 on its way to {target_deg:g} deg")
    return client, sent


def test_a_newer_move_joint_goal_preempts_the_older_on_its_joint(rig: Rig) -> None:
    """Two move_joint goals for one joint: the newer is the joint's move, the older ends ABORTED as
    preempted at its next look (it ran on, and its timeout halted the newer's motion)."""
    from action_msgs.msg import GoalStatus
    from rovercan_msgs.action import MoveJoint

    client, sent = moving(rig, 60.0)
    newer = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=-5.0, speed_deg_s=60.0))
    wait_for(newer.done, HANG_S, "the second goal answered")
    older = result_of(sent.result())
    assert older.status == GoalStatus.STATUS_ABORTED and not older.result.success
    assert older.result.message == "joint1: preempted by a newer move_joint goal; the joint goes to its target", \
        older.result.message
    done = result_of(newer.result())
    assert done.status == GoalStatus.STATUS_SUCCEEDED and done.result.message == "at -5.00 deg", done.result.message
    assert abs(done.result.angle + 5.0) < 0.5
    client.destroy()


@pytest.mark.parametrize("rig", [{"sdo_timeout_ms": 10000}], indirect=True)
def test_a_cancel_of_the_older_goal_while_a_newer_starts_leaves_the_newer_s_move_alone(rig: Rig) -> None:
    """The older goal of a joint is cancelled while a newer one starts (its speed's SDO held at the
    drive): the older's cancel waits for the newer's start and the newer preempts it (a halt then
    would stop the newer's move once it went out, and the newer would end "halted"); the newer ends
    at its own target."""
    from action_msgs.msg import GoalStatus
    from rovercan_msgs.action import MoveJoint

    client = ActionClient(rig.client._node, MoveJoint, "move_joint")
    assert client.wait_for_server(timeout_sec=HANG_S), "move_joint not served"
    looks: list[Any] = []  # the older goal's feedback: one a look at the joint
    sent = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=85.0, speed_deg_s=4.0),
                                  feedback_callback=looks.append)
    wait_for(sent.done, HANG_S, "the move answered")
    drive = rig.assembly.driver.drive("joint1")
    wait_for(lambda: drive.snapshot().angle_deg > 2.0, HANG_S, "joint1 on its way to 85 deg")
    sim = rig.sim.simulator_for(1)
    # the newer's SDO answered 9 s after it came (within the 10 s SDO timeout): the two looks below
    # take a tenth of a second; the older, at 4 deg/s, is far from 85 deg when the newer moves
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 9.0})
    newer = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=-5.0, speed_deg_s=60.0))
    wait_for(lambda: sim.call(lambda: sim.drive(1)._delayed_sdo is not None), HANG_S, "the newer's speed SDO at the drive")
    older = sent.result()
    cancel = older.cancel_goal_async()
    wait_for(cancel.done, HANG_S, "the cancel answered")
    seen = len(looks)
    # two more looks: the older saw its cancel while the newer started, and went on
    wait_for(lambda: len(looks) >= seen + 2, HANG_S, "the older goal looking on, its cancel deferred")
    assert sim.call(lambda: sim.drive(1)._delayed_sdo is not None), "the newer's start is still held"
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 0.0})
    wait_for(newer.done, HANG_S, "the newer goal answered")
    first = result_of(older)  # CANCELED, as every goal whose cancel was accepted ends; its words say why
    assert first.status == GoalStatus.STATUS_CANCELED and not first.result.success, first.status
    assert first.result.message == "joint1: preempted by a newer move_joint goal; the joint goes to its target", \
        first.result.message
    done = result_of(newer.result())
    assert done.status == GoalStatus.STATUS_SUCCEEDED and done.result.message == "at -5.00 deg", done.result.message
    client.destroy()


def test_a_newer_move_joint_goal_refused_preempts_nothing(rig: Rig) -> None:
    """A newer goal for the joint whose target is beyond its limits is refused in its start, before
    anything moves: the running goal is still the joint's move and ends at its own target (it ended
    "preempted" while the joint went on to that target unwatched)."""
    from action_msgs.msg import GoalStatus
    from rovercan_msgs.action import MoveJoint

    client, sent = moving(rig, 30.0)
    refused = client.send_goal_async(MoveJoint.Goal(joint="joint1", target_deg=170.0, speed_deg_s=20.0))
    wait_for(refused.done, HANG_S, "the second goal answered")
    bad = result_of(refused.result())
    assert bad.status == GoalStatus.STATUS_ABORTED and "170" in bad.result.message, bad.result.message
    done = result_of(sent.result())
    assert done.status == GoalStatus.STATUS_SUCCEEDED and done.result.message == "at 30.00 deg", done.result.message
    client.destroy()


def test_a_trajectory_taking_a_moving_joint_ends_its_move_joint_goal_unhalted(rig: Rig) -> None:
    """A FollowJointTrajectory goal takes a joint a move_joint goal is moving (to CSP): the move is
    over, said at once, and the trajectory runs unhalted (the move ran on and its timeout halted
    the joint under the trajectory)."""
    from action_msgs.msg import GoalStatus

    client, sent = moving(rig, 30.0)
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = ["joint1", "joint2"]
    goal.trajectory.points.append(JointTrajectoryPoint(positions=[math.radians(10.0), 0.0], velocities=[0.0, 0.0],
                                                       time_from_start=Duration(sec=2)))
    handle = send(rig, goal)
    assert handle.accepted
    move = result_of(sent.result())
    assert move.status == GoalStatus.STATUS_ABORTED and "joint1: the move is over: the joint left profile position" \
        in move.result.message, move.result.message
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.error_string
    assert abs(positions(rig)[0] - 10.0) < 0.5
    client.destroy()


def test_a_degree_command_on_a_moving_joint_ends_its_move_joint_goal(rig: Rig) -> None:
    """A position command (``degree_cmd``) to a joint a move_joint goal is moving sets its target:
    the goal is over, said at once, and the joint goes to the command's target (the goal watched on
    for its own and its timeout halted the joint)."""
    from action_msgs.msg import GoalStatus
    from std_msgs.msg import Float32

    from nodes.process.qos import SETPOINT_QOS

    client, sent = moving(rig, 30.0)
    drive = rig.assembly.driver.drive("joint1")
    publisher = rig.client._node.create_publisher(Float32, f"{drive.config.ros_prefix}/degree_cmd", SETPOINT_QOS)
    wait_for(lambda: publisher.get_subscription_count() > 0, HANG_S, "the driver's degree_cmd subscription")
    publisher.publish(Float32(data=10.0))
    move = result_of(sent.result())
    assert move.status == GoalStatus.STATUS_ABORTED, move.result.message
    assert move.result.message == "joint1: the move is over: another command set its target (10.00 deg)", \
        move.result.message
    wait_for(lambda: abs(drive.snapshot().angle_deg - 10.0) < 0.5 and drive.snapshot().target_reached, HANG_S,
             "joint1 at the command's 10 deg")
    client.destroy()


def test_a_halt_of_a_moving_joint_ends_its_move_joint_goal_naming_the_halt(rig: Rig) -> None:
    """``<joint>/halt`` while a move_joint goal moves the joint: the goal is over, said at once and
    naming the halt (it watched on until its timeout and then asked whether the joint was blocked),
    and the joint stands short of the goal's target, enabled."""
    from action_msgs.msg import GoalStatus
    from std_srvs.srv import Trigger

    client, sent = moving(rig, 60.0, 2.0)  # its timeout (35 s) beyond the test's wait: ended by the halt, not by it
    drive = rig.assembly.driver.drive("joint1")
    halt = rig.client._node.create_client(Trigger, f"{drive.config.ros_prefix}/halt")
    assert halt.wait_for_service(timeout_sec=HANG_S), "no halt service"
    answer = halt.call_async(Trigger.Request())
    wait_for(answer.done, HANG_S, "the halt answered")
    assert answer.result().success, answer.result().message
    move = result_of(sent.result())
    assert move.status == GoalStatus.STATUS_ABORTED, move.result.message
    assert move.result.message.startswith("joint1: the move is over: the joint was halted (a halt command,"), \
        move.result.message
    assert "blocked" not in move.result.message
    assert drive.snapshot().angle_deg < 55.0 and drive.snapshot().state.name == "OPERATION_ENABLED"
    rig.client._node.destroy_client(halt)
    client.destroy()


def assert_preempted(older: Any) -> None:
    """Ended as joint_trajectory_controller (jazzy >= 4.41.0, preempt_active_goal) ends a goal a newer
    one preempts: ABORTED, INVALID_GOAL, its words (up to 4.40: CANCELED, "cancelled due to")."""
    from action_msgs.msg import GoalStatus

    assert older.status == GoalStatus.STATUS_ABORTED, (older.status, older.result.error_string)
    assert older.result.error_code == FollowJointTrajectory.Result.INVALID_GOAL
    assert older.result.error_string == "Current goal preempted by new incoming action."


@pytest.mark.parametrize("rig", [{"sdo_timeout_ms": 10000}], indirect=True)
def test_goals_start_in_the_order_they_came_while_the_first_waits_on_the_drive(rig: Rig) -> None:
    """A second goal sent while the first one's switch to streaming waits on the drive starts
    after it and preempts it, as a newer goal does; it is neither refused as "busy" nor run
    before the first (which would then preempt the newer goal)."""
    from action_msgs.msg import GoalStatus

    sim = rig.sim.simulator_for(1)
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 3.0})
    asked = rig.client.send_goal_async(half_sine(20.0, 2.0))
    wait_for(lambda: sim.call(lambda: sim.drive(1)._delayed_sdo is not None), HANG_S, "the first switch at the drive")
    again = rig.client.send_goal_async(half_sine(10.0, 2.0))
    apply_action(rig.sim, {"action": "sdo", "node": 1, "delay_s": 0.0})
    wait_for(lambda: asked.done() and again.done(), HANG_S, "both goals answered")
    first, second = asked.result(), again.result()
    assert first.accepted and second.accepted
    older, newer = result_of(first), result_of(second)
    assert_preempted(older)
    assert newer.status == GoalStatus.STATUS_SUCCEEDED, newer.result.error_string


def test_a_goal_beyond_a_limit_is_rejected_and_nothing_moves(rig: Rig, listener_factory: ListenerFactory) -> None:
    frames: list[can.Message] = []
    notifier = can.Notifier(listener_factory(rig.sim), [frames.append], timeout=0.1)
    try:
        beyond = half_sine(100.0, 4.0)  # joint1 to 100 deg: max_deg is 90
        assert not send(rig, beyond).accepted  # rejected in the goal callback, as the controller does
        mark = len(frames)
        wait_for(lambda: sum(m.arbitration_id == SYNC for m in frames[mark:]) >= 3, HANG_S, "3 SYNCs after the result")
    finally:
        notifier.stop()
    assert not [m for m in frames if m.arbitration_id in SETPOINTS or 0x601 <= m.arbitration_id <= 0x602], \
        "a refused goal put a set-point or an SDO on the bus"


def test_the_client_example_of_the_docs_runs(rig: Rig, tmp_path: Path) -> None:
    """docs/ros.md's plain client, as a user would paste it into a file, against this graph."""
    text = (REPO / "docs" / "ros.md").read_text()
    found = re.search(r"<!-- example: follow_joint_trajectory client -->\n```py\n(.*?)^```", text, re.DOTALL | re.MULTILINE)
    assert found, "docs/ros.md has the client example"
    script = tmp_path / "client.py"
    script.write_text(found.group(1))
    env = os.environ | ({"ROS_DOMAIN_ID": str(rig.domain)} if rig.domain is not None else {})
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "error_code 0" in run.stdout


def test_what_can_be_judged_at_goal_time_is_rejected(rig: Rig) -> None:
    """As joint_trajectory_controller's goal callback: an unknown joint, a goal of some joints
    (allow_partial_joints_goal false), times not increasing, a past stamp, an illegal tolerance."""
    from control_msgs.msg import JointTolerance

    unknown = half_sine(10.0, 1.0)
    unknown.trajectory.joint_names = ["joint1", "knee"]
    partial = half_sine(10.0, 1.0)
    partial.trajectory.joint_names = ["joint1"]
    for point in partial.trajectory.points:
        point.positions, point.velocities = point.positions[:1], point.velocities[:1]
    backwards = half_sine(10.0, 1.0)
    backwards.trajectory.points[3].time_from_start = Duration(sec=0, nanosec=0)
    past = half_sine(10.0, 1.0)
    now = rig.assembly.node.get_clock().now().nanoseconds
    past.trajectory.header.stamp.sec = int(now // 10**9) - 10  # its 1 s ended 9 s ago
    illegal = half_sine(10.0, 1.0)
    illegal.path_tolerance = [JointTolerance(name="joint1", position=-0.5)]
    acceleration = half_sine(10.0, 1.0)  # a bound this driver cannot hold (it measures no acceleration)
    acceleration.goal_tolerance = [JointTolerance(name="joint1", acceleration=0.5)]
    for name, goal in (("unknown", unknown), ("partial", partial), ("backwards", backwards), ("past", past),
                       ("illegal", illegal), ("acceleration", acceleration)):
        assert not send(rig, goal).accepted, name


def test_a_trajectory_ending_in_motion_or_with_effort_is_rejected_and_nothing_moves(rig: Rig) -> None:
    """joint_trajectory_controller's validate_trajectory_msg: a last point with a velocity is rejected
    (allow_nonzero_velocity_at_trajectory_end false, the default: the joints would stop dead from
    60 deg/s at its end), and so is a point with effort (only with an effort command interface)."""
    moving = FollowJointTrajectory.Goal()
    moving.trajectory.joint_names = ["joint1", "joint2"]
    moving.trajectory.points = [
        JointTrajectoryPoint(positions=[0.0, 0.0], velocities=[0.0, 0.0], time_from_start=Duration(sec=0)),
        JointTrajectoryPoint(positions=[math.radians(30.0), 0.0], velocities=[math.radians(60.0), 0.0],
                             time_from_start=Duration(sec=1))]
    effort = half_sine(5.0, 1.0, points=5)
    for point in effort.trajectory.points:
        point.effort = [1.0, 1.0]
    for name, goal in (("moving at the end", moving), ("effort", effort)):
        assert not send(rig, goal).accepted, name
    n = len(rig.states)
    wait_for(lambda: len(rig.states) > n + 5, HANG_S, "/joint_states after the rejections")
    assert max(abs(p) for p in positions(rig)) <= 0.1, positions(rig)


def send_to_an_unreachable_goal(rig: Rig, joint1_deg: float, end_s: float, path_tolerance_rad: float = 0.0) -> Any:
    """A goal of one point at ``end_s`` s, joint1 to ``joint1_deg`` (between two counts of its encoder:
    its goal tolerance of 1e-6 rad is never met); the handle and its result's future once the
    trajectory's end is past (its feedback there), or the goal ended."""
    from control_msgs.msg import JointTolerance

    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = ["joint1", "joint2"]
    goal.trajectory.points = [JointTrajectoryPoint(positions=[math.radians(joint1_deg), 0.0], velocities=[0.0, 0.0],
                                                   time_from_start=Duration(sec=0, nanosec=int(end_s * 1e9)))]
    goal.path_tolerance = [JointTolerance(name="joint1", position=path_tolerance_rad)]
    goal.goal_tolerance = [JointTolerance(name="joint1", position=1e-6)]
    feedback: list[Any] = []
    handle = send(rig, goal, feedback)
    assert handle.accepted
    ended = handle.get_result_async()
    wait_for(lambda: ended.done() or any(seconds(f.desired.time_from_start) >= end_s for f in feedback), HANG_S,
             "the trajectory's end")
    return handle, ended


@pytest.mark.parametrize("rig", [{"group": {"goal_time_tolerance_s": 0.0}}], indirect=True)
def test_a_goal_time_tolerance_of_zero_waits_for_the_goal_without_a_bound(rig: Rig) -> None:
    """joint_trajectory_controller's update() bounds the wait for the goal tolerance only where
    goal_time != 0: the group's goal_time_tolerance_ms 0 (a JTC config ported), the goal's 0 (the
    group's), and a goal tolerance no count of the encoder meets (10.0009 deg: 0.0007 deg at least
    from every count): the goal stays active after its end, 100 /joint_states on, until cancelled.
    (It ended GOAL_TOLERANCE_VIOLATED at the first SYNC after its end.)"""
    from action_msgs.msg import GoalStatus

    handle, ended = send_to_an_unreachable_goal(rig, 10.0009, 0.5)
    n = len(rig.states)
    wait_for(lambda: ended.done() or len(rig.states) > n + 100, HANG_S, "100 /joint_states after the end")
    assert not ended.done(), ended.result().result.error_string
    handle.cancel_goal_async()
    assert result_of(handle).status == GoalStatus.STATUS_CANCELED


@pytest.mark.parametrize("rig", [{"group": {"goal_time_tolerance_s": 0.0}}], indirect=True)
def test_the_path_tolerance_ends_with_the_trajectory(rig: Rig) -> None:
    """joint_trajectory_controller's update() checks the path (state) tolerance only before the last
    point: past the end only the goal tolerance and the goal time apply. A goal to 0.0009 deg (no
    count of the encoder meets its goal tolerance; goal time 0: no bound) with a path tolerance of
    1e-3 rad, and a load within the drive's torque pushing joint1 off after the end (0.2 deg and more):
    the goal stays active, 100 /joint_states on, until cancelled. (It ended PATH_TOLERANCE_VIOLATED.)"""
    from action_msgs.msg import GoalStatus

    handle, ended = send_to_an_unreachable_goal(rig, 0.0009, 0.2, path_tolerance_rad=1e-3)
    n = len(rig.states)
    apply_action(rig.sim, {"action": "load", "node": 1, "nm": 2.5})
    try:
        wait_for(lambda: ended.done() or len(rig.states) > n + 100, HANG_S, "100 /joint_states after the load")
    finally:
        apply_action(rig.sim, {"action": "load", "node": 1, "nm": 0.0})
    assert not ended.done(), ended.result().result.error_string
    handle.cancel_goal_async()
    assert result_of(handle).status == GoalStatus.STATUS_CANCELED


def test_a_replanned_goal_preempts_the_first_aborted_as_the_controller_does(rig: Rig) -> None:
    """MoveIt's replan: a second goal from /joint_states 1.5 s into a first. It is accepted; the
    first ends ABORTED with INVALID_GOAL and joint_trajectory_controller's message (jazzy >= 4.41.0;
    it ended CANCELED as up to 4.40); the second is joined from the set-point and succeeds. (It was
    refused on the start tolerance once.)"""
    from action_msgs.msg import GoalStatus

    feedback: list[Any] = []
    first = send(rig, half_sine(30.0, 4.0), feedback)
    assert first.accepted
    wait_for(lambda: bool(feedback) and feedback[-1].desired.time_from_start.sec * 1e9
             + feedback[-1].desired.time_from_start.nanosec >= 1.5e9, HANG_S, "1.5 s into the first goal")
    here = rig.states[-1]
    replan = FollowJointTrajectory.Goal()
    replan.trajectory.joint_names = list(here.name)
    replan.trajectory.points = [
        JointTrajectoryPoint(positions=list(here.position), time_from_start=Duration(sec=0)),
        JointTrajectoryPoint(positions=[0.0, 0.0], velocities=[0.0, 0.0], time_from_start=Duration(sec=2))]
    second = send(rig, replan)
    assert second.accepted
    older, newer = result_of(first), result_of(second)
    assert_preempted(older)
    assert newer.status == GoalStatus.STATUS_SUCCEEDED, newer.result.error_string


def test_a_cancel_is_honoured_while_no_sample_comes(rig: Rig) -> None:
    """Every joint's TPDOs silenced mid-goal (heartbeats on), then a cancel: the goal ends CANCELED
    while the drives are still silent (it waited for the data to come back). The group's waits
    without a sample reach /diagnostics ("rovercan: follow arm_controller")."""
    from action_msgs.msg import GoalStatus
    from diagnostic_msgs.msg import DiagnosticArray

    from nodes.process.qos import DIAGNOSTICS_QOS

    said: list[Any] = []
    rig.client._node.create_subscription(
        DiagnosticArray, "/diagnostics",
        lambda a: said.extend(s for s in a.status if s.name == "rovercan: follow arm_controller"), DIAGNOSTICS_QOS)
    wait_for(lambda: bool(said), HANG_S, "the group's status on /diagnostics")
    assert {v.key: v.value for v in said[-1].values} == {"errors": "0", "late samples": said[-1].values[1].value,
                                                          "silences": said[-1].values[2].value,
                                                          "plan behind at most (s)": said[-1].values[3].value}
    feedback: list[Any] = []
    handle = send(rig, half_sine(30.0, 4.0), feedback)
    wait_for(lambda: bool(feedback) and feedback[-1].desired.time_from_start.sec >= 1, HANG_S, "the goal under way")
    seq = silence_and_mark(rig)
    cancel = handle.cancel_goal_async()
    wait_for(cancel.done, HANG_S, "the cancel answered")
    done = result_of(handle)
    silent = [d.cache.position_seq for d in rig.assembly.driver]
    for node in (1, 2):
        apply_action(rig.sim, {"action": "tpdos", "node": node, "on": True})
    assert seq == silent, (seq, silent)  # no sample after the marker: they were silent
    assert done.status in (GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED), done.result.error_string
    mark = len(said)
    wait_for(lambda: len(said) > mark and int({v.key: v.value for v in said[-1].values}["silences"]) > 0, HANG_S,
             "the silences counted on /diagnostics")


def test_a_goal_whose_joints_fall_silent_ends_aborted_while_they_are_silent(rig: Rig) -> None:
    """Every joint's TPDOs silenced mid-goal (heartbeats on), no cancel: the verdict says late once
    their data is older than its staleness bound, and the goal ends ABORTED naming it, while the
    drives are still silent (it waited for the data to come back)."""
    from action_msgs.msg import GoalStatus

    feedback: list[Any] = []
    handle = send(rig, half_sine(30.0, 4.0), feedback)
    wait_for(lambda: bool(feedback) and feedback[-1].desired.time_from_start.sec >= 1, HANG_S, "the goal under way")
    seq = silence_and_mark(rig)
    done = result_of(handle)
    silent = [d.cache.position_seq for d in rig.assembly.driver]
    for node in (1, 2):
        apply_action(rig.sim, {"action": "tpdos", "node": node, "on": True})
    assert seq == silent, (seq, silent)  # no sample after the marker: they were silent
    assert done.status == GoalStatus.STATUS_ABORTED, done.result.error_string
    assert done.result.error_code == FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED
    assert "late" in done.result.error_string and "joint" in done.result.error_string, done.result.error_string


def test_a_jammed_joint_under_a_path_tolerance_ends_the_goal_and_the_joints_stand(rig: Rig) -> None:
    """joint1's shaft blocked 1 s into a goal with a path tolerance of 0.05 rad: the goal ends
    PATH_TOLERANCE_VIOLATED naming joint1, and both joints then stand (50 /joint_states in a row)."""
    from action_msgs.msg import GoalStatus
    from control_msgs.msg import JointTolerance

    goal = half_sine(30.0, 4.0)
    goal.path_tolerance = [JointTolerance(name=n, position=0.05) for n in ("joint1", "joint2")]
    feedback: list[Any] = []
    handle = send(rig, goal, feedback)
    ended = handle.get_result_async()
    wait_for(lambda: ended.done() or (bool(feedback) and feedback[-1].desired.time_from_start.sec >= 1), HANG_S,
             "the goal under way")
    assert not ended.done(), ended.result().result.error_string
    apply_action(rig.sim, {"action": "load", "node": 1, "stall": True})
    done = result_of(handle)
    assert done.status == GoalStatus.STATUS_ABORTED, done.result.error_string
    assert done.result.error_code == FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED
    assert "joint1" in done.result.error_string and "path tolerance" in done.result.error_string

    def still() -> bool:
        last = [(math.degrees(s.position[0]), math.degrees(s.position[1])) for s in rig.states[-50:]
                if len(s.position) == 2]
        return len(last) == 50 and all(max(c) - min(c) < 0.01 for c in zip(*last, strict=True))
    wait_for(still, HANG_S, "both joints still")
    apply_action(rig.sim, {"action": "load", "node": 1, "stall": False})


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "hung"])
def test_the_driver_killed_mid_goal_leaves_the_arm_to_stop_itself(tmp_path: Path, sig: int) -> None:
    """The driver's process as the launch runs it (``python -m nodes.rover_driver``, ``arm:=true``,
    the arm's limited joints its default trajectory group) follows a 30 s goal of an independent
    client; SIGKILL (or SIGSTOP: frozen, not dead) once the joints move: no handler of ours runs.
    Each joint's drive stops itself on its host-heartbeat consumer: an independent listener sees its
    EMCY 0x8130 and nothing of the host after it, the test's own SDO client reads it disabled and still."""
    from can_config import GENERIC_EDS
    from virtual_can import SimDriveSpec

    from .test_host_loss import host_process, signal_the_host_and_see_the_drives_stop, watching, write_config

    drives = [("joint1", 1, "can0", GENERIC_EDS), ("joint2", 2, "can0", GENERIC_EDS)]
    # the drives' consumer time of the host's heartbeat, the driver's of theirs and its staleness
    # bound as in the in-process rigs: a driver starved beside the suite had the drives stop
    # themselves (150 ms) or found their data late (5 SYNCs) and refused the goal; the kill or the
    # freeze outlasts any bound
    arm = ARM | {"host_timeout_ms": IN_PROCESS_HOST_TIMEOUT_MS, "heartbeat_timeout_ms": IN_PROCESS_HEARTBEAT_TIMEOUT_MS}
    with SimService([SimDriveSpec(node, eds, ch, name, 4096) for name, node, ch, eds in drives], port=0) as sim:
        config = write_config(tmp_path / "arm.yaml", sim.port, drives, **arm)
        runner = sim.simulators["can0"]
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("trajectory_client", context=context)
        client = ActionClient(node, FollowJointTrajectory, ACTION)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        client_spin = SpinThread(executor, "test-client")
        try:
            with watching(sim, ["can0"]) as watches, host_process(
                    [sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p", f"config:={config}",
                     "-p", "arm:=true"], tmp_path / "driver.log") as proc:
                assert client.wait_for_server(timeout_sec=HANG_S), f"{ACTION} not served"

                def joints() -> list[tuple[str, float]]:
                    return runner.call(lambda: [(runner.drive(n).state.name, runner.drive(n).omega) for n in (1, 2)])

                wait_for(lambda: all(state == "OPERATION_ENABLED" for state, _ in joints()), HANG_S, "the arm armed")
                # and the driver done arming both (its own word): a drive shows Operation Enabled
                # before the driver's enable ends, and a goal then was refused "not armed"
                log = tmp_path / "driver.log"
                wait_for(lambda: all(f"{name} (node {node}): armed" in log.read_text() for name, node, _, _ in drives),
                         HANG_S, "the driver's 'armed' for both joints", lambda: log.read_text()[-3000:])
                feedback: list[Any] = []
                handle = send(Rig(sim, None, client, []), half_sine(40.0, 30.0), feedback)  # no assembly here
                assert handle.accepted, (tmp_path / "driver.log").read_text()[-3000:]  # why it refused
                wait_for(lambda: bool(feedback) and feedback[-1].desired.time_from_start.sec >= 1
                         and all(state == "OPERATION_ENABLED" and omega != 0.0 for state, omega in joints()),
                         HANG_S, "both joints moving on the goal")
                signal_the_host_and_see_the_drives_stop(proc, sim, watches, drives, sig)
        finally:
            client_spin.stop(5.0)
            client.destroy()  # as the rig's: not left to a failed test's traceback
            node.destroy_node()
            rclpy.shutdown(context=context)
