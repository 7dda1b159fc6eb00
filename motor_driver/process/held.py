"""A wait's timeout that gives its process one more look after a hold.

A waiter for an answer (an SDO answer, a statusword) and the thread that hands it the answer
(the bus's receive thread) live in one process. When the whole process is held (a machine
crowded with real-time work, a VM's emulation, a SIGSTOP), the answer may sit in the kernel's
socket buffer in time while neither thread runs; the waiter then wakes past its deadline before
the receive thread has read the buffer, and a timeout would blame a drive that answered. The
simulated drives judge the host the same way (by when frames reached the bus, not when they got
to look).

:class:`HeldDeadline` is checked at least every ``POLL_S`` by its waiter. When a hold (a gap
between two checks longer than ``HELD_GAP_S``) left less than ``resume_s`` (``RESUME_S``, at most
the timeout) of the wait, the wait goes on ``resume_s`` from the hold's end, so the receive
thread runs once before the verdict; at most ``MAX_RESUMES`` times a wait. Nothing else is
excused: a wait lasts its timeout plus at most those looks (and the holds themselves), however
starved the process, and a drive that does not answer is still declared silent.

A process that runs while its receive thread does not (a starved thread among busier ones, a
real-time thread of another process on its core) leaves the answer unread too, and no hold of
the waiter shows it. :class:`ReadBehind` asks, once the deadline is up, whether the receive thread
has handed on everything that had come to its socket (:func:`motor_driver.bus.adapters.receive_behind`);
while it has not, the waiter looks again, for at most ``READ_BEHIND_MAX_S`` past the deadline.
A receive thread that catches up and brought no answer leaves the verdict to the drive; one
still behind at the bound is named as the cause.

Owner: the one waiting thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable

#: How often a waiter checks its deadline (s): the longest a single wait may block.
POLL_S = 0.05
#: A gap between two checks longer than this (s) was a hold, not a poll.
HELD_GAP_S = 0.25
#: After a hold that left less than this of the wait, it goes on this long (s, at most the timeout).
RESUME_S = 0.25
#: At most this many such looks in one wait.
MAX_RESUMES = 2
#: How long past its deadline a wait goes on while the receive thread is behind (s): as long as
#: the supervisor waits for it before judging a heartbeat by the clock alone.
READ_BEHIND_MAX_S = 2.0


#: What helps when a receive thread did not keep up, for the messages that blame it.
LATE_READER_HELPS = ("its receive thread did not keep up (a starved host: CPU, real-time priorities); give the driver"
                     " its real-time priority (docs/deployment.md) or relieve the CPU")


class HeldDeadline:
    """A deadline ``timeout_s`` away that gives one more look after a hold (see the module)."""

    def __init__(self, timeout_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.timeout_s = timeout_s
        self._clock = clock
        now = clock()
        self._deadline = now + timeout_s
        self._last = now
        self.resumes = 0  # looks given after a hold
        self.held_s = 0.0  # the longest hold seen
        self._resume_s = min(RESUME_S, timeout_s)

    def remaining(self) -> float:
        """Seconds left (<= 0: the time is up)."""
        now = self._clock()
        gap = now - self._last
        self._last = now
        if gap > HELD_GAP_S:
            self.held_s = max(self.held_s, gap)
            if now + self._resume_s > self._deadline and self.resumes < MAX_RESUMES:
                self.resumes += 1  # the hold left less than a look: one look from now
                self._deadline = now + self._resume_s
        return self._deadline - now

    def said(self) -> str:
        """The hold seen, for a timeout's message ('' when none)."""
        if not self.held_s:
            return ""
        looked = "; looked again after it" if self.resumes else ""
        return f" (this process was held up to {self.held_s:.1f} s meanwhile{looked})"


class ReadBehind:
    """Whether a wait whose deadline is up looks again because the receive thread is behind (see
    the module). ``behind`` says whether that thread has yet to hand on what had come to its
    socket: True, False, or None when the bus cannot tell (then nothing is excused)."""

    def __init__(self, behind: Callable[[], bool | None], bound_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._behind = behind
        self._bound_s = READ_BEHIND_MAX_S if bound_s is None else bound_s
        self._clock = clock
        self._since: float | None = None  # when the deadline was first found up
        self.behind_s = 0.0  # how long past the deadline the receive thread was seen behind
        self.gave_up = False  # still behind at the bound: the receive thread is the cause
        self._looked = False  # it looked on at least once

    def wait_on(self) -> bool:
        """Called at each look once the deadline is up: True to look again (the receive thread is
        behind, within the bound), False to judge now."""
        now = self._clock()
        if self._since is None:
            self._since = now
        if self._behind() is not True:
            if self._looked:  # it had looked on: for how long, in the message
                self.behind_s = now - self._since
            self.gave_up = False  # caught up after all: the verdict is the drive's
            return False
        self._looked = True
        self.behind_s = now - self._since
        if self.behind_s >= self._bound_s:
            self.gave_up = True
            return False
        return True

    def said(self) -> str:
        """What the receive thread's lateness did, for a timeout's message ('' when it was not seen)."""
        if self.gave_up:
            return (f" (this driver's receive thread was still behind the bus {self.behind_s:.1f} s past the"
                    " deadline: the answer may be among what it had not read)")
        if self.behind_s:
            return f" (looked {self.behind_s:.2f} s past the deadline, until this driver's receive thread had caught up)"
        return ""
