"""Tier 1: skid-steer kinematics, ramp and odometry (pure)."""

from __future__ import annotations

import math

import pytest

from motor_driver.skid_steer import Pose2D, SkidSteer, Twist2D, body_twist, integrate, ramp, wheel_speeds_rad_s


def test_kinematics_round_trip() -> None:
    left, right = wheel_speeds_rad_s(Twist2D(1.0, 0.5), track_width_m=0.6, wheel_radius_m=0.1)
    assert left == pytest.approx((1.0 - 0.15) / 0.1)
    assert right == pytest.approx((1.0 + 0.15) / 0.1)
    back = body_twist(left, right, 0.6, 0.1)
    assert back.linear_m_s == pytest.approx(1.0) and back.angular_rad_s == pytest.approx(0.5)


def test_ramp_limits_the_rate() -> None:
    assert ramp(0.0, 10.0, 2.0, 0.5) == 1.0
    assert ramp(0.0, -10.0, 2.0, 0.5) == -1.0
    assert ramp(0.9, 1.0, 2.0, 0.5) == 1.0


def test_skid_steer_ramps_and_clamps() -> None:
    steer = SkidSteer(0.6, 0.1, max_accel_m_s2=1.0, max_speed_m_s=0.5)
    left, right = steer.step(Twist2D(2.0, 0.0), 0.1)  # 0.1 m/s of rim speed per 0.1 s
    assert left == pytest.approx(1.0) and right == pytest.approx(1.0)
    for _ in range(100):
        left, right = steer.step(Twist2D(2.0, 0.0), 0.1)
    assert left == pytest.approx(5.0)  # clamped to 0.5 m/s


def test_odometry_drives_a_quarter_circle() -> None:
    pose = Pose2D()
    twist = Twist2D(math.pi / 2, math.pi / 2)  # radius 1 m, quarter turn in 1 s
    for _ in range(1000):
        pose = integrate(pose, twist, 0.001)
    assert pose.x_m == pytest.approx(1.0, abs=1e-3)
    assert pose.y_m == pytest.approx(1.0, abs=1e-3)
    assert pose.yaw_rad == pytest.approx(math.pi / 2, abs=1e-6)
