"""The profile-position set-point handshake (CiA 402), as one small object both threads share.

A new target goes out with controlword bit 4 ("new set-point") rising; the drive answers
with statusword bit 12 ("set-point acknowledge"); the host then clears bit 4; the drive
releases bit 12; only then may the next target go out. A drive that reads its controlword once
per cycle would not see bit 4 fall and rise again if both frames came within one cycle (no
rising edge: the target ignored, its acknowledge still standing from the last one), so the
next target waits for bit 12 to be seen low. Targets commanded meanwhile are parked, and only
the newest is kept.

Two threads meet here: a command thread (:meth:`command`) and the bus's receive thread
(:meth:`acknowledged`, from the statusword). Each decision and the frame it implies are made
under one short lock, so the frames leave in the order of the decisions; the lock is never
held while waiting for the drive (sending one frame is not waiting). The rule is exact:
after any interleaving the last target sent is the newest commanded one, each target is sent
at most once, and targets go out in command order.

Owner of its state: this object (``_lock``); :meth:`idle` and :attr:`target` may be read
from any thread.

The streamed position modes (CSP, IP) have no handshake; their one reference is the last
set-point, checked for a jump. After a switch into such a mode, the drive holds where its shaft
was when the switch reached it, so the first set-point is judged from a position sampled after
the switch (:func:`rebase_after_switch`), not from one read before it: a shaft that kept turning
meanwhile (coasting after a torque command, a velocity profile still running, a slow SDO) would
have let a set-point near the old position through and the drive jump back to it, and refused
one where the drive really is.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from motor_driver.drive.received.state import DriveCache

#: SYNC periods to wait for a position sampled after a mode switch (one more is a bound).
SAMPLES_AFTER_SWITCH = 3


class SetpointHandshake:
    """``send_setpoint(counts)`` sends a target with bit 4 set; ``send_clear()`` clears bit 4."""

    def __init__(self, send_setpoint: Callable[[int], None], send_clear: Callable[[], None]) -> None:
        self._send_setpoint = send_setpoint
        self._send_clear = send_clear
        self._lock = threading.Lock()
        self._awaiting = False  # a target is out and not yet acknowledged
        self._releasing = False  # bit 4 cleared after the acknowledge; bit 12 not yet seen low
        self._pending: int | None = None  # the newest target commanded meanwhile
        self.target: int | None = None  # the last target sent

    def command(self, counts: int) -> bool:
        """Send ``counts`` now, or park it as the next one; True when it was sent now."""
        with self._lock:
            if self._awaiting or self._releasing:
                self._pending = counts  # newest wins: an older parked target is dropped
                return False
            self._send(counts)
            return True

    def on_status(self, acknowledged: bool) -> None:
        """A statusword arrived (receive thread): bit 12 set -> clear bit 4; bit 12 low again
        after that -> send the parked target, if any."""
        with self._lock:
            if self._awaiting and acknowledged:
                self._awaiting = False
                self._releasing = True
                self._send_clear()
            elif self._releasing and not acknowledged:
                self._releasing = False
                pending, self._pending = self._pending, None
                if pending is not None:
                    self._send(pending)

    def reset(self) -> None:
        """Forget the handshake (the drive left Operation Enabled, a mode switch, a re-boot)."""
        with self._lock:
            self._awaiting = False
            self._releasing = False
            self._pending = None

    @property
    def newest(self) -> int | None:
        """The newest target commanded: the one parked, else the last sent (None: none yet); any
        thread (under the lock: a parked target is being sent between the two)."""
        with self._lock:
            return self._pending if self._pending is not None else self.target

    @property
    def idle(self) -> bool:
        """No target out unacknowledged, none parked, and the drive's acknowledge released."""
        return not self._awaiting and not self._releasing and self._pending is None

    def _send(self, counts: int) -> None:
        self._awaiting = True  # before the send: an acknowledge can come back at once
        before, self.target = self.target, counts
        try:
            self._send_setpoint(counts)
        except BaseException:
            self._awaiting = False  # nothing went out: the drive will not acknowledge
            self.target = before  # nor take it
            raise


def rebase_after_switch(cache: DriveCache, forget: Callable[[int], None]) -> None:
    """After a switch into a streamed position mode: wait (at most a few SYNC periods) for a
    position sampled after it, and hand it to ``forget`` (the command channel's) as the reference of
    the first set-point."""
    seq = cache.position_seq
    cache.wait_until(lambda: cache.position_seq != seq, SAMPLES_AFTER_SWITCH * cache.sync_period_s + 0.05)
    forget(cache.received.position_counts)
