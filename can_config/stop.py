"""Process stop requests: SIGINT and SIGTERM set an event instead of raising.

Every long-running entry point (CLI commands, ROS nodes) waits on the event and then tears
down in one order it owns: drives to a safe state, threads joined, buses closed. Raising
``KeyboardInterrupt`` at a random bytecode, or rclpy shutting its context down under a
running executor, cannot give that order.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType


class StopSignal:
    """Context manager: while active, SIGINT/SIGTERM set :attr:`event` (main thread only)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signum: int | None = None
        self._old: dict[int, object] = {}

    def __enter__(self) -> StopSignal:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.signum = signum
        self.event.set()

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._old.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._old.clear()
