"""``home_joint`` and ``move_joint``: the long-running drive operations as ROS 2 actions
(rovercan_msgs/Home, rovercan_msgs/MoveJoint): feedback while they run, cancel that stops the
joint. The Trigger services stay for scripts. And each trajectory group's
``<group>/follow_joint_trajectory`` (control_msgs/FollowJointTrajectory, nodes/actions/follow_trajectory.py).

The goals are coroutines on a single-threaded executor of the node's own: between two looks
at the drive a goal awaits a future that a timer thread completes, so the executor serves the
cancel requests and other goals meanwhile. (rclpy's MultiThreadedExecutor was measured
starving the driver's own threads for 0.1-0.5 s: README.) Homing, which blocks in the driver,
runs on a thread of its own and is watched the same way; so do a move's start (its SDO writes, a
mode switch) and its last wait, on the joint's own worker.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import CancelledError, ThreadPoolExecutor
from typing import Any, TypeVar

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from rovercan_msgs.action import Home, MoveJoint

from can_config.errors import CommandRejected, DriveStateError, RovercanError
from can_config.objects import OperationMode
from motor_driver import Drive, MotorDriver
from motor_driver.drive.verdict import Condition
from motor_driver.follow import TrajectoryGroup
from nodes.process import spinning

logger = logging.getLogger(__name__)
T = TypeVar("T")

#: How often feedback is published and a cancel request looked at.
FEEDBACK_PERIOD_S = 0.05
#: How long a canceled move may take to come to rest before the result is sent anyway.
CANCEL_SETTLE_S = 3.0
#: A move is done when the drive says "target reached" within this of the target.
TARGET_WINDOW_DEG = 0.5
#: A move's overall timeout beyond its profile's own time (distance / speed + 2 x speed / acceleration):
#: a joint that does not get there (blocked, too weak, a drive that never says "target reached")
#: is halted and the goal aborted, naming how far it is.
MOVE_MARGIN_S = 5.0


def mode_name(mode: int) -> str:
    """A 0x6061 value's name (its number where CiA 402 has none)."""
    try:
        return OperationMode(mode).name
    except ValueError:
        return str(mode)


def move_timeout_s(distance_deg: float, speed_deg_s: float, accel_deg_s2: float) -> float:
    """How long a profile-position move of ``distance_deg`` may take before it is given up."""
    return MOVE_MARGIN_S + abs(distance_deg) / speed_deg_s + 2.0 * speed_deg_s / accel_deg_s2


