"""Commands that must wait for their drive, taken off the hot thread.

The hot executor's one thread carries every joint's commands: the per-joint topics,
/joint_commands and the drive system's tick. A command that needs its drive's answer before it
can go out (a mode switch: the first set-point of a stream, the first velocity after a position
move; a target the drive takes only by SDO) would hold every other joint's commands for its round
trips there: the six wheels' first streamed commands would hold a 500 Hz arm about 60 ms, and the
arm's next set-point, beyond its step limit by then, would be refused, and so would the rest of
its ramp (docs/performance.md).

:meth:`Handoff.send` sends a command at once where it can (``at_once=True``: the core refuses
with :class:`CommandWouldWait` before anything is sent otherwise) and hands the others to a
worker thread. The joint's commands that come while one is with the worker follow it there,
in order; only the newest is kept (set-points: the newest is the one that matters, as the
keep-last-1 subscriptions already do), so no backlog forms behind a slow drive.

Owner: the lock below guards which joints have a command with the worker and each one's newest
waiting command; nothing else here is shared. The workers are made when first needed (none
exists while every command goes at once), at most one per joint at a time.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Collection
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

from can_config.errors import CommandRejected, CommandWouldWait

logger = logging.getLogger(__name__)


class Call(NamedTuple):
    """A command for the worker: ``command(value)``, named by ``what`` (``{!r}`` for the value),
    and what to do with its failure (``failed(joint, what, value, error)``)."""

    command: Callable[..., object]
    value: float
    what: str
    failed: Callable[[str, str, float, Exception], None]


class Handoff:
    """Sends each joint's commands at once, or on a worker when they must wait for the drive."""

    def __init__(self, joints: Collection[str]) -> None:
        self._pool = ThreadPoolExecutor(max_workers=max(1, len(joints)), thread_name_prefix="rovercan-handoff")
        self._lock = threading.Lock()
        self._with_worker: set[str] = set()
        self._newest: dict[str, Call] = {}
        self._closed = False

    def send(self, joint: str, command: Callable[..., object], value: float, what: str,
             failed: Callable[[str, str, float, Exception], None]) -> bool:
        """``command(value, at_once=True)`` now (True); a refusal raises here, as from the command.
        When it would wait, or a command of ``joint`` is still with the worker, the command goes to
        the worker (False), and a failure there to ``failed(joint, what, value, error)``."""
        with self._lock:  # the command at once inside it: the worker never overtakes it
            if self._closed:
                raise CommandRejected(f"{joint}: the node is shutting down; no command is taken. Nothing was sent.")
            if joint in self._with_worker:
                self._newest[joint] = Call(command, value, what, failed)
                return False
            try:
                command(value, at_once=True)
                return True
            except CommandWouldWait:
                pass
            try:
                self._pool.submit(self._work, joint, Call(command, value, what, failed))
            except RuntimeError as err:  # no thread to be had (the interpreter is going): said, not lost
                raise CommandRejected(f"{joint}: no worker to send a command that waits for the drive ({err});"
                                      " nothing was sent") from err
            self._with_worker.add(joint)  # under the lock: the worker cannot be done before this
            return False

    def busy(self, joint: str) -> bool:
        """A command of ``joint`` is with the worker (or waits behind it)."""
        with self._lock:
            return joint in self._with_worker

    def waiting(self, joint: str) -> float | None:
        """The value of ``joint``'s newest command waiting behind the one with the worker, if any."""
        with self._lock:
            call = self._newest.get(joint)
            return None if call is None else call.value

    def _work(self, joint: str, call: Call) -> None:
        freed = False
        try:
            while True:
                try:
                    call.command(call.value)
                except Exception as err:  # every failure is said: never lost on a worker
                    _say(call, joint, err)
                with self._lock:
                    following = None if self._closed else self._newest.pop(joint, None)
                    if following is None:  # in the same hold as the look: nothing left behind
                        self._free(joint)
                        freed = True
                        return
                call = following
        finally:
            if not freed:  # something escaped even _say: the joint's next command is taken all the same
                with self._lock:
                    self._free(joint)

    def _free(self, joint: str) -> None:
        self._with_worker.discard(joint)
        self._newest.pop(joint, None)

    def close(self) -> None:
        """No command is taken from here on, nor one waiting behind a worker; the one with a
        worker ends as the driver's stop ends it (closed first: nothing moves)."""
        with self._lock:
            self._closed = True
            self._newest.clear()
        self._pool.shutdown(wait=False, cancel_futures=True)


def _say(call: Call, joint: str, err: Exception) -> None:
    try:
        call.failed(joint, call.what, call.value, err)
    except Exception:  # a refusal that could not be said is logged here
        logger.exception("%s: %s refused (%s), and saying so failed", joint, call.what.format(call.value), err)


__all__ = ["Call", "Handoff"]
