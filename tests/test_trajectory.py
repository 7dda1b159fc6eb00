"""motor_driver.drive.trajectory: the streamed point-to-point move is a trapezoid that ends exactly on
its target and never asks for more than the speed or the acceleration it was given."""

from __future__ import annotations

import itertools
import math

import pytest

from can_config.errors import CommandRejected
from motor_driver.drive.trajectory import trapezoid

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
