"""The values of a joint trajectory's run (:mod:`motor_driver.follow`): the goal in degrees, the
standard's result codes, a run's outcome and progress. :class:`GoalRun` is written by its group's
thread only (its outcome once, its progress replaced whole); any thread reads it."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum

from can_config.errors import TrajectoryRejected
from motor_driver.follow.trajectory import Knot


class TrajectoryCode(IntEnum):
    """control_msgs/action/FollowJointTrajectory's result codes (the standard's numbers)."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    OLD_HEADER_TIMESTAMP = -3
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5


@dataclass(frozen=True)
class Tolerance:
    """A joint's tolerance as the standard (control_msgs/JointTolerance) and joint_trajectory_controller
    read it: 0 the group's default, -1 none, a positive value the bound; any other negative is refused."""

    position_deg: float = 0.0
    velocity_deg_s: float = 0.0


@dataclass(frozen=True)
class TrajectoryGoal:
    """A trajectory in degrees: ``positions_deg[k][j]`` of ``joints[j]`` at ``times_s[k]``; a point's
    velocities or accelerations are empty or one per joint."""

    joints: tuple[str, ...]
    times_s: tuple[float, ...]
    positions_deg: tuple[tuple[float, ...], ...]
    velocities_deg_s: tuple[tuple[float, ...], ...] = ()
    accelerations_deg_s2: tuple[tuple[float, ...], ...] = ()
    path_tolerance: Mapping[str, Tolerance] = field(default_factory=dict)
    goal_tolerance: Mapping[str, Tolerance] = field(default_factory=dict)
    goal_time_tolerance_s: float = 0.0  # 0: the group's
    start_delay_s: float = 0.0  # from its acceptance (a header stamp in the future)


#: A goal preempted by a newer one ends ABORTED with INVALID_GOAL and joint_trajectory_controller's words
#: (ros2_controllers jazzy >= 4.41.0, preempt_active_goal; before: CANCELED, "cancelled due to").
PREEMPTED = "Current goal preempted by new incoming action."


@dataclass(frozen=True)
class Outcome:
    """How a goal ended: ``canceled`` for a cancel (the action's CANCELED); a preemption is not one."""

    code: TrajectoryCode
    message: str
    canceled: bool = False


@dataclass(frozen=True)
class Progress:
    """One tick of a running goal, in degrees: what was sent, what was measured."""

    time_s: float
    joints: tuple[str, ...]
    desired: tuple[tuple[float, float, float], ...]  # (position, velocity, acceleration) per joint
    actual: tuple[tuple[float, float], ...]  # (position, velocity) per joint


@dataclass(frozen=True)
class Plan:
    """A checked goal: its spline's knots without the start state (added by the group's thread)."""

    goal: TrajectoryGoal
    times_s: tuple[float, ...]  # > 0
    knots: tuple[tuple[Knot, ...], ...]
    path: tuple[Tolerance, ...]  # resolved per joint: -1 none
    final: tuple[Tolerance, ...]
    goal_time_s: float  # 0: no bound


class GoalRun:
    """A goal handed to a group: :attr:`done` is set when :attr:`outcome` is; :attr:`progress` is the
    last tick's. Written by the group's thread only. ``start_at``: the plan's time zero on the
    monotonic clock (its acceptance, or its header stamp); ``wake``: wakes the group's thread."""

    def __init__(self, plan: Plan, start_at: float = 0.0, wake: Callable[[], None] | None = None) -> None:
        self.plan = plan
        self.start_at = start_at
        self.done = threading.Event()
        self.outcome: Outcome | None = None
        self.progress: Progress | None = None
        self.cancel_requested = False  # set by cancel(), read by the group's thread
        self._wake = wake

    def cancel(self) -> None:
        """Stop the goal: the group's thread, woken now whether or not a sample comes, ends it
        CANCELED at once; its joints ramp down at the stop deceleration and hold."""
        self.cancel_requested = True
        if self._wake is not None:
            self._wake()

    def report(self, progress: Progress) -> None:
        self.progress = progress

    def finish(self, outcome: Outcome) -> None:
        if self.outcome is None:
            self.outcome = outcome
            self.done.set()


def refuse(code: TrajectoryCode, message: str) -> TrajectoryRejected:
    return TrajectoryRejected(message, code=int(code))


