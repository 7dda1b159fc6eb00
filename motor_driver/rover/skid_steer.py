"""Skid-steer kinematics, acceleration ramp and odometry of the rover's drive system (pure).

Body twist (v m/s, w rad/s) -> wheel speeds: left = (v - w*T/2)/r, right = (v + w*T/2)/r
(rad/s), T the track width and r the wheel radius. No I/O and no ROS: the node feeds it. The
odometry is :mod:`motor_driver.rover.odometry`'s: the wheels' measured position deltas, never a speed
times a tick.

Limits never bend a turn: a command beyond any limit (body speed, body turn rate, any wheel's
rim speed or drive speed) is scaled as a whole, v and w by one factor, so its curvature
stays; the acceleration ramp moves both sides along a straight line in (left, right) wheel
space, so they reach their target together and the curvature holds while ramping too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Twist2D:
    linear_m_s: float = 0.0
    angular_rad_s: float = 0.0


@dataclass(frozen=True)
class Pose2D:
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0


def wheel_speeds_rad_s(twist: Twist2D, track_width_m: float, wheel_radius_m: float) -> tuple[float, float]:
    """(left, right) wheel angular speeds for a body twist."""
    half = track_width_m / 2.0
    left = (twist.linear_m_s - twist.angular_rad_s * half) / wheel_radius_m
    right = (twist.linear_m_s + twist.angular_rad_s * half) / wheel_radius_m
    return left, right


def body_twist(left_rad_s: float, right_rad_s: float, track_width_m: float, wheel_radius_m: float) -> Twist2D:
    """Body twist from (mean) left and right wheel speeds."""
    v_left, v_right = left_rad_s * wheel_radius_m, right_rad_s * wheel_radius_m
    return Twist2D((v_left + v_right) / 2.0, (v_right - v_left) / track_width_m)


def ramp(current: float, target: float, max_rate: float, dt: float) -> float:
    """Move ``current`` toward ``target`` by at most ``max_rate * dt``."""
    step = max_rate * dt
    if target > current + step:
        return current + step
    if target < current - step:
        return current - step
    return target


def integrate(pose: Pose2D, twist: Twist2D, dt: float) -> Pose2D:
    """Advance a pose by a body twist over ``dt`` (midpoint heading)."""
    mid = pose.yaw_rad + twist.angular_rad_s * dt / 2.0
    return Pose2D(pose.x_m + twist.linear_m_s * math.cos(mid) * dt,
                  pose.y_m + twist.linear_m_s * math.sin(mid) * dt,
                  math.remainder(pose.yaw_rad + twist.angular_rad_s * dt, 2 * math.pi))


#: The share of a wheel's limit kept as margin against rounding (a nanometre a second at 1 m/s).
LIMIT_MARGIN = 1e-9
#: A command whose speed or turn rate exceeds this is first brought to it, curvature kept: beyond
#: any rover's limit, so the limits then scale it as any command over them.
BEYOND_ANY_LIMIT = 1e6


class SkidSteer:
    """Commanded twist -> desaturated, ramped wheel speed setpoints."""

    def __init__(self, track_width_m: float, wheel_radius_m: float, max_accel_m_s2: float,
                 max_speed_m_s: float, *, max_angular_rad_s: float = math.inf,
                 max_wheel_rad_s: float = math.inf) -> None:
        self.track_width_m = track_width_m
        self.wheel_radius_m = wheel_radius_m
        self.max_accel_m_s2 = max_accel_m_s2
        self.max_speed_m_s = max_speed_m_s
        self.max_angular_rad_s = max_angular_rad_s
        #: the slowest wheel's limit: its drive's max velocity, and max_speed_m_s at its rim, less a
        #: rounding's margin: a speed scaled to it and turned into the drive's unit must not come out an
        #: ulp over the drive's own limit, which refuses it (and the drive system then halts every wheel)
        self.max_wheel_rad_s = min(max_wheel_rad_s, max_speed_m_s / wheel_radius_m) * (1.0 - LIMIT_MARGIN)
        self.left_rad_s = 0.0
        self.right_rad_s = 0.0
        #: the share of every limit in force (1.0; less while wheels are left out: the drive system's
        #: on_wheel_loss: continue)
        self.share = 1.0

    def desaturate(self, twist: Twist2D) -> Twist2D:
        """``twist`` scaled as a whole (same curvature) so that every limit holds."""
        v, w = twist.linear_m_s, twist.angular_rad_s
        share = self.share
        if share <= 0.0:
            return Twist2D()
        if (size := max(abs(v), abs(w))) > BEYOND_ANY_LIMIT:  # its wheel speeds would overflow to inf (a
            v, w = v / size * BEYOND_ANY_LIMIT, w / size * BEYOND_ANY_LIMIT  # factor 0: a stop); same curvature
        factor = 1.0
        if abs(v) > self.max_speed_m_s * share:
            factor = min(factor, self.max_speed_m_s * share / abs(v))
        if abs(w) > self.max_angular_rad_s * share:
            factor = min(factor, self.max_angular_rad_s * share / abs(w))
        peak = max(abs(x) for x in wheel_speeds_rad_s(Twist2D(v, w), self.track_width_m, self.wheel_radius_m))
        if peak > self.max_wheel_rad_s * share:
            factor = min(factor, self.max_wheel_rad_s * share / peak)
        return Twist2D(v * factor, w * factor)

    def step(self, target: Twist2D, dt: float) -> tuple[float, float]:
        """(left, right) wheel setpoints in rad/s toward the desaturated ``target``; neither side
        changes faster than the rim acceleration allows, and both arrive together."""
        left, right = wheel_speeds_rad_s(self.desaturate(target), self.track_width_m, self.wheel_radius_m)
        cap = self.max_wheel_rad_s * self.share  # what scaling's rounding left over it, cut (never more than an ulp)
        left, right = max(-cap, min(cap, left)), max(-cap, min(cap, right))
        d_left, d_right = left - self.left_rad_s, right - self.right_rad_s
        largest = max(abs(d_left), abs(d_right))
        step = self.max_accel_m_s2 / self.wheel_radius_m * dt
        if largest <= step:
            self.left_rad_s, self.right_rad_s = left, right
        else:
            self.left_rad_s += d_left * step / largest
            self.right_rad_s += d_right * step / largest
        return self.left_rad_s, self.right_rad_s

    def limit_to(self, share: float) -> None:
        """Every limit cut to ``share`` of itself (1.0: all of it; 0.0: no motion)."""
        self.share = min(max(share, 0.0), 1.0)

    def halt(self) -> None:
        """Forget the ramp: the wheels were stopped by someone else (a refusal, a fault). The
        next command ramps up from standstill; a stale one never brings them back."""
        self.left_rad_s = self.right_rad_s = 0.0
