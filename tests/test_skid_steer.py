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


@given(limit=st.floats(60.0, 3000.0), radius=st.floats(0.05, 0.5), track=st.floats(0.2, 2.0),
       v=st.floats(-1e3, 1e3), w=st.floats(-1e3, 1e3), speed=st.floats(0.1, 10.0))
def test_no_wheel_speed_is_ever_over_its_drive_s_own_limit_in_its_unit(limit: float, radius: float, track: float,
                                                                       v: float, w: float, speed: float) -> None:
    """Each wheel's set-point, as the drive system sends it (rad/s x DEG_PER_RAD), against the
    drive's own check (`abs(velocity) > max_velocity_deg_s`: refused, and every wheel halted). A
    command scaled to the drive's limit came out an ulp over it for a third of the commands over
    it: at top speed the rover stopped, started again, and stopped."""
    from motor_driver.protocol.units import DEG_PER_RAD

    steer = SkidSteer(track, radius, max_accel_m_s2=1e9, max_speed_m_s=speed, max_wheel_rad_s=math.radians(limit))
    for _ in range(3):  # the ramp's last step lands on the target
        left, right = steer.step(Twist2D(v, w), 0.01)
        assert abs(left * DEG_PER_RAD) <= limit and abs(right * DEG_PER_RAD) <= limit, (left, right)


@pytest.mark.parametrize(("v", "w"), [(1e308, 0.0), (-1e308, 0.0), (0.0, 1e308), (1e308, 1e308), (1e300, -3e299)])
def test_a_huge_command_is_scaled_to_the_limits_not_turned_into_a_stop(v: float, w: float) -> None:
    """Its wheel speeds overflowed to inf and the scale factor to 0: the rover stopped while the
    drive system said "driving". Scaled as any command over the limits: the limit, its curvature."""
    steer = SkidSteer(0.6, 0.1, max_accel_m_s2=1.0, max_speed_m_s=1.0, max_angular_rad_s=2.0,
                      max_wheel_rad_s=math.radians(720.0))
    got = steer.desaturate(Twist2D(v, w))
    left, right = wheel_speeds_rad_s(got, 0.6, 0.1)
    assert max(abs(left), abs(right)) == pytest.approx(10.0) or abs(got.angular_rad_s) == pytest.approx(2.0)
    if v and w:
        assert got.angular_rad_s / got.linear_m_s == pytest.approx(w / v)
    assert math.copysign(1.0, got.linear_m_s or got.angular_rad_s) == math.copysign(1.0, v or w)
