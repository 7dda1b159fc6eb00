"""motor_driver.follow.trajectory: the streamed point-to-point move is a trapezoid that ends exactly on
its target and never asks for more than the speed or the acceleration it was given."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_config.errors import CommandRejected
from motor_driver.follow.trajectory import Spline, derivative, evaluate, excursion, sample_times, segment, trapezoid

PERIOD_S = 0.01


def rates(points: list[float], start: float) -> tuple[list[float], list[float]]:
    """Velocity and acceleration between successive set-points (one period apart)."""
    path = [start, *points]
    velocity = [(b - a) / PERIOD_S for a, b in itertools.pairwise(path)]
    accel = [(b - a) / PERIOD_S for a, b in itertools.pairwise(velocity)]
    return velocity, accel


def test_a_long_move_cruises_at_the_speed_and_ends_on_the_target() -> None:
    # 90 deg at 90 deg/s, 180 deg/s2: 0.5 s up (22.5 deg), 0.5 s at 90 deg/s, 0.5 s down: 1.5 s
    points = list(trapezoid(10.0, 100.0, 90.0, 180.0, PERIOD_S))
    assert len(points) == 150
    assert points[-1] == 100.0
    assert points[24] == pytest.approx(10.0 + 0.5 * 180.0 * 0.25**2)  # t = 0.25 s, on the ramp
    assert points[74] == pytest.approx(10.0 + 22.5 + 90.0 * 0.25)  # t = 0.75 s, cruising
    assert points[124] == pytest.approx(100.0 - 0.5 * 180.0 * 0.25**2)  # t = 1.25 s, braking
    velocity, accel = rates(points, 10.0)
    assert all(0 <= v <= 90.0 + 1e-9 for v in velocity)
    assert max(velocity) == pytest.approx(90.0, abs=180.0 * PERIOD_S)
    assert all(abs(a) <= 180.0 + 1e-6 for a in accel)


def test_a_short_move_is_a_triangle_below_the_speed() -> None:
    # 4 deg at 180 deg/s2: never 90 deg/s; peak sqrt(180 * 4) = 26.8 deg/s after 2 deg
    points = list(trapezoid(0.0, -4.0, 90.0, 180.0, PERIOD_S))
    assert points[-1] == -4.0
    velocity, accel = rates(points, 0.0)
    assert all(v <= 0.0 for v in velocity), "backwards all the way"
    assert max(abs(v) for v in velocity) == pytest.approx(math.sqrt(180.0 * 4.0), abs=180.0 * PERIOD_S)
    assert all(abs(a) <= 180.0 + 1e-6 for a in accel)
    assert all(b <= a for a, b in itertools.pairwise(points)), "monotonic toward the target"


def test_a_move_of_no_distance_is_its_target_once() -> None:
    assert list(trapezoid(42.0, 42.0, 90.0, 180.0, PERIOD_S)) == [42.0]


@pytest.mark.parametrize(("args", "named"), [
    ((0.0, math.nan, 90.0, 180.0, PERIOD_S), "target_deg"),
    ((math.inf, 1.0, 90.0, 180.0, PERIOD_S), "start_deg"),
    ((0.0, 1.0, 0.0, 180.0, PERIOD_S), "speed_deg_s"),
    ((0.0, 1.0, 90.0, -1.0, PERIOD_S), "accel_deg_s2"),
    ((0.0, 1.0, 90.0, 180.0, math.nan), "period_s"),
])
def test_bad_input_is_refused_naming_it_before_any_set_point(args: tuple[float, ...], named: str) -> None:
    with pytest.raises(CommandRejected, match=named):
        trapezoid(*args)


# ---------------------------------------------------------------------- the joint trajectory's spline
def test_a_cubic_meets_both_knots_and_their_velocities() -> None:
    c = segment(0.0, 0.0, None, 1.0, 0.0, None, 1.0)
    assert c == (0.0, 0.0, 3.0, -2.0)  # 3t^2 - 2t^3
    assert evaluate(c, 0.5) == (0.5, 1.5, 0.0)
    assert evaluate(c, 1.0) == (1.0, 0.0, -6.0)
    moving = segment(10.0, 4.0, None, 20.0, -2.0, None, 2.0)
    p, v, _ = evaluate(moving, 2.0)
    assert (p, v) == pytest.approx((20.0, -2.0), abs=1e-12)


def test_a_quintic_meets_position_velocity_and_acceleration_at_both_knots() -> None:
    c = segment(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    assert c == (0.0, 0.0, 0.0, 10.0, -15.0, 6.0)  # the minimum-jerk polynomial
    assert evaluate(c, 0.5) == (0.5, 1.875, 0.0)
    general = segment(-5.0, 3.0, -1.0, 7.0, 2.0, 4.0, 1.5)
    assert evaluate(general, 0.0) == (-5.0, 3.0, -1.0)
    assert evaluate(general, 1.5) == pytest.approx((7.0, 2.0, 4.0), abs=1e-9)


def test_positions_only_are_joined_by_lines() -> None:
    c = segment(2.0, None, None, 6.0, None, None, 4.0)
    assert c == (2.0, 1.0)
    assert evaluate(c, 1.0) == (3.0, 1.0, 0.0)
    # a knot with velocity beside one without: the line (the lowest order both give)
    assert segment(2.0, 5.0, None, 6.0, None, None, 4.0) == (2.0, 1.0)


def test_a_spline_samples_each_segment_and_rests_after_the_end() -> None:
    spline = Spline((0.0, 1.0, 3.0), (((0.0, 0.0, 0.0), (1.0, None, None)),
                                      ((1.0, 0.0, 0.0), (3.0, None, None)),
                                      ((0.0, 0.0, 0.0), (4.0, None, None))))
    assert spline.sample(-1.0) == ((0.0, 0.0, 0.0), (1.0, 2.0, 0.0))
    assert spline.sample(0.5) == ((0.5, 1.875, 0.0), (2.0, 2.0, 0.0))
    assert spline.sample(2.0) == ((0.5, -0.9375, 0.0), (3.5, 0.5, 0.0))  # the second segment: 1 s of 2, half way
    assert spline.sample(5.0) == ((0.0, 0.0, 0.0), (4.0, 0.0, 0.0))
    assert spline.end_s == 3.0


def test_a_spline_refuses_times_that_do_not_increase() -> None:
    knot = ((0.0, None, None),)
    for times in ((0.0,), (0.5, 1.0), (0.0, 1.0, 1.0)):
        with pytest.raises(CommandRejected, match="strictly increasing"):
            Spline(times, (knot,) * len(times))


def test_sample_times_one_a_period_and_the_end_exactly() -> None:
    assert list(sample_times(0.05, 0.02)) == [0.02, 0.04, 0.05]
    assert list(sample_times(0.04, 0.02)) == [0.02, 0.04]
    assert list(sample_times(0.001, 0.02)) == [0.001]
    assert len(list(sample_times(4.0, 0.002))) == 2000


coefficient = st.floats(-1e3, 1e3, allow_nan=False)


@given(st.lists(coefficient, min_size=1, max_size=6), st.floats(1e-4, 100.0), st.floats(-50.0, 50.0),
       st.floats(0.0, 100.0))
def test_excursion_finds_a_value_beyond_the_bounds_exactly_where_dense_samples_do(
        coefficients: list[float], duration_s: float, low: float, width: float) -> None:
    """Against 4,001 samples of the polynomial: a value found beyond is the polynomial's there and
    beyond; None only where no sample lies beyond the bounds (by more than rounding)."""
    poly, high = tuple(coefficients), low + width
    found = excursion(poly, duration_s, low, high)
    if found is not None:
        t, value = found
        assert 0.0 <= t <= duration_s
        assert value == pytest.approx(evaluate(poly, t)[0], rel=1e-6, abs=1e-6)
        assert not low <= value <= high
    else:
        slack = 1e-9 * max(1.0, *(abs(c) * duration_s**i for i, c in enumerate(poly)))
        for k in range(4001):
            value = evaluate(poly, duration_s * k / 4000)[0]
            assert low - slack <= value <= high + slack, (k, value)


def test_excursion_is_exact_between_samples_and_the_derivative_is_the_polynomial_s() -> None:
    # 10 deg in 8 ms: a line at 1,250 deg/s; within bounds of 1,250 and not of 1,249
    line = segment(0.0, None, None, 10.0, None, None, 0.008)
    assert derivative(line) == pytest.approx((1250.0,))
    assert excursion(derivative(line), 0.008, -1250.0, 1250.0) is None
    assert excursion(derivative(line), 0.008, -1249.0, 1249.0) == (0.0, pytest.approx(1250.0))
    # a cubic from 80 deg at 170 deg/s to 89 deg at rest in 0.5 s peaks between its ends, near 95.4 deg
    cubic = segment(80.0, 170.0, None, 89.0, 0.0, None, 0.5)
    assert excursion(cubic, 0.5, -90.0, 96.0) is None
    t, value = excursion(cubic, 0.5, -90.0, 90.0) or (0.0, 0.0)
    assert 0.0 < t < 0.5 and value > 90.0
    assert derivative((3.0,)) == (0.0,)
