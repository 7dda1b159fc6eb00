"""The CPU ratio's reference, the canopen library doing the stack run's work, counts only when
that work kept its timing on the wire: its SYNC every period and each drive's set-point every
command period (benchmarks/same_work.py). Opened without the config's transport settings, the
library's frames left in 40-50 ms clumps, and the run was a fifth of the receive wake-ups."""

from __future__ import annotations

import sys

import pytest

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
from same_work import CADENCE_MAX_PERIODS, cadence

PERIOD_S = 0.01


def frames(stamps: list[float], cob_id: int = 0x080) -> list[tuple[float, int, bytes]]:
    return [(t, cob_id, b"") for t in stamps]


def test_a_sync_every_period_keeps_its_cadence() -> None:
    on_time = frames([i * PERIOD_S + (0.0003 if i % 7 == 0 else 0.0) for i in range(500)])
    assert cadence(on_time, 0x080, 0.0, 5.0) <= CADENCE_MAX_PERIODS * PERIOD_S


def test_frames_clumped_by_nagle_are_not_the_same_work() -> None:
    """Five periods' SYNCs within a millisecond, every 50 ms, as the untuned connection sent them."""
    clumped = frames([k * 5 * PERIOD_S + j * 0.0002 for k in range(100) for j in range(5)])
    assert cadence(clumped, 0x080, 0.0, 5.0) > CADENCE_MAX_PERIODS * PERIOD_S


@pytest.mark.parametrize("window", [(1.0, 1.0), (6.0, 7.0)])
def test_no_frame_in_the_window_is_no_cadence(window: tuple[float, float]) -> None:
    stamps = frames([i * PERIOD_S for i in range(500)], cob_id=0x301)
    assert cadence(stamps, 0x301, *window) == float("inf")  # fails the check: nothing was sent
    assert cadence(stamps, 0x080, 0.0, 5.0) == float("inf")  # another frame's stamps do not count
