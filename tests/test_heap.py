"""can_config.heap: a long-running process's start-up objects leave the collector's walks,
and garbage made afterwards is still collected."""

from __future__ import annotations

import gc
import weakref

from can_config import heap


class _Node:
    def __init__(self) -> None:
        self.other: _Node | None = None


def test_settle_freezes_the_start_up_heap_and_later_cycles_are_still_collected() -> None:
    built = [{"od": i} for i in range(10_000)]  # what a node builds and keeps
    try:
        walked_before = len(gc.get_objects())
        frozen = heap.settle()
        assert frozen >= len(built)
        assert len(gc.get_objects()) < walked_before - len(built), "a full collection still walks the frozen heap"
        a, b = _Node(), _Node()
        a.other, b.other = b, a  # a cycle made after the freeze
        gone = weakref.ref(a)
        del a, b
        gc.collect()
        assert gone() is None, "garbage made after settle() was not collected"
    finally:
        gc.unfreeze()
