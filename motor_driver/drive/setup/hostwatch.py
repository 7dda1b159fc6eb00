"""How the drive watches the host (heartbeat consumer or node guarding), and the frames the
driver's supervisor sends a drive it stops hearing or loses to another master: it tells it to stop.

Owners: boot (the bus's worker, drive not booted) writes ``host_watch``, ``host_watch_problem``,
``guardable`` and when the drive was told to watch (``_told_at``) through :meth:`choose` and
:meth:`configure`; the driver sets ``remote_frames`` once, before the first boot. The count of host
heartbeats sent on the drive's bus is the supervisor's (its bus handle, read through
``host_beats``); the count of guard answers is the receive thread's (the cache). This object
keeps none of the ledger's records: lost, another master and the stop bookkeeping are the supervisor's
(:class:`motor_driver.drive.ledger.DriveRecord`, read here), which decides when :meth:`send_guard`,
:meth:`stop_lost` and :meth:`lose_control` run, on its thread; none of them waits (the
channel's lock is tried, not waited for). Blocking SDO work (the SDO copy of a stop) runs on the
bus's worker. Every NMT command goes through the drive's :class:`motor_driver.drive.ledger.NmtLedger`,
so that a state it causes is known as this driver's.

A drive declared lost may still be turning (a broken transmit line, a hung CAN task): the
driver tells it to stop by every means that needs no answer from it, the quick-stop
controlword on its RPDO (through the command channel) and NMT stop (CiA 402: entering NMT
stopped is an abort-connection event, 0x6007), and by SDO on the bus's worker; it repeats the
RPDO and NMT stop every heartbeat period until the drive is heard again or the bus is gone.
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import ON_HOST_LOSS, DriveConfig
from can_config.eds import has_object
from can_config.errors import MotorError, SdoError
from can_config.objects import OD, FunctionCode, NmtCommand, sdo_abort_text
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.drive.constants import (
    NO_HOST_WATCH,
    QUICK_STOP_THEN_DISABLE,
    VALUE_RANGE_ABORTS,
    WATCH_START_BEATS,
    WATCH_START_PERIODS,
)
from motor_driver.drive.ledger import DriveRecord, NmtLedger
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.sdo import SdoPort
from motor_driver.protocol.cia402 import Command, State
from motor_driver.protocol.safety import guard_settings, watch_mode

logger = logging.getLogger(__name__)


def host_consumer_entry(host_node_id: int, timeout_s: float) -> int:
    """A 0x1016 sub-entry: watch ``host_node_id``'s heartbeat with this consumer time (CiA 301)."""
    return (host_node_id & 0x7F) << 16 | max(1, min(0xFFFF, int(round(timeout_s * 1000))))


@dataclass(frozen=True)
class Host:
    """The host as a drive watches it: its node id, its heartbeat period, and how many of its
    heartbeats have gone out on the drive's bus so far (the supervisor's count)."""

    node_id: int
    heartbeat_s: float
    beats: Callable[[], int]


