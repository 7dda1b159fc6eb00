"""What every driver node shares: a refused command said once a second per joint, header stamps.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

from rclpy.node import Node

WARN_THROTTLE_S = 1.0
DEG = 180.0 / math.pi


def stamp_header(msg_header: Any, stamp: float) -> None:
    msg_header.stamp.sec = int(stamp)
    msg_header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)


class RefusalLog:
    """Counts refused commands per joint for /diagnostics and logs them, throttled."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self.count: dict[str, int] = {}
        self.last: dict[str, str] = {}

    def refuse(self, joint: str, why: str) -> None:
        self.count[joint] = self.count.pop(joint, 0) + 1  # re-inserted: the newest refusal is last
        self.last[joint] = why
        self._node.get_logger().warning(f"{joint}: refused: {why}", throttle_duration_sec=WARN_THROTTLE_S)

    def take(self, joint: str) -> tuple[int, str]:
        """Refusals of one joint since the last call, and the newest reason; cleared."""
        return self.count.pop(joint, 0), self.last.pop(joint, "")

    def take_others(self, joints: Collection[str]) -> tuple[int, str]:
        """Refusals not about a configured joint (unknown names, /cmd_vel), summed with the newest
        reason, and cleared: a publisher of made-up joint names cannot grow these tables."""
        others = [k for k in self.count if k not in joints]
        newest = self.last.get(others[-1], "") if others else ""
        total = 0
        for key in others:
            total += self.count.pop(key)
            self.last.pop(key, None)
        return total, newest
