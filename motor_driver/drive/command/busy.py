"""The busy registry of one drive: the operations under way, each under a token of its own.

Owner: the command channel, which reads and changes it only under its lock. An operation is
removed by its own token only, so an operation that ends never takes another's mark with it,
and a mark never outlives the operation that made it.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass


@dataclass(frozen=True)
class Op:
    """An operation under way: its token in the busy registry and the generation it began in."""

    token: int
    name: str
    generation: int


class BusyRegistry:
    """The operations under way, oldest first."""

    def __init__(self) -> None:
        self._ops: dict[int, str] = {}
        self._tokens = itertools.count(1)

    def add(self, name: str, generation: int) -> Op:
        op = Op(next(self._tokens), name, generation)
        self._ops[op.token] = name
        return op

    def remove(self, op: Op) -> None:
        self._ops.pop(op.token, None)

    @property
    def oldest(self) -> str | None:
        return next(iter(self._ops.values()), None)

    def other_than(self, op: Op | None) -> str | None:
        """The oldest operation under way that is not ``op``, or None."""
        return next((name for token, name in self._ops.items() if op is None or token != op.token), None)

    def under_way(self, name: str) -> bool:
        """An operation named ``name`` is under way (a read of one snapshot of the names)."""
        return name in tuple(self._ops.values())

    def __bool__(self) -> bool:
        return bool(self._ops)
