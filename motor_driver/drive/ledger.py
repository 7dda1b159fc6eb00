"""The ledger of the supervisor's judgements: what the driver has judged of each drive and each bus (lost, booted, to be
configured again, another master, the stops of a lost drive, the watchdog's and the guard's
times; a bus's reconnect and back-off, its host heartbeat), and the NMT commands it sent.

Owner: the :class:`motor_driver.runtime.supervisor.Supervisor`, on its thread, alone writes a
:class:`DriveRecord` and a :class:`BusRecord` (tests/test_ownership.py checks that no other
module assigns their fields). Every other thread reads them and hands the supervisor what it
found instead: the receive thread posts each heartbeat that may change a judgement
(:class:`Heard`, without waiting), a boot or a reconnect on the bus's worker reports its result
(:class:`Booting`, :class:`Booted`, :class:`BootRestarted`, :class:`RebootFailed`, :class:`RestoreFailed`, :class:`BusBack`,
:class:`BusDown`) and waits until the supervisor has applied it.

:class:`NmtLedger` is the one way an NMT command leaves for a drive: it sends and remembers the
command and when, so that a state the driver caused (its own NMT stop of a lost drive, taking
effect after a heartbeat sent just before it) is never taken for another master's.

It lives with the drive's parts because they read it and post to it (through :class:`SupervisorPort`);
the supervisor (:mod:`motor_driver.runtime`), the layer above, is its one writer.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

from can_config.objects import NmtCommand, NmtState

#: The state each NMT command puts a node in (CiA 301).
NMT_TARGET = {NmtCommand.START: NmtState.OPERATIONAL, NmtCommand.STOP: NmtState.STOPPED,
              NmtCommand.ENTER_PREOPERATIONAL: NmtState.PRE_OPERATIONAL,
              NmtCommand.RESET_NODE: NmtState.BOOTUP, NmtCommand.RESET_COMMUNICATION: NmtState.BOOTUP}


class DriveRecord:
    """The supervisor's judgement of one drive (read by anyone, written by the supervisor)."""

    def __init__(self) -> None:
        self.lost = False
        self.booted = False
        self.booted_at = 0.0  # when the last boot ended: a heartbeat heard before it is history
        #: the drive's EMCY 0x8130 count (DriveCache.host_loss_emcys) up to which they are spent: set
        #: as its boot ends (older ones explain nothing) and as one explains an NMT change of the drive's
        self.host_loss_emcys_spent = 0
        #: configure it again (a boot-up, a stop it was told, the other master gone, a failed try)
        self.reboot_wanted = False
        self.reboot_at = 0.0  # not before this (a failed re-configuration waits)
        self.reboot_job: Future[None] | None = None
        self.foreign_master = ""  # evidence that another master drives it: commands are refused
        #: the newest NMT state change nobody here commanded: (when, what)
        self.behind_back: tuple[float, str] = (0.0, "")
        self.lost_since = 0.0  # when its heartbeat was declared lost (0: it is not)
        self.next_stop = 0.0  # the next stop told to it while lost
        self.lost_stops = 0  # stop frames sent to it while lost
        self.stop_pending = False  # the channel was busy: the quick stop goes next period
        #: its heartbeat overdue by the clock while the bus's receive thread had not read that far
        #: (the driver's own lateness, not the drive's silence): so now, and how often it began
        self.read_behind = False
        self.read_behind_episodes = 0
        self.forget_pending = False  # the channel was busy: commanded state forgotten next period
        self.next_guard = 0.0  # node guarding: the next guard
        self.host_loss_seen = 0  # host-loss stops already reported
        #: the drive's boot-ups (DriveCache.bootups) its last configuration accounted for: one
        #: numbered above is a reset since, never history
        self.bootups_confirmed = 0
        self.boot_restarts = 0  # configurations started again: it reset in one, or did not hold what was written
        self.boot_restart_why = ""  # ... the newest reason
        self.reconfigure_failures = 0  # re-configurations that failed (each retried)
        self.reconfigure_error = ""  # ... the newest one's error


class BusRecord:
    """The supervisor's judgement of one bus (read by anyone, written by the supervisor)."""

    def __init__(self) -> None:
        self.lost = False
        self.job: Future[None] | None = None  # the bus's reconnect or SYNC restart, while it runs
        self.backoff_s = 0.0
        self.next_attempt = 0.0
        self.last_beat = 0.0
        self.next_beat = 0.0
        self.last_frames = 0
        self.last_rx = 0.0
        self.reported_error = 0.0  # the newest error frame reported
        self.reported_losing = 0.0
        self.send_failing: tuple[float, str] | None = None  # since when host heartbeats fail, and why
        self.reported_queue_full = 0  # ENOBUFS refusals already said
        self.link_down_said = False  # a kernel link's going down said, until it is back

    def job_done(self) -> bool:
        return self.job is None or self.job.done()


