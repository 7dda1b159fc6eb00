"""A refused command is said at most once a second per joint, counted before rclpy's logger is
called (whose own throttle costs about 200 us a call, silent or not: nodes/joints/refusals.py), and no
refusal is lost: each is said or counted in the joint's next line and in /diagnostics' count."""

from __future__ import annotations

import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from nodes.joints.refusals import SAID_MAX, WARN_THROTTLE_S, RefusalLog


class Clock:
    """Time the test sets (no clock in a test)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def held_in(line: str) -> int:
    """The count of refusals a said line stands for besides itself."""
    if "more refused in the last" not in line:
        return 0
    return int(line.rsplit(" (", 1)[1].split(" ", 1)[0])


def test_a_flood_of_refusals_is_said_once_a_second_per_joint_with_the_count_held_back() -> None:
    clock, said = Clock(), []
    log = RefusalLog(said.append, clock)
    for _ in range(600):  # a second of six drives at 100 Hz, every command refused
        for joint in ("left", "right"):
            log.refuse(joint, "drive disabled")
        clock.now += 1 / 600
    assert said == ["left: refused: drive disabled", "right: refused: drive disabled"]
    clock.now += 0.01
    log.refuse("left", "drive disabled")
    assert said[-1] == "left: refused: drive disabled (599 more refused in the last 1 s)"
    assert log.take("left") == (601, "drive disabled") and log.take("right") == (600, "drive disabled")


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.floats(0.0, 1.5, allow_nan=False)), max_size=200))
def test_every_refusal_is_said_or_counted_and_lines_are_a_period_apart(steps: list[tuple[int, float]]) -> None:
    clock, said = Clock(), []
    log = RefusalLog(lambda line: said.append((clock.now, line)), clock)
    refused: dict[str, int] = {}
    for joint_index, dt in steps:
        clock.now += dt
        joint = f"j{joint_index}"
        log.refuse(joint, "why")
        refused[joint] = refused.get(joint, 0) + 1
    for joint, total in refused.items():
        lines = [(t, line) for t, line in said if line.startswith(f"{joint}: ")]
        assert lines, f"{joint}: its first refusal was not said"
        assert all(b[0] - a[0] >= WARN_THROTTLE_S for a, b in itertools.pairwise(lines))
        accounted = sum(1 + held_in(line) for _, line in lines) + log.said.held(joint)
        assert accounted == total  # said, or held and said with the next line (or still held)
        assert log.take(joint)[0] == total


def test_made_up_joint_names_cannot_grow_the_table() -> None:
    clock, said = Clock(), []
    log = RefusalLog(said.append, clock)
    for i in range(10 * SAID_MAX):
        log.refuse(f"made_up_{i}", "unknown joint")
    assert len(log.said) == SAID_MAX and len(said) == 10 * SAID_MAX
    assert log.take_others(())[0] == 10 * SAID_MAX  # /diagnostics still counts every one, once
