"""How the drive watches the host (heartbeat consumer or node guarding), how the driver's
supervisor watches the drive (its heartbeat, another master on the bus), and what the driver
does about a drive it stops hearing: it tells it to stop.

Owners: boot (the bus's worker, drive not booted) writes ``host_watch``, ``host_watch_problem``
and ``remote_frames`` through :meth:`configure`; the supervisor thread owns ``_next_guard``,
``foreign_master`` and the lost drive's stop bookkeeping (``_lost_since``, ``_next_stop``,
``lost_stops``), and calls :meth:`guard`, :meth:`check_heartbeat`, :meth:`set_foreign_master`
and :meth:`mark_lost`, none of which waits; blocking SDO work (the SDO copy of a stop) is
handed back to the caller to run on the bus's worker.

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

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import ON_HOST_LOSS, DriveConfig
from can_config.eds import has_object
from can_config.errors import MotorError, SdoError
from can_config.objects import OD, FunctionCode, NmtCommand, sdo_abort_text
from motor_driver.cia402 import Command, State
from motor_driver.drive.channel import CommandChannel
from motor_driver.drive.constants import NO_HOST_WATCH, QUICK_STOP_THEN_DISABLE, VALUE_RANGE_ABORTS
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.state import DriveCache
from motor_driver.safety import guard_settings

logger = logging.getLogger(__name__)


def host_consumer_entry(host_node_id: int, timeout_s: float) -> int:
    """A 0x1016 sub-entry: watch ``host_node_id``'s heartbeat with this consumer time (CiA 301)."""
    return (host_node_id & 0x7F) << 16 | max(1, min(0xFFFF, int(round(timeout_s * 1000))))


