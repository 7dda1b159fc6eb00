"""What every driver node shares: a refused command said once a second per joint.

The once a second is counted here (motor_driver.process.ratelimit's Throttle), before rclpy's logger is called: rclpy's own throttle
(``throttle_duration_sec``) finds its caller's file and line (``inspect``, a ``stat`` per
frame) before it decides to stay silent, about 200 us a call; a publisher whose every command
is refused (600 a second: six drives at 100 Hz, the drives stopped) took the driver's main thread
to two thirds of its CPU in that (the six-drive profile, docs/performance.md).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection
from typing import Any

from motor_driver.process.ratelimit import KINDS_MAX, Throttle

WARN_THROTTLE_S = 1.0
#: Joints whose last line is remembered; beyond it the oldest are forgotten (made-up names).
SAID_MAX = KINDS_MAX


class RefusalLog:
    """Counts refused commands per joint for /diagnostics and says them with ``say`` (a node's
    ``get_logger().warning``), at most once per joint every WARN_THROTTLE_S, with the count of
    those held back since. Thread-safe: the hot thread and the handoff's workers refuse
    (nodes/joints/handoff.py), the diagnostics timer takes."""

    def __init__(self, say: Callable[[str], Any], clock: Callable[[], float] = time.monotonic) -> None:
        self._say = say
        self._lock = threading.Lock()
        self.count: dict[str, int] = {}
        self.last: dict[str, str] = {}
        self.said = Throttle(WARN_THROTTLE_S, clock, SAID_MAX)

    def refuse(self, joint: str, why: str) -> None:
        with self._lock:
            self.count[joint] = self.count.pop(joint, 0) + 1  # re-inserted: the newest refusal is last
            self.last[joint] = why
            passed = self.said.admit(joint)
        if passed is None:
            return
        held, since = passed
        more = f" ({held} more refused in the last {since:.0f} s)" if held else ""
        self._say(f"{joint}: refused: {why}{more}")

    def take(self, joint: str) -> tuple[int, str]:
        """Refusals of one joint since the last call, and the newest reason; cleared."""
        with self._lock:
            return self.count.pop(joint, 0), self.last.pop(joint, "")

    def take_others(self, joints: Collection[str]) -> tuple[int, str]:
        """Refusals not about a configured joint (unknown names, /cmd_vel), summed with the newest
        reason, and cleared: a publisher of made-up joint names cannot grow these tables."""
        with self._lock:
            others = [k for k in self.count if k not in joints]
            newest = self.last.get(others[-1], "") if others else ""
            total = 0
            for key in others:
                total += self.count.pop(key)
                self.last.pop(key, None)
        return total, newest
