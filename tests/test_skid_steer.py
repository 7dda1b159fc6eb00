"""Tier 1: skid-steer kinematics, ramp and odometry (pure)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motor_driver.rover.skid_steer import Pose2D, SkidSteer, Twist2D, body_twist, integrate, ramp, wheel_speeds_rad_s


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


def test_desaturation_scales_the_whole_command_and_keeps_its_curvature() -> None:
    steer = SkidSteer(0.6, 0.1, max_accel_m_s2=1.0, max_speed_m_s=1.0, max_angular_rad_s=2.0,
                      max_wheel_rad_s=math.radians(720.0))
    wanted = Twist2D(1.0, 4.0)  # the right wheel would need (1.0 + 1.2) / 0.1 = 22 rad/s
    got = steer.desaturate(wanted)
    assert got.angular_rad_s / got.linear_m_s == pytest.approx(4.0)  # same curvature
    left, right = wheel_speeds_rad_s(got, 0.6, 0.1)
    assert max(abs(left), abs(right)) == pytest.approx(10.0)  # the rim limit 1.0 m/s binds first
    assert abs(got.angular_rad_s) <= 2.0
    spin = steer.desaturate(Twist2D(0.0, 4.0))
    assert spin.angular_rad_s == pytest.approx(2.0) and spin.linear_m_s == 0.0  # max_angular_rad_s
    slow_drive = SkidSteer(0.6, 0.1, 1.0, 5.0, max_wheel_rad_s=3.0)
    left, right = wheel_speeds_rad_s(slow_drive.desaturate(Twist2D(1.0, 1.0)), 0.6, 0.1)
    assert max(abs(left), abs(right)) == pytest.approx(3.0)  # the slowest drive's limit
    assert steer.desaturate(Twist2D(0.2, 0.1)) == Twist2D(0.2, 0.1)  # within every limit: untouched


@given(v=st.floats(-5, 5), w=st.floats(-10, 10))
def test_no_wheel_ever_exceeds_its_limit_and_both_sides_arrive_together(v: float, w: float) -> None:
    steer = SkidSteer(0.6, 0.1, max_accel_m_s2=1.0, max_speed_m_s=1.0, max_angular_rad_s=2.0,
                      max_wheel_rad_s=math.radians(720.0))
    target = wheel_speeds_rad_s(steer.desaturate(Twist2D(v, w)), 0.6, 0.1)
    for _ in range(400):
        left, right = steer.step(Twist2D(v, w), 0.01)
        assert max(abs(left), abs(right)) <= 10.0 + 1e-9
        if abs(target[0]) > 1e-6 and abs(target[1]) > 1e-6:
            assert left / target[0] == pytest.approx(right / target[1], abs=1e-9)  # on the line to the target
    assert (left, right) == pytest.approx(target)
    for _ in range(400):  # stale: down to zero, and never away from it again
        prev = (left, right)
        left, right = steer.step(Twist2D(), 0.01)
        assert abs(left) <= abs(prev[0]) + 1e-12 and abs(right) <= abs(prev[1]) + 1e-12
    assert (left, right) == (0.0, 0.0)


def test_halt_forgets_the_ramp() -> None:
    steer = SkidSteer(0.6, 0.1, max_accel_m_s2=1.0, max_speed_m_s=1.0)
    for _ in range(50):
        steer.step(Twist2D(1.0, 0.0), 0.1)
    steer.halt()
    assert steer.step(Twist2D(), 0.1) == (0.0, 0.0)  # a stale ramp-down from nothing is nothing
