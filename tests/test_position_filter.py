"""The position filter holds back a position the joint cannot have reached (a corrupted frame),
judged at the faster of the joint's limit and the velocity the drive measured. A shaft coasting
past the limit (after a torque command: the kernel tier's CSP stream was refused as "jumps 65 deg"
from a position held back since the coast began) keeps its position current."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from motor_driver.drive.position import JUMP_CONFIRMATIONS, PositionFilter

PERIOD_S = 0.01
LIMIT_COUNTS_S = 1_000


def tracked(speed_counts_s: int, samples: int, *, reported: bool) -> list[bool]:
    """Positions of a shaft turning at ``speed_counts_s``, one a SYNC period; the drive's own
    velocity given with each (``reported``) or not."""
    positions = PositionFilter(1, PERIOD_S)
    positions.set_bound(LIMIT_COUNTS_S, 10.0)
    last, verdicts = 0, []
    for i in range(samples + 1):
        value = round(speed_counts_s * i * PERIOD_S)
        ok = positions.plausible(value, last, 100.0 + i * PERIOD_S, speed_counts_s if reported else 0)
        verdicts.append(ok)
        if ok:
            last = value
    return verdicts[1:]


@given(st.integers(LIMIT_COUNTS_S * 3, LIMIT_COUNTS_S * 100))
def test_a_shaft_faster_than_the_limit_keeps_its_position_current(speed: int) -> None:
    assert all(tracked(speed, 20, reported=True))


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
