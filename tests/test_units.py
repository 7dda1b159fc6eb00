"""Tier 1: unit conversions and command checks (pure)."""

from __future__ import annotations

import math

import pytest

from can_config.errors import CommandRejected
from motor_driver.units import Scale, check_limits, nearest_equivalent, require_finite


def test_degrees_to_counts_with_gear_ratio() -> None:
    scale = Scale(counts_per_deg=4096 * 100 / 360.0, rated_torque_nm=0.5, gear_ratio=100)
    assert scale.deg_to_counts(90.0) == 102_400
    assert scale.counts_to_deg(102_400) == pytest.approx(90.0)
    assert scale.deg_s_to_counts_s(-3.6) == -4096
    # 0x6077 is per mille of the motor's rated torque; the joint sees it times the gear ratio
    assert scale.permille_to_nm(500) == pytest.approx(0.25 * 100)
    assert scale.nm_to_permille(25.0) == 500


@pytest.mark.parametrize(("cmd", "current", "expected"), [
    (0.0, 359.9, 360.0),  # wraps the short way
    (359.9, 0.0, -0.1),
    (180.0, 0.0, -180.0),
    (90.0, 725.0, 810.0),  # multi-turn
    (10.0, 10.0, 10.0),
])
def test_continuous_joint_takes_the_short_way(cmd: float, current: float, expected: float) -> None:
    assert nearest_equivalent(cmd, current) == pytest.approx(expected)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_commands_are_refused_naming_the_input(bad: float) -> None:
    with pytest.raises(CommandRejected, match=r"joint1 angle=.*not a finite number"):
        require_finite("joint1 angle", bad, "deg")


def test_limits_name_the_limit() -> None:
    check_limits("elbow", 10.0, -90.0, 90.0)
    with pytest.raises(CommandRejected, match=r"above the upper limit max_deg=90"):
        check_limits("elbow", 90.5, -90.0, 90.0)
    with pytest.raises(CommandRejected, match=r"below the lower limit min_deg=-90"):
        check_limits("elbow", -91.0, -90.0, 90.0)
