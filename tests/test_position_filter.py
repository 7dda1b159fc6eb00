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