class HostWatch:
    """The drive's watch of the host, and the supervisor's of the drive."""

    def __init__(self, config: DriveConfig, od: ObjectDictionary, network: canopen.Network, cache: DriveCache,
                 channel: CommandChannel, sdo: SdoPort, host_node_id: int) -> None:
        self.config = config
        self.name, self.node_id = config.name, config.node_id
        self._od = od
        self._network = network
        self._cache = cache
        self._channel = channel
        self._sdo = sdo
        self.host_node_id = host_node_id
        #: the bus carries remote frames (a kernel bus; socketcand's rawmode cannot)
        self.remote_frames = False
        #: how the drive watches the host (after boot), or None: nothing stops it if the host dies
        self.host_watch: str | None = None
        self.host_watch_problem: str | None = None
        self.guardable = False  # node guarding chosen and possible on this bus (boot's)
        self._next_guard = 0.0
        self.foreign_master = ""
        self._lost_since = 0.0  # supervisor: when the drive was declared lost (0: it is not)
        self._next_stop = 0.0
        self.lost_stops = 0  # stop frames sent to lost drives

    def set_remote_frames(self, carried: bool) -> None:
        self.remote_frames = carried

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
        if self.host_watch is None and cfg.allow_no_host_watch:
            logger.warning("node %d (%s): %s; allowed by allow_no_host_watch: if this process dies, hangs or"
                           " loses power while the drive is enabled, NOTHING stops it", self.node_id, self.name,
                           self.host_watch_problem)
        elif self.host_watch is None:
            logger.warning("node %d (%s): %s; it will not be enabled (allow_no_host_watch: true overrides)",
                           self.node_id, self.name, self.host_watch_problem)

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
        ``auto`` takes the heartbeat consumer where the drive has one."""
        mode = self.config.host_watch
        if mode == "auto":
            guardable = has_object(self._od, OD.GUARD_TIME) and has_object(self._od, OD.LIFE_TIME_FACTOR)
            mode = "guarding" if guardable and not has_object(self._od, OD.CONSUMER_HEARTBEAT_TIME, 1) else "heartbeat"
        return mode

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
        self._next_guard = 0.0
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
    def guard(self, now: float) -> None:
        """Supervisor: the guard (a remote frame on 0x700 + id) when one is due. Its answer is the
        drive's 'heartbeat': a missing one makes the drive lost after heartbeat_timeout_ms. A lost
        drive is guarded no more: its life guarding then trips too."""
        if not self._cache.guarding or now < self._next_guard or self._lost_since:
            return
        self._next_guard = max(self._next_guard + self.config.heartbeat_period_s, now)
        try:
            self._network.send_message(FunctionCode.HEARTBEAT + self.node_id, b"", remote=True)
        except (can.CanError, OSError, RuntimeError) as err:  # a lost bus is the supervisor's to find
            logger.debug("node %d: guard not sent: %s", self.node_id, err)

    def check_heartbeat(self, now: float) -> Callable[[], None] | None:
        """Supervisor: declare the drive lost when its heartbeat is overdue, and tell it to stop
        (again every heartbeat period while it stays lost). Returns the SDO copy of the stop for
        the bus's worker when the drive was declared lost just now."""
        cache = self._cache
        if self._lost_since and not cache.lost:
            logger.warning("node %d (%s): heard again after %.1f s lost; it was told to stop %d times; enable it"
                           " again to drive it", self.node_id, self.name, now - self._lost_since, self.lost_stops)
            self._lost_since = 0.0
        if cache.booted and not cache.lost and cache.last_heartbeat and \
                now - cache.last_heartbeat > self.config.heartbeat_timeout_s:
            cache.mark_lost()
            self._lost_since = now
            logger.error("node %d (%s): heartbeat lost (none for %.0f ms, consumer time %.0f ms); telling it to stop"
                         " (quick stop by RPDO and SDO, NMT stop) until it is heard again", self.node_id, self.name,
                         (now - cache.last_heartbeat) * 1000, self.config.heartbeat_timeout_s * 1000)
            self._stop_lost(now)
            return self.quick_stop_lost_by_sdo
        if self._lost_since and cache.booted and now >= self._next_stop:
            self._stop_lost(now)
        return None

    def _stop_lost(self, now: float) -> None:
        """The stops that need no answer: the quick-stop controlword on the RPDO, then NMT stop."""
        self._next_stop = now + self.config.heartbeat_period_s
        self.lost_stops += 1
        try:
            self._channel.stop(Command.QUICK_STOP, "the drive was lost")
            self._network.send_message(0x000, bytes([NmtCommand.STOP, self.node_id]))
        except (MotorError, can.CanError, OSError, RuntimeError) as err:
            logger.debug("node %d: stop of a lost drive not sent: %s", self.node_id, err)

    def quick_stop_lost_by_sdo(self) -> None:
        """Bus worker: the quick stop as an SDO write as well (a drive whose PDOs are off still
        takes it); no answer is needed for it to act, a timeout here is expected."""
        try:
            self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.info("%s: quick stop by SDO to the lost drive: %s", self.name, err)

    def set_foreign_master(self, evidence: str) -> bool:
        """Supervisor: another master drives this drive ("" once it has been gone long enough).
        A drive this driver had enabled gets a quick stop (nothing else of this driver's goes to
        it meanwhile); when it clears, the drive is configured again (not enabled): the other
        master may have reset or re-mapped it. True when the quick stop went out as an RPDO: the
        caller sends it by SDO as well (:meth:`quick_stop_by_sdo`, on the bus worker), since a
        drive the other master put in PRE-OPERATIONAL ignores PDOs and would keep moving."""
        stopped = False
        if evidence and not self.foreign_master:
            logger.error("%s (node %d): another master on the bus: %s; commands are refused", self.name,
                         self.node_id, evidence)
            if self._channel.was_enabled and self._cache.state == State.OPERATION_ENABLED:
                # two masters on one drive is no state to keep moving in: the last thing this
                # driver sends it is a quick stop (the watchdog no longer runs for it)
                stopped = True
                try:
                    self._channel.stop(Command.QUICK_STOP, "another master on the bus")
                except MotorError as err:
                    logger.error("%s: quick stop on losing control not sent: %s", self.name, err)
            self._channel.forget_commanded()
        elif not evidence and self.foreign_master:
            logger.warning("%s (node %d): the other master is gone; configuring the drive again (not enabled)",
                           self.name, self.node_id)
            self._cache.mark_unbooted()
            self._cache.rebooted.set()
        self.foreign_master = evidence
        return stopped

    def quick_stop_by_sdo(self, since: float) -> None:
        """Bus worker: the quick stop of losing control once more, as an SDO write of the
        controlword, where the RPDO cannot have reached the drive: its first heartbeat after
        ``since`` (when the other master was noticed) says PRE-OPERATIONAL. Not to a drive that
        reset meanwhile (a boot-up: the reset disabled it) or is still OPERATIONAL (it took the
        RPDO): the other master's SDO transfers use the same channel, and a needless write of
        ours breaks them."""
        cache = self._cache
        deadline = since + self.config.heartbeat_timeout_s  # a heartbeat by then, or the drive is lost
        cache.wait_until(lambda: cache.last_heartbeat > since, max(0.0, deadline - time.monotonic()))
        if cache.reset_since_operational() or cache.reported_nmt != "PRE_OPERATIONAL":
            return
        try:
            self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.error("%s: quick stop by SDO on losing control failed: %s", self.name, err)

    def mark_lost(self) -> None:
        """Supervisor: the drive's bus is gone; nothing is commanded until it is booted again."""
        self._cache.mark_lost(booted=False)
        self._channel.forget_commanded()
        self._lost_since = 0.0

    def lost_while_closing(self) -> None:
        """The driver shuts down with the drive lost: one last quick stop and NMT stop, unanswered."""
        if self._cache.lost:
            self._stop_lost(time.monotonic())
