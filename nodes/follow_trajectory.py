"""``<group>/follow_joint_trajectory`` (control_msgs/action/FollowJointTrajectory): a trajectory
group of the config (:mod:`motor_driver.follow`) as the action MoveIt's
moveit_simple_controller_manager (``type: FollowJointTrajectory``) and any client of the standard
type send goals to. Thin: a goal becomes a :class:`TrajectoryGoal` in degrees, the group checks and
runs it on its own thread at the bus's SYNC; this side publishes feedback at the group's
``feedback_rate_hz``, passes a cancel on, and turns the run's outcome into the result's
``error_code`` and ``error_string``.

Every goal is accepted, then checked: a refusal is an aborted goal whose result carries the standard's
code (INVALID_JOINTS, INVALID_GOAL, OLD_HEADER_TIMESTAMP) and a message naming the joint and the limit;
nothing moved. Whatever holds the drives' motion (a stop, the lifecycle node inactive) holds it in
each drive's command channel, where every set-point and mode switch of a goal goes: such a goal ends
INVALID_GOAL with the channel's reason, as every other motion entry is refused. A cancelled goal ends CANCELED once its joints stand; a goal
preempted by a newer one ends ABORTED with INVALID_GOAL (as joint_trajectory_controller does).

The goals are coroutines on the actions' executor (nodes/actions.py): between two looks at the run a
goal awaits the node's pause, so the executor serves cancels and other goals meanwhile. A goal's start
(its checks, and each joint's switch to a streamed mode, which waits on the drive's SDO answers) runs
on the server's start worker, watched the same way: a drive slow to answer holds its goal, never the
executor. One worker a server, so goals start in the order they came (a newer goal preempts an
older one, never the other way round); a goal cancelled while it starts is never handed over and
leaves the goal running alone; a server destroyed drops the starts not begun.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Awaitable, Callable
from concurrent.futures import CancelledError, ThreadPoolExecutor
from typing import Any

from builtin_interfaces.msg import Duration
from control_msgs.action import FollowJointTrajectory
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from trajectory_msgs.msg import JointTrajectoryPoint

from can_config.errors import RovercanError, TrajectoryRejected
from motor_driver.follow import Progress, Tolerance, TrajectoryCode, TrajectoryGoal, TrajectoryGroup
from motor_driver.protocol.units import DEG_PER_RAD

Result = FollowJointTrajectory.Result
logger = logging.getLogger(__name__)


def _seconds(duration: Any) -> float:
    return float(duration.sec) + float(duration.nanosec) * 1e-9


def _degrees(values: Any) -> tuple[float, ...]:
    return tuple(float(v) * DEG_PER_RAD for v in values)


def _tolerances(entries: Any) -> dict[str, Tolerance]:
    """JointTolerance[] in degrees; the special values 0 (the default) and -1 (none) kept as they are."""
    def deg(value: float) -> float:
        return value if value in (0.0, -1.0) else float(value) * DEG_PER_RAD
    return {t.name: Tolerance(deg(t.position), deg(t.velocity)) for t in entries}


def goal_from_message(request: Any, now_s: float) -> TrajectoryGoal:
    """A FollowJointTrajectory goal in the core's terms (degrees, seconds). ``now_s``: the node
    clock's time, against which a header stamp is judged: 0 starts now, a later stamp delays the
    start, one whose whole trajectory is past is refused (OLD_HEADER_TIMESTAMP)."""
    trajectory = request.trajectory
    if request.multi_dof_trajectory.joint_names:
        raise TrajectoryRejected(f"multi-DOF joints {list(request.multi_dof_trajectory.joint_names)}: this driver moves"
                                 " single-DOF joints only; nothing moved", code=int(TrajectoryCode.INVALID_JOINTS))
    points = trajectory.points
    times = tuple(_seconds(p.time_from_start) for p in points)
    stamp = _seconds(trajectory.header.stamp)
    delay = 0.0
    if stamp > 0.0:
        delay = stamp - now_s
        if times and delay + times[-1] < 0.0:
            raise TrajectoryRejected(f"the trajectory's header stamp {stamp:.3f} s and its {times[-1]:.3f} s end before"
                                     f" now ({now_s:.3f} s); stamp 0 starts it on arrival. Nothing moved",
                                     code=int(TrajectoryCode.OLD_HEADER_TIMESTAMP))
    return TrajectoryGoal(
        joints=tuple(trajectory.joint_names), times_s=times,
        positions_deg=tuple(_degrees(p.positions) for p in points),
        velocities_deg_s=tuple(_degrees(p.velocities) for p in points),
        accelerations_deg_s2=tuple(_degrees(p.accelerations) for p in points),
        path_tolerance=_tolerances(request.path_tolerance), goal_tolerance=_tolerances(request.goal_tolerance),
        goal_time_tolerance_s=_seconds(request.goal_time_tolerance), start_delay_s=max(delay, 0.0))


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


class FollowTrajectoryServer:
    """One group's action server on ``node``. ``pause(period_s)``: an awaitable that holds no executor thread."""

    def __init__(self, node: Node, group: TrajectoryGroup, *, pause: Callable[[float], Awaitable[None]],
                 callback_group: CallbackGroup | None = None) -> None:
        self._node, self._group = node, group
        self._pause = pause
        self._period_s = 1.0 / group.config.feedback_rate_hz
        self._alive = True
        # goals' starts, one at a time in the order they came; each start's Future is read by its goal
        self._starter = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"rovercan-follow-start-{group.name}")
        self._server = ActionServer(node, FollowJointTrajectory, f"{group.name}/follow_joint_trajectory",
                                    execute_callback=self._execute, goal_callback=lambda _goal: GoalResponse.ACCEPT,
                                    cancel_callback=lambda _goal: CancelResponse.ACCEPT, callback_group=callback_group)

    def destroy(self) -> None:
        self._alive = False  # a start under way hands nothing over
        self._starter.shutdown(wait=False, cancel_futures=True)
        self._server.destroy()

    async def _execute(self, goal_handle: Any) -> Any:
        result = Result()
        try:
            now_s = self._node.get_clock().now().nanoseconds * 1e-9
            goal = goal_from_message(goal_handle.request, now_s)
            if not self._alive:
                raise CancelledError
            starting = self._starter.submit(self._group.follow, goal,
                                            lambda: goal_handle.is_cancel_requested or not self._alive)
            while not starting.done():  # the executor serves cancels and other goals meanwhile
                await self._pause(self._period_s)
            run = starting.result()
        except RovercanError as err:
            result.error_code = err.code if isinstance(err, TrajectoryRejected) else Result.INVALID_GOAL
            result.error_string = str(err)
            self._node.get_logger().warning(f"{self._group.name}: goal refused: {err}")
            goal_handle.abort()
            return result
        except CancelledError:  # its start was dropped: the server is being destroyed
            result.error_code = Result.INVALID_GOAL
            result.error_string = f"{self._group.name}: the driver's actions shut down before the goal started"
            goal_handle.abort()
            return result
        except Exception as err:  # a fault of this driver's: logged with its trace, the goal aborted
            logger.exception("%s: a goal's start failed unexpectedly", self._group.name)
            result.error_code = Result.INVALID_GOAL
            result.error_string = f"the goal's start failed unexpectedly ({type(err).__name__}: {err}); see the log"
            goal_handle.abort()
            return result
        feedback = FollowJointTrajectory.Feedback()
        cancelled = False
        while not run.done.is_set():
            if goal_handle.is_cancel_requested and not cancelled:  # before the first pause too
                cancelled = True
                run.cancel()
            await self._pause(self._period_s)
            if (progress := run.progress) is not None and not run.done.is_set():
                feedback.header.stamp = self._node.get_clock().now().to_msg()
                goal_handle.publish_feedback(fill_feedback(feedback, progress))
        outcome = run.outcome
        assert outcome is not None  # done is set with it
        result.error_code, result.error_string = int(outcome.code), outcome.message
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif outcome.code == TrajectoryCode.SUCCESSFUL and not outcome.canceled:  # not dropped at shutdown
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result


__all__ = ["FollowTrajectoryServer", "fill_feedback", "goal_from_message"]
