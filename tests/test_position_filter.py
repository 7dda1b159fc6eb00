"""The position filter holds back a position the joint cannot have reached (a corrupted frame),
judged at the faster of the joint's limit and the velocity the drive measured. A shaft coasting
past the limit (after a torque command: the kernel tier's CSP stream was refused as "jumps 65 deg"
from a position held back since the coast began) keeps its position current."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from motor_driver.drive.constants import MEASURED_SPEED_CAP
from motor_driver.drive.received.position import JUMP_CONFIRMATIONS, PositionFilter

PERIOD_S = 0.01
LIMIT_COUNTS_S = 1_000


def tracked(speed_counts_s: int, samples: int, *, reported: bool, counts_per_unit: float = 1.0) -> list[bool]:
    """Positions of a shaft turning at ``speed_counts_s``, one a SYNC period; the drive's own
    velocity (in its unit: ``counts_per_unit`` position counts/s each) given with each
    (``reported``) or not."""
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0, counts_per_unit)
    last, verdicts = 0, []
    for i in range(samples + 1):
        value = round(speed_counts_s * i * PERIOD_S)
        velocity = round(speed_counts_s / counts_per_unit) if reported else 0
        ok = positions.plausible(value, last, 100.0 + i * PERIOD_S, velocity)
        verdicts.append(ok)
        if ok:
            last = value
    return verdicts[1:]


@given(st.integers(LIMIT_COUNTS_S * 3, LIMIT_COUNTS_S * MEASURED_SPEED_CAP), st.sampled_from([1.0, 4096 / 60.0, 0.1]))
def test_a_shaft_faster_than_the_limit_keeps_its_position_current(speed: int, counts_per_unit: float) -> None:
    """In the drive's velocity unit, whatever it is (increments/s, rpm for 4096 counts, 10 units a count)."""
    assert all(tracked(speed, 20, reported=True, counts_per_unit=counts_per_unit))


def test_a_measured_speed_opens_the_check_only_up_to_its_cap() -> None:
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0)
    assert positions.plausible(0, 0, 100.0)
    beyond = LIMIT_COUNTS_S * MEASURED_SPEED_CAP * 3 * PERIOD_S  # a bad velocity frame's speed: 10^9
    assert not positions.plausible(round(beyond), 0, 100.0 + PERIOD_S, 10**9)


def test_without_the_measured_velocity_such_a_shaft_was_held_back() -> None:
    """The rule's reason: judged at the limit alone, the coasting shaft's positions are refused
    (JUMP_CONFIRMATIONS never agree: each is further on)."""
    assert tracked(LIMIT_COUNTS_S * 10, 20, reported=False).count(False) >= 20 - JUMP_CONFIRMATIONS


def test_a_corrupted_position_is_still_held_back() -> None:
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0)
    assert positions.plausible(0, 0, 100.0, 500)
    assert not positions.plausible(1_000_000, 0, 100.0 + PERIOD_S, 500)  # 1e8 counts/s: no drive measured that
    assert positions.plausible(5, 0, 100.0 + 2 * PERIOD_S, 500)


@given(st.integers(0, 200), st.integers(1, LIMIT_COUNTS_S), st.sampled_from([1, -1]))
def test_the_32_bit_counter_wrapping_is_a_step_in_a_new_reference_never_held(before: int, speed: int,
                                                                              direction: int) -> None:
    """A continuous joint turning on past the INTEGER32 counter's end (0x6064 wraps from 2**31 - 1
    to -2**31, or back), from ``before`` counts short of it: every position is taken as it comes,
    none held back as a jump (which repeated the last one), and the wrap, once, starts a new
    reference, so the odometry never subtracts across it."""
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0)
    unwrapped = (2**31 - 1 - before) * direction
    last = unwrapped
    assert positions.plausible(last, last, 100.0)
    first = positions.reference
    for i in range(1, 60):
        unwrapped += direction * (speed * i // 100 - speed * (i - 1) // 100)  # speed counts/s, one a period
        value = (unwrapped + 2**31) % 2**32 - 2**31
        assert positions.plausible(value, last, 100.0 + i * PERIOD_S), (value, last)
        last = value
    assert positions.reference == first + (not -(2**31) <= unwrapped <= 2**31 - 1)


def test_a_position_at_the_counter_s_other_end_is_held_unless_it_is_a_wrap() -> None:
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0)
    top = 2**31 - 5
    assert positions.plausible(top, top, 100.0)
    assert positions.plausible(-(2**31) + 4, top, 100.0 + PERIOD_S)  # 10 counts on, past the end
    assert not positions.plausible(2**31 - 1000, -(2**31) + 4, 100.0 + 2 * PERIOD_S)  # 999 counts back at once
