"""A wait's timeout that does not count the time its process was held.

A waiter for an answer (an SDO answer, a statusword) and the thread that hands it the answer
(the bus's receive thread) live in one process. When the whole process is held (a machine
crowded with real-time work, a VM's emulation, a SIGSTOP), the answer may sit in the kernel's
socket buffer in time while neither thread runs; the waiter then wakes past its deadline before
the receive thread has read the buffer, and a timeout would blame a drive that answered. The
simulated drives judge the host the same way (by when frames reached the bus, not when they got
to look).

:class:`HeldDeadline` is checked at least every ``POLL_S`` by its waiter. A gap between two
checks longer than ``HELD_GAP_S`` is a hold: it is not counted (beyond the poll it stood for),
and after it the waiter gets at least ``resume_s`` more, so the receive thread runs once before
the verdict. What is excused is bounded (``excusable_s``): a process held for good still ends
its wait, and a drive that does not answer is still declared silent once the waiter has run
for the whole timeout.

Owner: the one waiting thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable

#: How often a waiter checks its deadline (s): the longest a single wait may block.
POLL_S = 0.05
#: A gap between two checks longer than this (s) was a hold, not a poll.
HELD_GAP_S = 0.25
#: After a hold, the wait goes on at least this long (s), capped at the timeout: the receive
#: thread gets to run once before the verdict.
RESUME_S = 0.25
#: At most this many times the timeout (and at least MIN_EXCUSABLE_S) of holds is excused.
EXCUSABLE_FACTOR = 4.0
MIN_EXCUSABLE_S = 5.0


class HeldDeadline:
    """A deadline ``timeout_s`` of this waiter's running time away (see the module)."""

    def __init__(self, timeout_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.timeout_s = timeout_s
        self._clock = clock
        now = clock()
        self._deadline = now + timeout_s
        self._last = now
        self.held_s = 0.0  # the holds excused so far
        self.excusable_s = max(MIN_EXCUSABLE_S, EXCUSABLE_FACTOR * timeout_s)
        self._resume_s = min(RESUME_S, timeout_s)

    def remaining(self) -> float:
        """Seconds left (<= 0: the time is up); a hold since the last call is not counted."""
        now = self._clock()
        gap = now - self._last
        self._last = now
        if gap > HELD_GAP_S and self.held_s < self.excusable_s:
            excused = min(gap - POLL_S, self.excusable_s - self.held_s)
            self.held_s += excused
            self._deadline = max(self._deadline + excused, now + self._resume_s)
        return self._deadline - now

    def said(self) -> str:
        """The holds excused, for a timeout's message ('' when none)."""
        return f" (this process was held {self.held_s:.1f} s meanwhile, not counted)" if self.held_s else ""
