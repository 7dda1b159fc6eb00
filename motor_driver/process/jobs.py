"""Background work supervised: a job that fails in a way nobody foresaw (an exception of any
type its own code does not handle) is logged with its cause, counted per kind of job, and handed
to the caller's ``on_fail`` (which retries it with its back-off, or stops), instead of ending in
a Future nobody reads. The counts are in /diagnostics (:func:`motor_driver.diagnostics.health.jobs_health`).

Kinds (:data:`JOB_KINDS`): ``reconnect`` (a lost bus opened again), ``reconfigure`` (a drive
configured again after a reset), ``restore_enable`` (its enable again after that, where the
config restores it), ``sync_restart`` (the daemon's SYNC job set up again),
``stop_by_sdo`` (the SDO copy of a stop), ``supervisor`` (one period of the supervisor's loop),
``stop`` (a stop a node hands to a worker). A kind not in the list is counted all the same.

Owner: :class:`JobFaults` is written by the thread a job failed on, under its own lock (each
count and the newest cause, one assignment of an immutable :class:`JobFault`); anyone reads
:meth:`JobFaults.snapshot`. Its log lines go through a :class:`motor_driver.process.ratelimit.Throttle`
per kind: a job failing every period says so once every ``period_s``, with the count held back.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from motor_driver.process.ratelimit import PERIOD_S, Throttle

logger = logging.getLogger(__name__)

JOB_KINDS = ("reconnect", "reconfigure", "restore_enable", "sync_restart", "stop_by_sdo", "supervisor", "stop")


@dataclass(frozen=True)
class JobFault:
    """How often a kind of job failed unexpectedly, and the newest failure: where and why."""

    count: int
    where: str
    cause: str
    at: float


def brief_error(err: BaseException) -> str:
    """An error in one line: its own text up to any traceback python-can put in it, and the
    cause it was raised from (``ConnectionResetError: [Errno 104] Connection reset by peer``)."""
    text = str(err).split("Traceback (most recent call last)")[0].strip().splitlines()
    line = text[0].strip() if text else type(err).__name__
    cause = err.__cause__ or err.__context__
    if cause is not None and str(cause) and str(cause) not in line:
        line = f"{line.rstrip(':')}: {type(cause).__name__}: {brief_error(cause)}"
    return line


def cause_of(err: BaseException) -> str:
    """An unexpected exception in one line, with its type: ``Boom: the text``."""
    return f"{type(err).__name__}: {brief_error(err)}"


class JobFaults:
    """The unexpected failures of a driver's background jobs, per kind (thread-safe)."""

    def __init__(self, period_s: float = PERIOD_S, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._faults: dict[str, JobFault] = {}
        self._throttle = Throttle(period_s, clock)
        self._clock = clock

    def failed(self, kind: str, where: str, err: BaseException) -> JobFault:
        """Count ``err`` against ``kind`` and log it (with its traceback, at a bounded rate)."""
        cause = cause_of(err)
        with self._lock:
            count = self._faults[kind].count + 1 if kind in self._faults else 1
            fault = self._faults[kind] = JobFault(count, where, cause, self._clock())
        passed = self._throttle.admit(kind)
        if passed is not None:
            held, since = passed
            logger.error("%s: %s failed unexpectedly (%s); %d time(s) so far%s", where, kind, cause, count,
                         f", {held} more in the last {since:.0f} s" if held else "", exc_info=err)
        return fault

    def snapshot(self) -> dict[str, JobFault]:
        with self._lock:
            return dict(self._faults)

    def supervised(self, kind: str, where: str, job: Callable[[], object],
                   on_fail: Callable[[BaseException], None] | None = None) -> Callable[[], None]:
        """``job`` as a worker's job that never leaves an exception in its Future: an unexpected
        one is counted and logged here, then ``on_fail`` decides (a retry, a stop)."""

        def run() -> None:
            try:
                job()
            except Exception as err:
                self.failed(kind, where, err)
                if on_fail is not None:
                    try:
                        on_fail(err)
                    except Exception as again:  # the recovery itself failed: said, never silent
                        logger.exception("%s: recovery after a failed %s failed too: %s", where, kind,
                                         cause_of(again))

        return run