class HostWatch:
    """The drive's watch of the host, and the supervisor's of the drive."""

    def __init__(self, config: DriveConfig, od: ObjectDictionary, cache: DriveCache, channel: CommandChannel,
                 sdo: SdoPort, network: canopen.Network, host: Host, *, record: DriveRecord, nmt: NmtLedger) -> None:
        self.config, self._od, self._cache, self._channel, self._sdo = config, od, cache, channel, sdo
        self.name, self.node_id = config.name, config.node_id
        self._network = network
        self.host_node_id = host.node_id
        self._record = record  # the supervisor's: read only
        self.nmt_ledger = nmt
        #: the bus carries remote frames (a kernel bus; socketcand's rawmode cannot)
        self.remote_frames = False
        #: how the drive watches the host (after boot), or None: nothing stops it if the host dies
        self.host_watch: str | None = None
        self.host_watch_problem: str | None = None
        self.guardable = False  # node guarding chosen and possible on this bus (boot's)
        self._host_beats = host.beats
        self._host_heartbeat_s = host.heartbeat_s
        #: boot's: that count, and the cache's count of guard answers, once the drive was told to watch the host
        self._told_at: tuple[int, int] = (0, 0)

    def set_remote_frames(self, carried: bool) -> None:
        self.remote_frames = carried

    @property
    def foreign_master(self) -> str:
        """Evidence that another master drives it (the supervisor's judgement): commands are refused."""
        return self._record.foreign_master

    # ------------------------------------------------------------------ boot's
    def choose(self) -> bool:
        """Boot: whether the drive will be guarded (then it produces no heartbeat, CiA 301)."""
        self.guardable = self.watch_mode() == "guarding" and self.remote_frames
        self._cache.set_guarding(False)
        return self.guardable

    def configure(self) -> None:
        """Tell the drive to stop by itself when the host falls silent (CiA 301 0x1016, CiA 402
        0x6007 and 0x605A): the one stop that holds when this process is killed, hung or unpowered."""
        cfg = self.config
        self.host_watch = None
        self.host_watch_problem = f"{NO_HOST_WATCH}: the drive has no consumer heartbeat time (0x1016)"
        if has_object(self._od, OD.QUICK_STOP_OPTION):
            self._sdo.write_typed(OD.QUICK_STOP_OPTION, 0, QUICK_STOP_THEN_DISABLE)
        if has_object(self._od, OD.ABORT_CONNECTION_OPTION):
            self._sdo.write_typed(OD.ABORT_CONNECTION_OPTION, 0, ON_HOST_LOSS[cfg.on_host_loss])
        if self.watch_mode() == "guarding":
            self._configure_guarding()
        elif has_object(self._od, OD.CONSUMER_HEARTBEAT_TIME, 1) and cfg.host_timeout_s is not None:
            self._configure_consumer(cfg.host_timeout_s)
        self._told_at = (self._host_beats(), self._cache.guard_answers)
        if self.host_watch is None:
            self._say_no_watch()

    def _say_no_watch(self) -> None:
        """The drive watches nothing (``host_watch_problem`` says why): armed only if the config allows it."""
        if self.config.allow_no_host_watch:
            logger.warning("node %d (%s): %s; allowed by allow_no_host_watch: if this process dies, hangs or"
                           " loses power while the drive is enabled, NOTHING stops it", self.node_id, self.name,
                           self.host_watch_problem)
        else:
            logger.warning("node %d (%s): %s; it will not be enabled (allow_no_host_watch: true overrides)",
                           self.node_id, self.name, self.host_watch_problem)

    def read_back_wrong(self, why: str) -> None:
        """Boot's safety check: the watch written did not hold (read back otherwise): the drive
        counts as not watching the host, and enable is refused as for one that cannot (a drive
        already without a watch keeps the reason it has)."""
        if self.host_watch is None:
            return
        self.host_watch, self.host_watch_problem = None, why
        self._say_no_watch()

    def not_watching_yet(self) -> str:
        """Why the drive told to watch the host is not watching it yet, and what helps ('' once it
        is). CiA 301 starts a heartbeat consumer at the first heartbeat it hears after its entry
        is written, life guarding at the first guard: a drive enabled before that keeps moving if
        the host dies then. Counted from when the drive answered the last write: the second host
        heartbeat sent since (one thread sends them, each counted once sent: the first may have
        been on its way), or the second guard answer taken since (the first may answer a guard
        sent before)."""
        beats, answers = self._told_at
        if self._cache.guarding:
            got = self._cache.guard_answers - answers
            if got >= WATCH_START_BEATS:
                return ""
            guard_ms, _ = guard_settings(self.config)
            return (f"{got} of the {WATCH_START_BEATS} guard answers it needs since it was told to (guard time"
                    f" {guard_ms} ms): does it answer node guarding on this bus? See its heartbeat and guard"
                    " errors in the diagnostics")
        got = self._host_beats() - beats
        if got >= WATCH_START_BEATS:
            return ""
        return (f"{got} of the {WATCH_START_BEATS} host heartbeats (node {self.host_node_id}, every"
                f" {self._host_heartbeat_s * 1000:g} ms) it needs have gone out since it was told to: this"
                " process is starved or cannot send on the bus; see the bus's diagnostics")

    def start_bound_s(self) -> float:
        """How long the drive's watch may take to start: WATCH_START_PERIODS of what it waits for."""
        period = guard_settings(self.config)[0] / 1000 if self._cache.guarding else self._host_heartbeat_s
        return WATCH_START_PERIODS * period

    def _reaction(self) -> str:
        return self.config.on_host_loss if has_object(self._od, OD.ABORT_CONNECTION_OPTION) else \
            "the drive's own reaction (no 0x6007 to choose it)"

    def _configure_consumer(self, timeout_s: float) -> None:
        entry = host_consumer_entry(self.host_node_id, timeout_s)
        try:
            self._sdo.write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", entry))
        except SdoError as err:
            if err.abort_code not in VALUE_RANGE_ABORTS:
                raise
            self.host_watch_problem = (f"{NO_HOST_WATCH}: node {self.node_id} refuses 0x1016:1 = 0x{entry:08X}"
                                       f" (watch node {self.host_node_id}): {sdo_abort_text(err.abort_code or 0)}")
            return
        self.host_watch = (f"heartbeat consumer 0x1016:1 watches node {self.host_node_id}"
                           f" ({timeout_s * 1000:.0f} ms), then {self._reaction()}")
        self.host_watch_problem = None

    def watch_mode(self) -> str:
        """How this drive watches the host: ``heartbeat`` (0x1016) or ``guarding`` (0x100C/0x100D);
        ``auto`` takes the heartbeat consumer where the drive has one (:func:`watch_mode`)."""
        return watch_mode(self.config, self._od)

    def _configure_guarding(self) -> None:
        """Node guarding: guard time and life time factor written; the supervisor guards the drive
        from then on (never a kernel timer: a hung process must fall silent)."""
        if not (has_object(self._od, OD.GUARD_TIME) and has_object(self._od, OD.LIFE_TIME_FACTOR)):
            self.host_watch_problem = f"{NO_HOST_WATCH}: host_watch: guarding, but the drive has no 0x100C/0x100D"
            return
        if not self.remote_frames:
            self.host_watch_problem = (f"{NO_HOST_WATCH}: node guarding needs remote frames, which this bus cannot"
                                       " carry (socketcand's rawmode has none); use a kernel bus (socketcan)")
            return
        guard_ms, factor = guard_settings(self.config)
        self._sdo.write_typed(OD.GUARD_TIME, 0, guard_ms)
        self._sdo.write_typed(OD.LIFE_TIME_FACTOR, 0, factor)
        self.host_watch = (f"node guarding every {guard_ms} ms, life time {guard_ms * factor} ms (0x100C x 0x100D),"
                           f" then {self._reaction()}")
        self.host_watch_problem = None
        self._cache.set_guarding(True)

    def release_host_watch(self) -> None:
        """Clean shutdown of a disabled drive: stop watching the host, so that its last heartbeat
        raises no EMCY. Kept on a drive that is still enabled (the watch is then its only stop)."""
        if self.host_watch is None or self._cache.lost or self._cache.state == State.OPERATION_ENABLED:
            return
        if self._cache.guarding:
            self._sdo.write_typed(OD.LIFE_TIME_FACTOR, 0, 0)  # 0: life guarding off
            self._cache.set_guarding(False)
        else:
            self._sdo.write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0))
        self.host_watch = None

    # ------------------------------------------------------------------ the supervisor's
    def send_guard(self) -> None:
        """Supervisor, when a guard is due: a remote frame on 0x700 + id. Its answer is the
        drive's 'heartbeat': a missing one makes the drive lost after heartbeat_timeout_ms."""
        try:
            self._network.send_message(FunctionCode.HEARTBEAT + self.node_id, b"", remote=True)
        except (can.CanError, OSError, RuntimeError) as err:  # a lost bus is the supervisor's to find
            logger.debug("node %d: guard not sent: %s", self.node_id, err)

    def stop_lost(self) -> bool:
        """Supervisor: the stops that need no answer, the quick-stop controlword on the RPDO, then
        NMT stop. False when the channel was busy (its lock is tried, never waited for): the RPDO
        goes at the caller's next period; the NMT stop went."""
        sent = False
        try:
            sent = self._channel.stop(Command.QUICK_STOP, "the drive was lost", timeout_s=0.0)
        except (MotorError, can.CanError, OSError, RuntimeError) as err:
            logger.debug("node %d: stop of a lost drive not sent: %s", self.node_id, err)
            sent = True  # tried: the bus is the trouble, not the lock
        try:
            self.nmt_ledger.send(NmtCommand.STOP)
        except (can.CanError, OSError, RuntimeError) as err:
            logger.debug("node %d: NMT stop of a lost drive not sent: %s", self.node_id, err)
        return sent

    def quick_stop_lost_by_sdo(self) -> None:
        """Bus worker: the quick stop as an SDO write as well (a drive whose PDOs are off still
        takes it); no answer is needed for it to act, a timeout here is expected."""
        try:
            self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.info("%s: quick stop by SDO to the lost drive: %s", self.name, err)

    def lose_control(self, evidence: str) -> bool | None:
        """Supervisor: another master drives this drive. A drive this driver had enabled gets a
        quick stop (nothing else of this driver's goes to it meanwhile). True when the quick stop
        went out as an RPDO: the caller sends it by SDO as well (:meth:`quick_stop_by_sdo`, on the
        bus worker), since a drive the other master put in PRE-OPERATIONAL ignores PDOs and would
        keep moving. None when the channel was busy (nothing done: the caller tries again)."""
        stopping = self._channel.was_enabled and self._cache.state == State.OPERATION_ENABLED
        if stopping:
            # two masters on one drive is no state to keep moving in: the last thing this
            # driver sends it is a quick stop (the watchdog no longer runs for it)
            try:
                if not self._channel.stop(Command.QUICK_STOP, "another master on the bus", timeout_s=0.0):
                    return None
            except MotorError as err:
                logger.error("%s: quick stop on losing control not sent: %s", self.name, err)
        elif not self._channel.forget_commanded(timeout_s=0.0):
            return None
        logger.error("%s (node %d): another master on the bus: %s; commands are refused", self.name,
                     self.node_id, evidence)
        return stopping

    def quick_stop_by_sdo(self, since: float) -> None:
        """Bus worker: the quick stop of losing control once more, as an SDO write of the
        controlword, where the RPDO cannot have reached the drive: its first heartbeat after
        ``since`` (when the other master was noticed) says PRE-OPERATIONAL. Not to a drive that
        reset meanwhile (a boot-up: the reset disabled it) or is still OPERATIONAL (it took the
        RPDO): the other master's SDO transfers use the same channel, and a needless write of
        ours breaks them."""
        cache = self._cache
        deadline = since + self.config.heartbeat_timeout_s  # a heartbeat by then, or the drive is lost
        # at least two heartbeat periods from now: a worker busy past the deadline still hears one
        cfg = self.config  # bounded by the consumer time: the bus's worker has other drives' stops to send
        wait_s = max(min(2.0 * cfg.heartbeat_period_s, cfg.heartbeat_timeout_s), deadline - time.monotonic())
        cache.wait_until(lambda: cache.last_heartbeat > since, wait_s)
        if cache.reset_since_operational() or cache.reported_nmt != "PRE_OPERATIONAL":
            return
        try:
            self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.error("%s: quick stop by SDO on losing control failed: %s", self.name, err)

    def lost_while_closing(self) -> None:
        """The driver shuts down with the drive lost: one last quick stop and NMT stop, unanswered."""
        if self._cache.lost:
            try:
                self._channel.stop(Command.QUICK_STOP, "the drive was lost")
                self.nmt_ledger.send(NmtCommand.STOP)
            except (MotorError, can.CanError, OSError, RuntimeError) as err:
                logger.debug("node %d: last stop of a lost drive not sent: %s", self.node_id, err)
