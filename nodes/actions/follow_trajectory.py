"""``<group>/follow_joint_trajectory`` (control_msgs/action/FollowJointTrajectory): a trajectory
group of the config (:mod:`motor_driver.follow`) as the action MoveIt's
moveit_simple_controller_manager (``type: FollowJointTrajectory``) and any client of the standard
type send goals to. Thin: a goal becomes a :class:`TrajectoryGoal` in degrees, the group checks and
runs it on its own thread at the bus's SYNC; this side publishes feedback at the group's
``feedback_rate_hz``, passes a cancel on, and turns the run's outcome into the result's
``error_code`` and ``error_string``.

What can be judged at goal time is judged in the goal callback, as joint_trajectory_controller
does, and a goal failing it is REJECTED, the reason logged (WARNING): joints unknown, repeated, of
another group or not all of the group's (unless ``allow_partial_joints_goal``), points of the wrong
size, not finite or not strictly increasing in time, beyond a joint's limits, a last point with a
velocity (unless ``allow_nonzero_velocity_at_trajectory_end``), a point with effort, a tolerance negative
other than -1, a header stamp whose trajectory is over, a joint not usable or its motion held (the
lifecycle node inactive). Each joint's switch to a streamed mode (SDO answers) happens there too,
awaited off the executor: before acceptance, so that it never shifts the plan. Acceptance is the
plan's time zero (header stamp zero), or the stamp: the group samples the plan at each SYNC's time
from it (motor_driver/follow/group.py).

A newer goal preempts: it is accepted and the older one ends ABORTED with INVALID_GOAL and "Current
goal preempted by new incoming action." (the controller's, jazzy >= 4.41.0); the new plan is joined from
the current set-point. A cancel is passed to the group in the cancel callback and wakes its thread:
the goal ends CANCELED within a SYNC period whether or not samples come, its joints then ramp down
and hold. What goes wrong later ends ABORTED with the standard's code and a message naming the joint.

Each second the server publishes its group's background counts on /diagnostics, as the status
``rovercan: follow <group>``: the group thread's unexpected errors (each ended a goal in a stop), the
samples it took too late (a SYNC let go) and its waits that ended without a sample; WARN once an
error was counted, ERROR when the group's thread has ended.

The goals are coroutines on the actions' executor (nodes/actions/driver_actions.py): between two looks at the run a
goal awaits the node's pause, so the executor serves cancels and other goals meanwhile; a goal's
switch to streaming runs on the server's start worker (one a server: in the order goals came).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import CancelledError, ThreadPoolExecutor
from typing import Any

from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import GoalEvent
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from trajectory_msgs.msg import JointTrajectoryPoint

from can_config.errors import RovercanError, TrajectoryRejected
from motor_driver.follow import GoalRun, Plan, Progress, Tolerance, TrajectoryCode, TrajectoryGoal, TrajectoryGroup
from motor_driver.protocol.units import DEG_PER_RAD
from nodes.joints.messages import stamp_header
from nodes.process.qos import DIAGNOSTICS_QOS, NO_PUB_EVENTS

Result = FollowJointTrajectory.Result
logger = logging.getLogger(__name__)


def _seconds(duration: Any) -> float:
    return float(duration.sec) + float(duration.nanosec) * 1e-9


def _degrees(values: Any) -> tuple[float, ...]:
    return tuple(float(v) * DEG_PER_RAD for v in values)


def _tolerances(entries: Any) -> dict[str, Tolerance]:
    """JointTolerance[] in degrees; the special values 0 (the default) and -1 (none) kept as they are,
    any other negative refused (joint_trajectory_controller's meanings); an acceleration bound refused
    (no acceleration is measured here: a goal is not run without a tolerance it asked for)."""
    def deg(name: str, what: str, value: float) -> float:
        if value in (0.0, -1.0):
            return float(value)
        if not (math.isfinite(value) and value > 0.0):
            raise TrajectoryRejected(f"{name}: {what} tolerance {value!r}: allowed -1 (none), 0 (the default) or a"
                                     " bound > 0; nothing moved", code=int(TrajectoryCode.INVALID_GOAL))
        return float(value) * DEG_PER_RAD
    for t in entries:
        if t.acceleration not in (0.0, -1.0):
            raise TrajectoryRejected(f"{t.name}: acceleration tolerance {t.acceleration!r}: this driver measures no joint"
                                     " acceleration and cannot hold a goal to one; send 0 (none given) or -1 (none)."
                                     " Nothing moved", code=int(TrajectoryCode.INVALID_GOAL))
    return {t.name: Tolerance(deg(t.name, "position", t.position), deg(t.name, "velocity", t.velocity))
            for t in entries}


def goal_from_message(request: Any, now_s: float) -> TrajectoryGoal:
    """A FollowJointTrajectory goal in the core's terms (degrees, seconds). ``now_s``: the node
    clock's time, against which a header stamp is judged: 0 starts now, a later stamp delays the
    start, one whose whole trajectory is past is refused (OLD_HEADER_TIMESTAMP)."""
    trajectory = request.trajectory
    if request.multi_dof_trajectory.joint_names:
        raise TrajectoryRejected(f"multi-DOF joints {list(request.multi_dof_trajectory.joint_names)}: this driver moves"
                                 " single-DOF joints only; nothing moved", code=int(TrajectoryCode.INVALID_JOINTS))
    points = trajectory.points
    for k, point in enumerate(points):
        if len(point.effort):
            raise TrajectoryRejected(f"point {k} carries effort {list(point.effort)}: this driver commands positions"
                                     " only (joint_trajectory_controller takes effort with an effort command interface"
                                     " only); send no effort. Nothing moved", code=int(TrajectoryCode.INVALID_GOAL))
    times = tuple(_seconds(p.time_from_start) for p in points)
    stamp = _seconds(trajectory.header.stamp)
    if stamp > 0.0 and times and stamp - now_s + times[-1] < 0.0:
        raise TrajectoryRejected(f"the trajectory's header stamp {stamp:.3f} s and its {times[-1]:.3f} s end before"
                                 f" now ({now_s:.3f} s); stamp 0 starts it on arrival. Nothing moved",
                                 code=int(TrajectoryCode.OLD_HEADER_TIMESTAMP))
    return TrajectoryGoal(
        joints=tuple(trajectory.joint_names), times_s=times,
        positions_deg=tuple(_degrees(p.positions) for p in points),
        velocities_deg_s=tuple(_degrees(p.velocities) for p in points),
        accelerations_deg_s2=tuple(_degrees(p.accelerations) for p in points),
        path_tolerance=_tolerances(request.path_tolerance), goal_tolerance=_tolerances(request.goal_tolerance),
        goal_time_tolerance_s=_seconds(request.goal_time_tolerance), start_delay_s=start_delay(stamp, now_s))


def start_delay(stamp_s: float, now_s: float) -> float:
    """How long after ``now_s`` a goal with header stamp ``stamp_s`` (ROS time, s) starts: 0 for
    stamp 0 (on arrival) and for a stamp in the past (another host's clock behind this one's: run from
    acceptance; joint_trajectory_controller samples it at now, a jump into the part that has passed,
    and a plan joined there would be caught up at the joints' limit from rest: docs/ros.md)."""
    return max(stamp_s - now_s, 0.0) if stamp_s > 0.0 else 0.0


def fill_feedback(feedback: Any, progress: Progress) -> Any:
    """The feedback's desired, actual and error points (rad, rad/s) from one tick of the run."""
    rad = math.radians
    seconds = int(progress.time_s)
    stamp = Duration(sec=seconds, nanosec=int((progress.time_s - seconds) * 1e9))
    pairs = list(zip(progress.desired, progress.actual, strict=True))
    feedback.joint_names = list(progress.joints)
    feedback.desired = JointTrajectoryPoint(positions=[rad(p) for p, _, _ in progress.desired],
                                            velocities=[rad(v) for _, v, _ in progress.desired],
                                            accelerations=[rad(a) for _, _, a in progress.desired], time_from_start=stamp)
    feedback.actual = JointTrajectoryPoint(positions=[rad(p) for p, _ in progress.actual],
                                           velocities=[rad(v) for _, v in progress.actual], time_from_start=stamp)
    feedback.error = JointTrajectoryPoint(positions=[rad(d[0] - a[0]) for d, a in pairs],
                                          velocities=[rad(d[1] - a[1]) for d, a in pairs], time_from_start=stamp)
    return feedback


#: How often a goal's switch to streaming is looked at while the goal callback awaits it.
START_POLL_S = 0.005
#: How often the group's counts go to /diagnostics.
DIAGNOSTICS_PERIOD_S = 1.0


def follow_status(group: TrajectoryGroup) -> DiagnosticStatus:
    """The group's /diagnostics status: its thread's background counts, and its level."""
    counts = group.counters()
    if not group.alive:
        level, message = DiagnosticStatus.ERROR, "its thread has ended (see the log): goals are refused; restart the driver"
    elif counts["errors"]:
        level, message = DiagnosticStatus.WARN, f"{counts['errors']} unexpected error(s), each ended a goal (see the log)"
    else:
        level, message = DiagnosticStatus.OK, "following" if group.busy else "idle"
    status = DiagnosticStatus(level=level, name=f"rovercan: follow {group.name}", message=message,
                              hardware_id=group.name)
    status.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
    return status


class FollowTrajectoryServer:
    """One group's action server on ``node``. ``pause(period_s)``: an awaitable that holds no executor thread."""

    def __init__(self, node: Node, group: TrajectoryGroup, *, pause: Callable[[float], Awaitable[None]],
                 callback_group: CallbackGroup | None = None) -> None:
        self._node, self._group = node, group
        self._pause = pause
        self._period_s = 1.0 / group.config.feedback_rate_hz
        self._alive = True
        # goals' switches to streaming, one at a time in the order they came
        self._starter = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"rovercan-follow-start-{group.name}")
        self._plans: dict[int, tuple[Any, Plan]] = {}  # id(goal request) -> (it, its plan): goal callback -> accepted
        self._runs: dict[int, GoalRun | str] = {}  # id(goal handle) -> its run, or why it could not start
        self._arrived = 0  # goals that came; those still judged, by arrival: accepted in that order
        self._judging: set[int] = set()
        self._server = ActionServer(node, FollowJointTrajectory, f"{group.name}/follow_joint_trajectory",
                                    execute_callback=self._execute, goal_callback=self._judge,
                                    handle_accepted_callback=self._accepted, cancel_callback=self._cancel,
                                    callback_group=callback_group)
        self._diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS,
                                                  event_callbacks=NO_PUB_EVENTS)
        self._diag_timer = node.create_timer(DIAGNOSTICS_PERIOD_S, self.publish_diagnostics,
                                             callback_group=callback_group)

    def publish_diagnostics(self) -> None:
        array = DiagnosticArray()
        stamp_header(array.header, time.time())
        array.status = [follow_status(self._group)]
        self._diagnostics.publish(array)

    def destroy(self) -> None:
        self._alive = False  # a goal under judgement is rejected
        self._node.destroy_timer(self._diag_timer)
        self._node.destroy_publisher(self._diagnostics)
        self._starter.shutdown(wait=False, cancel_futures=True)
        self._server.destroy()

    async def _judge(self, request: Any) -> GoalResponse:
        """The goal callback: what can be judged at goal time, and each joint's switch to streaming;
        accepted after every goal that came before it was answered (a newer goal preempts an older
        one, never the other way round)."""
        self._arrived += 1
        mine = self._arrived
        self._judging.add(mine)
        try:
            response = await self._checked(request)
            while response == GoalResponse.ACCEPT and any(other < mine for other in self._judging):
                await self._pause(START_POLL_S)
            return response
        finally:
            self._judging.discard(mine)

    async def _checked(self, request: Any) -> GoalResponse:
        name = self._group.name
        try:
            if not self._alive:
                raise CancelledError
            goal = goal_from_message(request, self._node.get_clock().now().nanoseconds * 1e-9)
            plan = self._group.plan(goal)
            switching = self._starter.submit(self._group.prepare, goal.joints)  # waits on the drives
            while not switching.done():  # the executor serves cancels and other goals meanwhile
                await self._pause(START_POLL_S)
            switching.result()
        except RovercanError as err:
            self._node.get_logger().warning(f"{name}: goal rejected: {err}")
            return GoalResponse.REJECT
        except CancelledError:
            self._node.get_logger().warning(f"{name}: goal rejected: the driver's actions shut down")
            return GoalResponse.REJECT
        except Exception as err:  # a fault of this driver's: logged with its trace, the goal rejected
            logger.exception("%s: judging a goal failed unexpectedly", name)
            self._node.get_logger().warning(f"{name}: goal rejected: unexpected {type(err).__name__}: {err}")
            return GoalResponse.REJECT
        self._plans[id(request)] = (request, plan)
        return GoalResponse.ACCEPT

    def _accepted(self, goal_handle: Any) -> None:
        """Acceptance: the plan's time zero (or its stamp's); the group takes it at once, preempting."""
        accepted_at = time.monotonic()
        request = goal_handle.request
        _, plan = self._plans.pop(id(request), (None, None))
        delay = start_delay(_seconds(request.trajectory.header.stamp), self._node.get_clock().now().nanoseconds * 1e-9)
        try:
            if plan is None:
                raise RuntimeError("accepted without a plan")
            self._runs[id(goal_handle)] = self._group.start(plan, accepted_at + delay)
        except RovercanError as err:
            self._runs[id(goal_handle)] = str(err)
        except Exception as err:  # a fault of this driver's: logged with its trace, the goal aborted
            logger.exception("%s: a goal's start failed unexpectedly", self._group.name)
            self._runs[id(goal_handle)] = f"the goal's start failed unexpectedly ({type(err).__name__}: {err})"
        goal_handle.execute()

    def _cancel(self, goal_handle: Any) -> CancelResponse:
        """Passed on at once: the group's thread is woken and ends the goal within a SYNC period."""
        run = self._runs.get(id(goal_handle))
        if isinstance(run, GoalRun):
            run.cancel()
        return CancelResponse.ACCEPT

    async def _execute(self, goal_handle: Any) -> Any:
        result = Result()
        run = self._runs.get(id(goal_handle), "the goal was never started")
        try:
            if isinstance(run, str):
                result.error_code, result.error_string = Result.INVALID_GOAL, run
                goal_handle.abort()
                return result
            try:
                await self._follow(goal_handle, run)
            except Exception as err:  # a fault of this server's: the motion is not left running under it
                run.cancel()  # the group's thread ramps the joints down within a SYNC period
                logger.exception("%s: following a goal failed unexpectedly", self._group.name)
                result.error_code = Result.INVALID_GOAL
                result.error_string = (f"following the goal failed unexpectedly ({type(err).__name__}: {err});"
                                       " its motion was cancelled (ramped down); see the driver's log")
                goal_handle.abort()
                return result
            outcome = run.outcome
            assert outcome is not None  # done is set with it
            result.error_code, result.error_string = int(outcome.code), outcome.message
            if outcome.canceled and not goal_handle.is_cancel_requested:  # a cancel ended it before rclpy's state did
                goal_handle._update_state(GoalEvent.CANCEL_GOAL)  # rclpy's one way there (its cancel service's)
            # the group's outcome decides: a cancel that came as the goal ended on its own (at the goal, or
            # aborted) does not make it CANCELED, as the controller cancels only its goal still active
            if outcome.canceled:
                goal_handle.canceled()
            elif outcome.code == TrajectoryCode.SUCCESSFUL:
                goal_handle.succeed()
            else:
                goal_handle.abort()
            return result
        finally:
            self._runs.pop(id(goal_handle), None)

    async def _follow(self, goal_handle: Any, run: GoalRun) -> None:
        """Until the run ends: feedback at the group's rate, a cancel passed on (the cancel callback's too)."""
        feedback = FollowJointTrajectory.Feedback()
        while not run.done.is_set():
            if goal_handle.is_cancel_requested and not run.cancel_requested:
                run.cancel()
            await self._pause(self._period_s)
            if (progress := run.progress) is not None and not run.done.is_set():
                feedback.header.stamp = self._node.get_clock().now().to_msg()
                goal_handle.publish_feedback(fill_feedback(feedback, progress))


__all__ = ["FollowTrajectoryServer", "fill_feedback", "goal_from_message"]
