"""A joint trajectory (control_msgs/FollowJointTrajectory) followed by a group of joints on their
bus's SYNC clock, no rclpy (the node: nodes/actions/follow_trajectory.py).

What lives where: :mod:`motor_driver.follow.group` (:class:`TrajectoryGroup`: the group's thread,
tolerances, cancel, preemption, the stop ramp), :mod:`motor_driver.follow.checks` (the checks before
anything moves), :mod:`motor_driver.follow.goal` (the goal, the standard's codes, a run's outcome and
progress), :mod:`motor_driver.follow.trajectory` (the spline, and the streamed move's set-points: pure
generators).

Owner: each group's own thread (``rovercan-follow-<group>``) runs a goal; a caller's thread hands
it goals and cancels, and reads its progress.
"""

from motor_driver.follow.goal import GoalRun, Outcome, Plan, Progress, Tolerance, TrajectoryCode, TrajectoryGoal
from motor_driver.follow.group import TrajectoryGroup, groups_of

__all__ = ["GoalRun", "Outcome", "Plan", "Progress", "Tolerance", "TrajectoryCode", "TrajectoryGoal",
           "TrajectoryGroup", "groups_of"]
