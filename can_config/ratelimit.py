"""Repeated log lines at a bounded rate: a starved process must not bury its operator in the same
warning (227 lines in 25 s on a starved machine). The first line of a kind is logged at once;
the same kind again within ``period_s`` is counted instead, and the count is said with the next
line logged ("... (12 more like this in the last 10 s)"). The core's modules and the nodes use it
alike; its clock is injectable so that tests need none."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Hashable

#: Default: at most one line of a kind every 10 s.
PERIOD_S = 10.0


class RateLimitedLog:
    """``log(level, key, msg, *args)``: at most one line per ``key`` every ``period_s``."""

    def __init__(self, logger: logging.Logger, period_s: float = PERIOD_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._logger = logger
        self._period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last: dict[Hashable, tuple[float, int]] = {}  # key -> (when last logged, held back since)

    def log(self, level: int, key: Hashable, msg: str, *args: object) -> bool:
        """Log now, or count it; True when the line was logged."""
        now = self._clock()
        with self._lock:
            last, held = self._last.get(key, (-math.inf, 0))
            if now - last < self._period_s:
                self._last[key] = (last, held + 1)
                return False
            self._last[key] = (now, 0)
        if held:
            msg += " (%d more like this in the last %.0f s)"
            args = (*args, held, now - last)
        self._logger.log(level, msg, *args)
        return True

    def held(self, key: Hashable) -> int:
        """Lines of ``key`` held back since the last one logged."""
        with self._lock:
            return self._last.get(key, (0.0, 0))[1]