class DriverActionsNode(Node):
    def __init__(self, driver: MotorDriver, drives: Mapping[str, Drive] | None = None, *,
                 trajectory_groups: Mapping[str, TrajectoryGroup] | None = None, **kwargs: Any) -> None:
        super().__init__("rovercan_driver_actions", **kwargs)
        self.driver = driver
        self.drives = dict(driver.drives) if drives is None else drives  # the joints it takes goals for
        group = ReentrantCallbackGroup()
        self._home = ActionServer(self, Home, "home_joint", execute_callback=self._execute_home,
                                  goal_callback=self._known_joint, cancel_callback=self._accept_cancel,
                                  callback_group=group)
        self._move = ActionServer(self, MoveJoint, "move_joint", execute_callback=self._execute_move,
                                  goal_callback=self._known_joint, cancel_callback=self._accept_cancel,
                                  callback_group=group)
        # a joint's work on its drive, one at a time per lane: "start" (a goal's SDO writes and mode
        # switch, in arrival order) and "wait" (a goal's last wait, never queued behind another's start)
        self._workers: dict[tuple[str, str], ThreadPoolExecutor] = {}
        # the executor's thread alone: per joint, the goals' arrival count, the goals (by arrival) whose
        # start runs, and the newest whose move was sent (arrival, goal; kept after it ended: an older
        # goal still looking learns it was preempted whenever it looks)
        self._arrived: dict[str, int] = {}
        self._starting: dict[str, set[int]] = {}
        self._moving: dict[str, tuple[int, Any]] = {}
        self._alive = True
        self._trajectories: list[Any] = []
        if trajectory_groups:  # control_msgs is needed only then (a wheels-only rover runs without it)
            from nodes.actions.follow_trajectory import FollowTrajectoryServer

            self._trajectories = [FollowTrajectoryServer(self, g, pause=self._pause, callback_group=group)
                                  for g in trajectory_groups.values()]

    async def _pause(self, period_s: float = FEEDBACK_PERIOD_S) -> None:
        """``period_s`` without holding the executor: a timer thread completes a future."""
        done = Future(executor=self.executor)

        def finish() -> None:
            if not done.done():
                done.set_result(True)
            executor = self.executor
            if executor is not None:  # the goal resumes at the executor's next turn, now (it does not poll)
                spinning.give_work(executor)
        timer = threading.Timer(period_s, finish)
        timer.daemon = True
        timer.start()
        await done

    async def _off_executor(self, joint: str, work: Callable[[], T], lane: str = "start") -> T:
        """``work`` (it waits on the drive) on the joint's own worker of ``lane``, watched between
        pauses: the executor serves cancels and other goals meanwhile; its result, or its error, is
        the goal's."""
        if not self._alive:
            raise CancelledError(f"{joint}: the driver's actions shut down")  # said by the goal
        worker = self._workers.get((joint, lane))
        if worker is None:
            worker = self._workers[(joint, lane)] = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix=f"rovercan-action-{joint}-{lane}")
        future = worker.submit(work)
        while not future.done():
            await self._pause()
        return future.result()

    def destroy_node(self) -> None:
        self._alive = False  # no new work on the joints' workers
        for worker in self._workers.values():
            worker.shutdown(wait=False, cancel_futures=True)
        self._home.destroy()
        self._move.destroy()
        for server in self._trajectories:
            server.destroy()
        super().destroy_node()

    def _known_joint(self, goal: Any) -> GoalResponse:
        if goal.joint not in self.drives:
            logger.warning("goal for unknown joint %r refused; joints: %s", goal.joint, list(self.drives))
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    @staticmethod
    def _accept_cancel(_goal: Any) -> CancelResponse:
        return CancelResponse.ACCEPT

    def _finish(self, goal: Any, result: Any, joint: str, success: bool, message: str) -> Any:
        state = self.drives[joint].snapshot()
        result.success, result.message = success, message
        result.angle, result.state = float(state.angle_deg), state.state.name
        if goal.is_cancel_requested:
            goal.canceled()
        elif success:
            goal.succeed()
        else:
            goal.abort()
        return result

    def _start_move(self, goal: Any, drive: Drive) -> tuple[float, int] | None:
        """A move goal's start, off the executor (SDO writes, a mode switch: it waits on the drive):
        the goal checked whole before anything is written (a refused target or speed changes
        nothing); the move's target and its counts as commanded, or None when cancelled (or shut
        down) before it moved."""
        request = goal.request
        drive.motion.check_position(float(request.target_deg))
        speed = float(request.speed_deg_s)
        if speed != 0.0:  # NaN, negative, beyond the limit or below the drive's resolution: refused
            try:
                drive.motion.check_profile_velocity(speed)
            except CommandRejected as err:
                raise CommandRejected(f"{err} (speed_deg_s 0: the joint's configured profile velocity)") from err
        if not goal.is_cancel_requested and speed:
            drive.motion.set_profile_velocity(speed)
        elif not goal.is_cancel_requested:  # the configured speed again, never the one an earlier goal left
            drive.motion.restore_profile_velocity()
        if not goal.is_cancel_requested:
            drive.power.set_mode(OperationMode.PROFILE_POSITION)  # where it is not: waits on the drive
        if goal.is_cancel_requested or not self._alive:
            return None
        target = drive.move_to(float(request.target_deg))  # the counts it commanded, exactly (not read back:
        return target, drive.cache.scale.deg_to_counts(target)  # another command may have followed already)

    async def _execute_move(self, goal: Any) -> Any:
        """A joint's newest goal whose move was sent is its move (as joint_trajectory_controller's newest
        goal, once accepted, preempts the one running): an older goal of the joint still running ends
        ABORTED, "preempted", at its next look, without halting the joint (the newer's target is its
        own). While a newer goal is starting the older's timeout does not halt (the newer may send its
        move); a newer goal refused or cancelled before it moved preempts nothing."""
        joint = goal.request.joint
        self._arrived[joint] = seq = self._arrived.get(joint, 0) + 1
        self._starting.setdefault(joint, set()).add(seq)
        try:
            return await self._run_move(goal, seq)
        finally:
            self._starting[joint].discard(seq)

    def _moved(self, goal: Any, seq: int) -> None:
        """The goal's move was sent: it is its joint's move unless a newer one's was sent before."""
        joint = goal.request.joint
        self._starting[joint].discard(seq)
        if self._moving.get(joint, (0, None))[0] < seq:
            self._moving[joint] = (seq, goal)

    def _newer_starting(self, joint: str, seq: int) -> bool:
        return any(other > seq for other in self._starting.get(joint, ()))

    def _taken(self, drive: Drive, mode: int, own: int, seq: int) -> str | None:
        """Why the move is over because another command took its joint, else None: the drive left
        profile position (a trajectory, a stream), a halt of the joint stands (``<joint>/halt``: the
        goal ran on to its timeout and blamed the joint), or the newest target commanded is not the
        move's (a position command, /joint_commands; a newer move_joint goal starting is waited for:
        it says "preempted")."""
        joint = drive.name
        if mode != OperationMode.PROFILE_POSITION:
            return (f"{joint}: the move is over: the joint left profile position (mode {mode_name(mode)}): another"
                    " command took it")
        if drive.channel.halted:  # not the move's own halt: it ends the goal where it halts
            return (f"{joint}: the move is over: the joint was halted (a halt command, {drive.config.ros_prefix}/halt)"
                    f" at {drive.snapshot().angle_deg:.2f} deg")
        newest = drive.channel.newest_move_counts
        if newest != own and newest is not None and not self._newer_starting(joint, seq):
            return (f"{joint}: the move is over: another command set its target"
                    f" ({drive.cache.scale.counts_to_deg(newest):.2f} deg)")
        return None

    def _preempted(self, goal: Any) -> Any | None:
        """The finished result of a move a newer goal of its joint took over, else None."""
        joint = goal.request.joint
        if self._moving.get(joint, (0, goal))[1] is goal:
            return None
        return self._finish(goal, MoveJoint.Result(), joint, False,
                            f"{joint}: preempted by a newer move_joint goal; the joint goes to its target")

    async def _run_move(self, goal: Any, seq: int) -> Any:
        request = goal.request
        drive = self.drives[request.joint]
        feedback = MoveJoint.Feedback()
        try:
            started = await self._off_executor(request.joint, lambda: self._start_move(goal, drive))
            if started is None:
                return self._finish(goal, MoveJoint.Result(), request.joint, False, "canceled before it moved"
                                    if goal.is_cancel_requested else "the driver's actions shut down before it moved")
            self._moved(goal, seq)
            if (preempted := self._preempted(goal)) is not None:  # a newer goal's move went out after this one's
                return preempted
            target, own = started
            cfg = drive.config
            speed = float(request.speed_deg_s) if request.speed_deg_s > 0 else cfg.profile_velocity_deg_s
            timeout_s = move_timeout_s(target - drive.snapshot().angle_deg, speed, cfg.profile_acceleration_deg_s2)
            deadline = time.monotonic() + timeout_s
            while True:
                await self._pause()
                if (preempted := self._preempted(goal)) is not None:
                    return preempted
                state = drive.snapshot()
                verdict = state.verdict  # the one judgement of the drive: nothing else is read
                if not verdict.usable and verdict.condition is not Condition.LATE:
                    # faulted, stopped (a deactivate, /disarm, its own host watch), held or lost: the
                    # move cannot end at its target (late data only delays the feedback)
                    raise DriveStateError(f"{request.joint}: the move ended: {verdict.text()}", node_id=drive.node_id)
                if (taken := self._taken(drive, state.mode, own, seq)) is not None:  # another command's now
                    return self._finish(goal, MoveJoint.Result(), request.joint, False, taken)
                if time.monotonic() > deadline and not self._newer_starting(request.joint, seq):
                    drive.halt()
                    raise DriveStateError(f"{request.joint}: not at {target:.2f} deg after {timeout_s:.1f} s (the"
                                          f" move's time and {MOVE_MARGIN_S:g} s); halted at {state.angle_deg:.2f} deg,"
                                          f" {abs(target - state.angle_deg):.2f} deg short ({verdict.text()}). Is the"
                                          " joint blocked or its speed too low?", node_id=drive.node_id)
                if state.target_reached and abs(target - state.angle_deg) < TARGET_WINDOW_DEG:
                    # the handshake's last word, and a fresh position
                    await self._off_executor(request.joint, lambda: drive.wait_target_reached(1.0), lane="wait")
                    break
                feedback.angle, feedback.remaining_deg = float(state.angle_deg), float(target - state.angle_deg)
                goal.publish_feedback(feedback)
                if goal.is_cancel_requested and not self._newer_starting(request.joint, seq):
                    # (while a newer goal of the joint starts, its move may be out already: a halt now
                    # would stop it, and it would end "halted"; the newer preempts this one, or fails
                    # to start and this cancel halts at the next look)
                    drive.halt()  # the profile deceleration; the drive stays enabled
                    settle = time.monotonic() + CANCEL_SETTLE_S
                    while abs(drive.snapshot().velocity_deg_s) > 0.5 and time.monotonic() < settle:
                        await self._pause()
                    return self._finish(goal, MoveJoint.Result(), request.joint, False,
                                        f"canceled: halted at {drive.snapshot().angle_deg:.2f} deg")
        except RovercanError as err:
            return self._finish(goal, MoveJoint.Result(), request.joint, False, str(err))
        except CancelledError:  # its work was dropped: the node is being destroyed
            return self._finish(goal, MoveJoint.Result(), request.joint, False, "the driver's actions shut down")
        except Exception as err:  # a fault of this driver's: logged with its trace, the goal aborted
            logger.exception("%s: move_joint failed unexpectedly", request.joint)
            return self._finish(goal, MoveJoint.Result(), request.joint, False,
                                f"the move failed unexpectedly ({type(err).__name__}: {err}); see the log")
        return self._finish(goal, MoveJoint.Result(), request.joint, True, f"at {target:.2f} deg")

    async def _execute_home(self, goal: Any) -> Any:
        joint = goal.request.joint
        drive = self.drives[joint]
        failure: list[str] = []

        def run() -> None:
            try:
                drive.home()
            except RovercanError as err:
                failure.append(str(err))
            except Exception as err:  # a fault of this driver's: never "homed"
                logger.exception("%s: homing failed unexpectedly", joint)
                failure.append(f"homing failed unexpectedly ({type(err).__name__}: {err}); the joint is not referenced")

        homing = threading.Thread(target=run, name=f"rovercan-home-{joint}", daemon=True)
        homing.start()
        feedback = Home.Feedback()
        stopped = False
        stop_failed = ""  # the cancel's quick stop, when it failed: the result says that, not "quick-stopped"
        while homing.is_alive():
            state = drive.snapshot()
            feedback.angle, feedback.state = float(state.angle_deg), state.state.name
            goal.publish_feedback(feedback)
            if goal.is_cancel_requested and not stopped:
                stopped = True
                try:
                    drive.quick_stop()  # preempts the homing operation, which then gives up
                except RovercanError as err:
                    stop_failed = (f"canceled, but its quick stop failed: {err}; stop the joint with"
                                   f" {drive.config.ros_prefix}/quick_stop or /disarm")
                    logger.error("%s: home_joint %s", joint, stop_failed)
            await self._pause()
        if stopped:
            return self._finish(goal, Home.Result(), joint, False, stop_failed or "canceled: quick-stopped while homing")
        if failure:
            return self._finish(goal, Home.Result(), joint, False, failure[0])
        return self._finish(goal, Home.Result(), joint, True, "homed")