# ---------------------------------------------------------------------- what others hand it
@dataclass(frozen=True)
class Heard:
    """The receive thread: a heartbeat (or guard answer) of ``drive`` in NMT ``state``;
    ``was`` is the state the drive said before it; ``bootups``: the drive's boot-ups heard so far,
    this one included."""

    drive: str
    state: int
    was: str
    at: float
    bootups: int = 0


@dataclass(frozen=True)
class Booting:
    """A boot of ``drive`` begins: it is not booted until it reports :class:`Booted`."""

    drive: str


@dataclass(frozen=True)
class Booted:
    """A boot of ``drive`` ended with NMT start, its configuration confirmed with the drive's
    boot-ups (:attr:`motor_driver.drive.received.state.DriveCache.bootups`) at ``bootups``: a boot-up heard
    beyond them is a reset since."""

    drive: str
    bootups: int = 0


@dataclass(frozen=True)
class BootRestarted:
    """A boot of ``drive`` starts its configuration again (``why``: it reset meanwhile, or it
    does not hold what was written)."""

    drive: str
    why: str


@dataclass(frozen=True)
class RebootFailed:
    """A re-configuration of ``drive`` failed (``error``): tried again after ``retry_s``."""

    drive: str
    retry_s: float
    error: str = ""


@dataclass(frozen=True)
class RestoreFailed:
    """``drive``, configured again after a reset, was not enabled again: its enable failed in a
    way nobody foresaw (``error``). It stays configured and disabled; counted as a job's failure."""

    drive: str
    error: BaseException


@dataclass(frozen=True)
class BusBack:
    """The bus's worker: ``bus`` reconnected and its drives booted."""

    bus: str


@dataclass(frozen=True)
class BusDown:
    """The bus's worker: ``bus`` could not be (re)opened (``why``; ``link_down``: the kernel's
    interface is not ready, and why); try again after ``retry_s`` (None: the back-off doubles)."""

    bus: str
    retry_s: float | None
    link_down: str
    why: str


Event = Heard | Booting | Booted | BootRestarted | RebootFailed | RestoreFailed | BusBack | BusDown


class SupervisorPort:
    """How a part hands the supervisor what it found: ``post`` (never waits: the receive thread)
    and ``report`` (returns once the supervisor applied it: a worker, a caller's thread); ``wake``
    (never waits): something it watches changed (a velocity or torque command went live, another
    master's sign), so its next period comes now rather than at the quiet supervisor's next due
    time (:meth:`motor_driver.runtime.supervisor.Supervisor.wait_s`)."""

    def __init__(self, post: Callable[[Event], None], report: Callable[[Event], None],
                 wake: Callable[[], None] = lambda: None) -> None:
        self.post = post
        self.report = report
        self.wake = wake


class NmtLedger:
    """The NMT commands sent to one node: each leaves through :meth:`send`, which remembers the
    command and when, before the frame goes (one assignment of an immutable pair: no lock is
    held while the bus may make a sender wait; of two senders the newest is kept)."""

    def __init__(self, node_id: int, send: Callable[[int, bytes], None]) -> None:
        self.node_id = node_id
        self._send = send
        self._last: tuple[NmtCommand | None, float] = (None, 0.0)

    def send(self, command: NmtCommand) -> None:
        """Send ``command`` to the node; errors are the caller's."""
        self._last = (command, time.monotonic())
        self._send(0x000, bytes([command, self.node_id]))

    @property
    def last(self) -> tuple[NmtCommand | None, float]:
        return self._last

    def explains(self, state: int) -> bool:
        """The newest NMT command this driver sent the node asks for ``state``: a change this
        driver caused, however late it is heard (a starved host hears it seconds later). Another
        master's NMT command to the same state shows as its NMT frame (the bus listener), not here."""
        command, _ = self._last
        return command is not None and NMT_TARGET.get(command) == state

    def in_flight(self, state: int, at: float, within_s: float) -> bool:
        """A heartbeat in another state than the newest command asks for, heard within
        ``within_s`` of sending it: sent before the drive obeyed (on its way, or queued on a
        loaded host), no change of the drive's."""
        command, when = self._last
        return command is not None and NMT_TARGET.get(command) != state and 0.0 <= at - when <= within_s
