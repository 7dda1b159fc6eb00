"""Repeated lines at a bounded rate: a starved process must not bury its operator in the same
warning (227 lines in 25 s on a starved machine), and a publisher whose every command is refused
must not bury it in refusals. The first line of a kind is said at once; the same kind again within
``period_s`` is counted instead, and the count is said with the next line ("... (12 more like this
in the last 10 s)"). :class:`Throttle` decides; :class:`RateLimitedLog` (the core's modules) and
the nodes' refusal log (nodes/joints/refusals.py) say. The clock is injectable so that tests need none.

Owner: whichever thread logs; each limiter keeps its counts under its own lock.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Hashable

#: Default: at most one line of a kind every 10 s.
PERIOD_S = 10.0
#: Kinds remembered at most; beyond it the least recently seen are forgotten, so that kinds made of
#: input (a publisher's made-up joint names) cannot grow the table.
KINDS_MAX = 64


class Throttle:
    """``admit(key)``: at most one pass per key every ``period_s``, with the count held back since
    the last pass. Thread-safe; at most ``kinds_max`` keys are remembered."""

    def __init__(self, period_s: float = PERIOD_S, clock: Callable[[], float] = time.monotonic,
                 kinds_max: int = KINDS_MAX) -> None:
        self._period_s = period_s
        self._clock = clock
        self._kinds_max = kinds_max
        self._lock = threading.Lock()
        self._last: dict[Hashable, tuple[float, int]] = {}  # key -> (when last passed, held back since); oldest first

    def admit(self, key: Hashable) -> tuple[int, float] | None:
        """None: held back (counted). Else the pass: (held back since the last pass, seconds since
        it; the count is 0 for a key's first pass)."""
        now = self._clock()
        with self._lock:
            last, held = self._last.pop(key, (-math.inf, 0))  # re-inserted: the newest is last
            if now - last < self._period_s:
                self._last[key] = (last, held + 1)
                return None
            if len(self._last) >= self._kinds_max:
                del self._last[next(iter(self._last))]
            self._last[key] = (now, 0)
        return held, now - last

    def held(self, key: Hashable) -> int:
        """Held back since the key's last pass."""
        with self._lock:
            return self._last.get(key, (0.0, 0))[1]

    def __len__(self) -> int:
        return len(self._last)


class RateLimitedLog:
    """``log(level, key, msg, *args)``: at most one line per ``key`` every ``period_s``."""

    def __init__(self, logger: logging.Logger, period_s: float = PERIOD_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._logger = logger
        self._throttle = Throttle(period_s, clock)

    def log(self, level: int, key: Hashable, msg: str, *args: object) -> bool:
        """Log now, or count it; True when the line was logged."""
        passed = self._throttle.admit(key)
        if passed is None:
            return False
        held, since = passed
        if held:
            msg += " (%d more like this in the last %.0f s)"
            args = (*args, held, since)
        self._logger.log(level, msg, *args)
        return True

    def held(self, key: Hashable) -> int:
        """Lines of ``key`` held back since the last one logged."""
        return self._throttle.held(key)
