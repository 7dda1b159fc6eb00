"""A stall of the machine told apart from a product failure, in the kernel tier's VM.

Under software emulation beside the host tier, a process in the VM can be held for a second
and more (measured: the host heartbeat 156 ms late, a drive's consumer hearing none for 1206
ms). The kernel tier's consumer times are set above the worst stall seen (conftest.KERNEL_DRIVE);
a stall longer still trips a drive anyway, as designed. When a test of order and outcome fails,
:func:`told_apart` says which it was, from what the bus itself shows: the longest silence of the
driver's host heartbeat and of the drive's own heartbeat on the wire (kernel receive times, so a
stall of either process shows), the EMCY 0x8130 (the drive stopped itself: no host), and the
worst wake-up lateness of a thread of this process (:class:`StallWatch`).

The worst stall of every kernel test is kept in :data:`SEEN` and the worst of the session printed
at its end (tests/conftest.py), so the consumer times can be checked against what was measured.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import can

from can_config.errors import MotorError

#: How often the watch thread wakes up to see how late it is.
TICK_S = 0.02
#: The driver's NMT id in the kernel tier's configs (the config's default host_node_id).
HOST_NODE_ID = 127
#: (test, the worst lateness of this process during it, in s): printed at the session's end
SEEN: list[tuple[str, float]] = []


class StallWatch:
    """A thread that sleeps TICK_S at a time and keeps the worst lateness of its wake-ups: how
    long this process (its threads, the GIL, the VM's vCPU) was held at most."""

    def __init__(self) -> None:
        self.worst_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stall-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(TICK_S):
            now = time.monotonic()
            self.worst_s = max(self.worst_s, now - last - TICK_S)
            last = now

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def longest_silence(frames: Sequence[can.Message], cob_id: int, heard_until: float | None = None) -> float:
    """The longest gap between two frames of ``cob_id`` (kernel receive times), and from its last
    frame to ``heard_until`` (a time by which the listener had read everything the kernel had
    received: a silence still going on when a test fails); 0.0 with none to judge."""
    stamps = [m.timestamp for m in frames if m.arbitration_id == cob_id and not m.is_error_frame]
    if stamps and heard_until is not None and heard_until > stamps[-1]:
        stamps.append(heard_until)
    return max((b - a for a, b in itertools.pairwise(stamps)), default=0.0)


def host_loss_emcy(frames: Sequence[can.Message], node: int) -> bool:
    """The drive said EMCY 0x8130 (heartbeat or life guard of its master lost): it stopped itself."""
    return any(m.arbitration_id == 0x080 + node and len(m.data) >= 2 and m.data[:2] == b"\x30\x81" for m in frames)


@dataclass
class Evidence:
    """What the bus and this process show of a stall, for one drive and its consumer times."""

    frames: Callable[[], Sequence[can.Message]]
    node: int
    host_timeout_s: float
    heartbeat_timeout_s: float
    watch: StallWatch | None = None
    #: the wall-clock time by which the listener had read all the kernel had received (None: unknown)
    heard_until: Callable[[], float | None] = lambda: None

    def verdict(self) -> str:
        until = self.heard_until()  # before the frames: every frame stamped before it is among them
        frames = list(self.frames())
        host = longest_silence(frames, 0x700 + HOST_NODE_ID, until)
        drive = longest_silence(frames, 0x700 + self.node, until)
        held = self.watch.worst_s if self.watch is not None else 0.0
        seen = (f"longest silence on the wire: host heartbeat {host * 1000:.0f} ms (the drive's consumer time"
                f" {self.host_timeout_s * 1000:.0f} ms), node {self.node}'s heartbeat {drive * 1000:.0f} ms (the"
                f" driver's consumer time {self.heartbeat_timeout_s * 1000:.0f} ms); this process held at most"
                f" {held * 1000:.0f} ms; EMCY 0x8130 {'seen' if host_loss_emcy(frames, self.node) else 'not seen'}")
        if host > self.host_timeout_s or drive > self.heartbeat_timeout_s or held > min(self.host_timeout_s,
                                                                                          self.heartbeat_timeout_s):
            return ("MACHINE STALL, not a product failure: a process in the VM was held longer than a consumer"
                    f" time, and the drive stopped itself as designed ({seen}). Raise the kernel tier's consumer"
                    " times in tests/conftest.py (KERNEL_DRIVE) above the stall if it recurs")
        return f"PRODUCT FAILURE: no stall longer than a consumer time was seen ({seen})"


@contextmanager
def told_apart(evidence: Evidence) -> Iterator[None]:
    """A failed assertion or a refused command inside the block fails the test with the stall
    verdict in front of its own message."""
    try:
        yield
    except (AssertionError, MotorError) as err:
        raise AssertionError(f"{evidence.verdict()}\n{type(err).__name__}: {err}") from err


def summary() -> str:
    """The session's worst stalls, for the terminal summary ("" when no kernel test ran)."""
    if not SEEN:
        return ""
    worst = sorted(SEEN, key=lambda row: row[1], reverse=True)[:3]
    return "kernel tier: worst stall of the test process: " + "; ".join(f"{s * 1000:.0f} ms ({t})" for t, s in worst)
