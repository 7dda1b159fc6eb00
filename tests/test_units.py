"""Tier 1: unit conversions and command checks (pure)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_config.errors import CommandRejected
from motor_driver.protocol.units import Scale, check_limits, nearest_equivalent, require_finite


def test_degrees_to_counts_with_gear_ratio() -> None:
    scale = Scale(counts_per_deg=4096 * 100 / 360.0, rated_torque_nm=0.5, gear_ratio=100)
    assert scale.deg_to_counts(90.0) == 102_400
    assert scale.counts_to_deg(102_400) == pytest.approx(90.0)
    assert scale.deg_s_to_counts_s(-3.6) == -4096
    # 0x6077 is per mille of the motor's rated torque; the joint sees it times the gear ratio
    assert scale.permille_to_nm(500) == pytest.approx(0.25 * 100)
    assert scale.nm_to_permille(25.0) == 500


@given(st.integers(-(2**31), 2**31 - 1), st.floats(0.01, 1e6), st.booleans(), st.floats(-3600.0, 3600.0))
def test_a_drive_position_in_degrees_converts_back_to_the_same_counts(counts: int, counts_per_deg: float, invert: bool,
                                                                      offset_deg: float) -> None:
    """move_to returns its target in degrees; move_joint takes the counts it commanded back from it
    (to tell another command's target from its own), so the round trip is exact over 0x607A's range."""
    scale = Scale(counts_per_deg=counts_per_deg, rated_torque_nm=1.0, invert=invert, offset_deg=offset_deg)
    assert scale.deg_to_counts(scale.counts_to_deg(counts)) == counts


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


def test_scale_from_the_drives_own_objects() -> None:
    from motor_driver.protocol.units import scale_from_objects

    # Ingenia Everest: 0x608F = 2000/1 increments per motor rev, feed 1:1 -> increments
    scale, notes = scale_from_objects(None, 1.0, 1.0, {(0x608F, 1): 2000, (0x608F, 2): 1,
                                                       (0x6092, 1): 1, (0x6092, 2): 1, (0x6076, 0): 0x136})
    assert scale.deg_to_counts(360.0) == 2000
    assert scale.rated_torque_nm == pytest.approx(0.310)
    assert any("0x6076" in n for n in notes)
    # Faulhaber MCBL: feed constant 3000/1 -> 3000 feed units per joint revolution
    scale, _ = scale_from_objects(4096, 1.0, 1.0, {(0x6092, 1): 3000, (0x6092, 2): 1})
    assert scale.deg_to_counts(90.0) == 750
    # maxon EPOS4: 0x60A9 = 0x00B44700 -> velocity in motor rev/min; gear 10 at the joint
    scale, notes = scale_from_objects(4096, 10.0, 1.0, {(0x60A9, 0): 0x00B44700})
    assert scale.deg_s_to_counts_s(36.0) == 60  # 36 deg/s at the joint = 0.1 rev/s = 1 rev/s at the motor = 60 rpm
    assert scale.counts_s_to_deg_s(60) == pytest.approx(36.0)
    assert any("rev/min" in n for n in notes)
    # nothing from the drive: the config
    scale, _ = scale_from_objects(1000, 2.0, 1.0, {})
    assert scale.deg_to_counts(180.0) == 1000
