"""A joint trajectory's checks before anything moves (:mod:`motor_driver.follow`): each refusal a
:class:`TrajectoryRejected` with the standard's code and a message naming the joint and the limit.
No state of its own beyond the group's config and drives; called on the caller's thread."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

from can_config.errors import CommandRejected
from can_config.model import TrajectoryGroupConfig
from motor_driver.drive import Drive
from motor_driver.drive.constants import ENABLED_CW_MASK
from motor_driver.follow.goal import Plan, Tolerance, TrajectoryCode, TrajectoryGoal, refuse
from motor_driver.follow.trajectory import Knot, Spline, derivative, excursion

#: Slack on the velocity limit between the points (rounding of a spline that touches it).
VELOCITY_SLACK = 1e-6
#: Slack on the position limits between the points, deg: a point at a limit is allowed (its own
#: check is exact), and its polynomial's value there, through the hull's arithmetic, may round an
#: ulp past it (a count is 0.002 deg on the shipped arm).
POSITION_SLACK_DEG = 1e-6
#: A last point's velocity above this is not zero: joint_trajectory_controller's
#: ``std::numeric_limits<float>::epsilon()`` (2**-23 rad/s), in deg/s.
END_VELOCITY_EPSILON_DEG_S = math.degrees(2.0**-23)


class GoalChecks:
    """The checks of one trajectory group's goals."""

    def __init__(self, config: TrajectoryGroupConfig, drives: Mapping[str, Drive]) -> None:
        self.config, self.name, self.drives = config, config.name, drives

    def plan(self, goal: TrajectoryGoal, reference: Callable[[Sequence[str]], tuple[Knot, ...]]) -> Plan:
        """``goal`` checked against the group, the joints' limits and their drives (nothing sent);
        ``reference(joints)``: where the group's set-points of those joints are now."""
        self._check_joints(goal.joints)
        times, knots = self._check_points(goal)
        path, final, goal_time = self._tolerances(goal)
        drives = [self.drives[j] for j in goal.joints]
        for drive in drives:
            self._check_armed(drive)
        start = reference(goal.joints)
        if goal.times_s[0] == 0.0:
            self._check_start(goal, drives, start)
        self._check_between(goal.joints, times, knots, start)
        return Plan(goal, times, knots, path, final, goal_time)

    def _tolerances(self, goal: TrajectoryGoal) -> tuple[tuple[Tolerance, ...], tuple[Tolerance, ...], float]:
        """Each joint's path and goal tolerance and the goal time tolerance, as joint_trajectory_controller
        resolves them: the goal's value where it gives one, 0 the group's default, -1 none; the group's
        stopped velocity tolerance the default at the goal; any other negative refused (INVALID_GOAL). A goal
        time tolerance of 0 (the group's) or -1 (the goal's) is no bound: the goal waits for its tolerance."""
        cfg = self.config
        for kind, given in (("path", goal.path_tolerance), ("goal", goal.goal_tolerance)):
            for name in given:
                if name not in goal.joints:
                    raise refuse(TrajectoryCode.INVALID_JOINTS, f"trajectory group {self.name}: a {kind} tolerance"
                                  f" for {name!r}, not one of the goal's joints {list(goal.joints)}; nothing moved")
        path = tuple(self._tolerance(j, "path", goal.path_tolerance.get(j), cfg.path_tolerance_deg, 0.0)
                     for j in goal.joints)
        final = tuple(self._tolerance(j, "goal", goal.goal_tolerance.get(j), cfg.goal_tolerance_deg,
                                      cfg.stopped_velocity_tolerance_deg_s) for j in goal.joints)
        given_s = goal.goal_time_tolerance_s
        if given_s == -1.0:  # "erased" (control_msgs' JointTolerance meanings): no bound, as 0 in the controller
            return path, final, 0.0
        if not (math.isfinite(given_s) and given_s >= 0.0):
            raise refuse(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: goal_time_tolerance {given_s!r} s:"
                          " allowed -1 (no bound), 0 (the group's default) or more; nothing moved")
        return path, final, given_s if given_s > 0 else cfg.goal_time_tolerance_s

    def _check_joints(self, joints: Sequence[str]) -> None:
        if not joints:
            raise refuse(TrajectoryCode.INVALID_JOINTS, f"trajectory group {self.name}: the goal names no joint;"
                          f" its joints: {list(self.drives)}")
        for name in joints:
            if name not in self.drives:
                raise refuse(TrajectoryCode.INVALID_JOINTS, f"trajectory group {self.name}: joint {name!r} is not"
                              f" one of its joints {list(self.drives)}; nothing moved")
        if len(set(joints)) != len(joints):
            raise refuse(TrajectoryCode.INVALID_JOINTS, f"trajectory group {self.name}: joints {list(joints)}"
                          " name a joint twice; nothing moved")
        if not self.config.allow_partial_joints_goal and set(joints) != set(self.drives):
            raise refuse(TrajectoryCode.INVALID_JOINTS, f"trajectory group {self.name}: the goal names {list(joints)},"
                          f" not all of its joints {list(self.drives)} (allow_partial_joints_goal is false); nothing"
                          " moved")

    def _check_points(self, goal: TrajectoryGoal) -> tuple[tuple[float, ...], tuple[tuple[Knot, ...], ...]]:
        """The points with a time over 0, as knots; INVALID_GOAL for a malformed one."""
        n, count = len(goal.joints), len(goal.times_s)
        bad = refuse
        if count == 0 or len(goal.positions_deg) != count:
            raise bad(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: {count} point time(s) and"
                      f" {len(goal.positions_deg)} position list(s): give one or more points, each with positions")
        previous = -math.inf
        for k, t in enumerate(goal.times_s):
            if not (math.isfinite(t) and t >= 0.0 and t > previous):
                raise bad(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: point {k} at {t!r} s: the"
                          " times must be finite, >= 0 and strictly increasing; nothing moved")
            previous = t
        if count == 1 and goal.times_s[0] == 0.0:
            raise bad(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: one point at time 0 leaves no"
                      " time to move: give it a time_from_start; nothing moved")
        knots: list[tuple[Knot, ...]] = []
        for k in range(count):
            row = []
            for j, name in enumerate(goal.joints):
                row.append(self._knot(goal, k, j, n, name))
            knots.append(tuple(row))
        self._check_end_at_rest(goal, knots[-1])
        first = 1 if goal.times_s[0] == 0.0 else 0
        return goal.times_s[first:], tuple(knots[first:])

    def _check_end_at_rest(self, goal: TrajectoryGoal, last: tuple[Knot, ...]) -> None:
        """The last point's velocities zero (or none) unless ``allow_nonzero_velocity_at_trajectory_end``:
        after it no set-point follows, so the joints would stop dead from that velocity within one SYNC
        (joint_trajectory_controller's validate_trajectory_msg, INVALID_GOAL)."""
        if self.config.allow_nonzero_velocity_at_trajectory_end:
            return
        for name, (_, velocity, _) in zip(goal.joints, last, strict=True):
            if velocity is not None and abs(velocity) > END_VELOCITY_EPSILON_DEG_S:
                raise refuse(TrajectoryCode.INVALID_GOAL, f"{name}: the trajectory's last point has a velocity of"
                              f" {velocity:.6g} deg/s: it must end at rest (velocity 0, or none), or set"
                              f" allow_nonzero_velocity_at_trajectory_end for group {self.name}; nothing moved")

    def _knot(self, goal: TrajectoryGoal, k: int, j: int, n: int, name: str) -> Knot:
        values: list[float | None] = []
        for what, rows in (("positions", goal.positions_deg), ("velocities", goal.velocities_deg_s),
                           ("accelerations", goal.accelerations_deg_s2)):
            row = rows[k] if k < len(rows) else ()
            if what != "positions" and len(row) == 0:
                values.append(None)
                continue
            if len(row) != n or not math.isfinite(row[j]):
                raise refuse(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: point {k}: {what}"
                              f" {list(row)!r} for {n} joint(s) {list(goal.joints)}: give one finite value per joint"
                              f"{'' if what == 'positions' else ' or none'}; nothing moved")
            values.append(float(row[j]))
        position, velocity, acceleration = values
        assert position is not None
        drive = self.drives[name]
        cfg = drive.config
        low, high = cfg.min_deg, cfg.max_deg
        if low is not None and high is not None and not low <= position <= high:
            raise refuse(TrajectoryCode.INVALID_GOAL, f"{name}: point {k} at {position:g} deg is beyond the joint's"
                          f" limits min_deg={low:g}, max_deg={high:g}; nothing moved")
        if velocity is not None and abs(velocity) > cfg.max_velocity_deg_s:
            raise refuse(TrajectoryCode.INVALID_GOAL, f"{name}: point {k} asks {velocity:g} deg/s, beyond"
                          f" max_velocity_deg_s={cfg.max_velocity_deg_s:g}; nothing moved")
        return (position, velocity, acceleration)

    def _check_armed(self, drive: Drive) -> None:
        """The joint may be moved: motion not held (the lifecycle node active), its verdict usable
        (the one every part reads), and this driver's last controlword Enable Operation."""
        try:
            drive.channel.admit("trajectory goal")
        except CommandRejected as err:
            raise refuse(TrajectoryCode.INVALID_GOAL, str(err)) from err
        verdict = drive.snapshot().verdict
        if not verdict.usable:
            raise refuse(TrajectoryCode.INVALID_GOAL, f"{verdict.name}: {verdict.condition.value}: {verdict.cause}"
                          + (f"; {verdict.helps}" if verdict.helps else "") + "; nothing moved")
        if drive.channel.cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
            raise refuse(TrajectoryCode.INVALID_GOAL, f"{drive.name}: not armed by this driver; enable it (/arm or"
                          " <joint>/enable) first; nothing moved")

    def _check_start(self, goal: TrajectoryGoal, drives: Sequence[Drive], start: tuple[Knot, ...]) -> None:
        """A first point at time 0 stands for where the joint is: within ``start_tolerance_deg`` of its
        set-point now (a replanned goal: the new plan is joined there) or of its measured position
        (a plan from /joint_states, which lag the set-point while the joint moves)."""
        limit = self.config.start_tolerance_deg
        for j, drive in enumerate(drives):
            first, actual, setpoint = goal.positions_deg[0][j], drive.cache.angle_deg, start[j][0]
            off = min(abs(first - actual), abs(first - setpoint))
            if not off <= limit:
                raise refuse(TrajectoryCode.INVALID_GOAL, f"{drive.name}: the trajectory starts at {first:g} deg,"
                              f" {off:.3g} deg from where the joint is ({actual:.3f} deg, set-point {setpoint:.3f});"
                              f" at most start_tolerance_deg={limit:g}. Plan from the current state; nothing moved")

    def _check_between(self, joints: Sequence[str], times: tuple[float, ...], knots: tuple[tuple[Knot, ...], ...],
                       start: tuple[Knot, ...]) -> None:
        """The plan as given within the limits at every instant, not only at its points (a cubic can
        overshoot them) nor at SYNC samples (the group samples the plan where its clock says, and a
        segment shorter than a period falls between samples): each segment's position and velocity
        polynomial judged whole (:func:`excursion`), whatever the trajectory's duration. The group
        joins the plan from where its joints are (the first segment may start elsewhere and be
        shorter, ``TrajectoryGroup._join``); each step it sends is held to the joint's limit there."""
        spline = Spline((0.0, *times), (start, *knots))
        cfgs = [self.drives[j].config for j in joints]
        for t0, duration, polys in spline.segments():
            for cfg, poly in zip(cfgs, polys, strict=True):
                low, high = cfg.min_deg, cfg.max_deg
                if low is not None and high is not None and (
                        beyond := excursion(poly, duration, low - POSITION_SLACK_DEG, high + POSITION_SLACK_DEG)):
                    raise refuse(TrajectoryCode.INVALID_GOAL, f"{cfg.name}: the trajectory passes {beyond[1]:.3f} deg"
                                  f" at {t0 + beyond[0]:.3f} s, beyond the joint's limits min_deg={low:g}, max_deg={high:g}"
                                  " (between its points); nothing moved")
                top = cfg.max_velocity_deg_s * (1 + VELOCITY_SLACK)
                if (faster := excursion(derivative(poly), duration, -top, top)) is not None:
                    raise refuse(TrajectoryCode.INVALID_GOAL, f"{cfg.name}: the trajectory moves at {faster[1]:.1f} deg/s"
                                  f" at {t0 + faster[0]:.3f} s, beyond max_velocity_deg_s={cfg.max_velocity_deg_s:g};"
                                  " slow it down; nothing moved")

    def _tolerance(self, joint: str, kind: str, given: Tolerance | None, default_deg: float,
                   default_deg_s: float) -> Tolerance:
        """A joint's tolerance: the goal's where it gives one (-1: none), else the group's (0: none)."""
        out = []
        for what, value, default in (("position", given.position_deg if given else 0.0, default_deg),
                                     ("velocity", given.velocity_deg_s if given else 0.0, default_deg_s)):
            if not math.isfinite(value) or (value < 0.0 and value != -1.0):
                raise refuse(TrajectoryCode.INVALID_GOAL, f"{joint}: {kind} {what} tolerance {value!r}: allowed -1"
                              " (none), 0 (the group's default) or a bound > 0; nothing moved")
            out.append(value if value != 0.0 else default if default > 0 else -1.0)
        return Tolerance(out[0], out[1])
