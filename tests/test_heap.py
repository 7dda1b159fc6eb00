"""motor_driver.process.heap: a long-running process's start-up objects leave the collector's walks,
and garbage made afterwards is still collected."""

from __future__ import annotations

import gc
import weakref

from motor_driver.process import heap


class _Node:
    def __init__(self) -> None:
        self.other: _Node | None = None


def test_settle_freezes_the_start_up_heap_and_later_cycles_are_still_collected() -> None:
    built = [_Node() for _ in range(10_000)]  # what a node builds and keeps (containers the collector watches)

    def watched() -> int:
        return sum(1 for obj in gc.get_objects() if isinstance(obj, _Node))
    try:
        assert watched() >= len(built)
        frozen = heap.settle()
        assert frozen >= len(built)
        assert watched() == 0, "a full collection still walks the frozen heap"
        a, b = _Node(), _Node()
        a.other, b.other = b, a  # a cycle made after the freeze
        gone = weakref.ref(a)
        del a, b
        gc.collect()
        assert gone() is None, "garbage made after settle() was not collected"
    finally:
        gc.unfreeze()
