"""How the drive watches the host (heartbeat consumer or node guarding) and how the driver's
supervisor watches the drive (its heartbeat, another master on the bus).

Owners: boot (the bus's worker) writes ``host_watch``, ``host_watch_problem``, ``guarding``
while the drive is not booted; the supervisor thread owns ``_next_guard`` and calls
``check_heartbeat``, ``guard``, ``set_foreign_master`` and ``mark_lost``, none of which waits;
the bus's worker runs ``quick_stop_by_sdo`` (the SDO copy of the quick stop on losing control).
"""

from __future__ import annotations

import logging
import struct
import time

import can

from can_config.config import ON_HOST_LOSS
from can_config.eds import has_object
from can_config.errors import MotorError, SdoError
from can_config.objects import OD, FunctionCode, sdo_abort_text
from motor_driver.cia402 import Command, State
from motor_driver.drive.constants import NO_HOST_WATCH, QUICK_STOP_THEN_DISABLE, VALUE_RANGE_ABORTS
from motor_driver.drive.homing import Homing
from motor_driver.safety import guard_settings

logger = logging.getLogger(__name__)


def host_consumer_entry(host_node_id: int, timeout_s: float) -> int:
    """A 0x1016 sub-entry: watch ``host_node_id``'s heartbeat with this consumer time (CiA 301)."""
    return (host_node_id & 0x7F) << 16 | max(1, min(0xFFFF, int(round(timeout_s * 1000))))


class HostWatch(Homing):
    """Layer 7: how the drive watches the host, and the supervisor's view of the drive."""

    def _init_state(self) -> None:
        super()._init_state()
        #: set by the driver: the bus carries remote frames (a kernel bus; socketcand's rawmode cannot)
        self.remote_frames = False
        self._next_guard = 0.0  # supervisor only
        self._guardable = False  # boot's: node guarding chosen and possible on this bus

    def _configure_host_watch(self) -> None:
        """Tell the drive to stop by itself when the host falls silent (CiA 301 0x1016, CiA 402
        0x6007 and 0x605A): the one stop that holds when this process is killed, hung or unpowered."""
        cfg = self.config
        self.host_watch = None
        self.host_watch_problem = f"{NO_HOST_WATCH}: the drive has no consumer heartbeat time (0x1016)"
        if has_object(self.od, OD.QUICK_STOP_OPTION):
            self._write_typed(OD.QUICK_STOP_OPTION, 0, QUICK_STOP_THEN_DISABLE)
        if has_object(self.od, OD.ABORT_CONNECTION_OPTION):
            self._write_typed(OD.ABORT_CONNECTION_OPTION, 0, ON_HOST_LOSS[cfg.on_host_loss])
        if self.watch_mode() == "guarding":
            self._configure_guarding()
        elif has_object(self.od, OD.CONSUMER_HEARTBEAT_TIME, 1) and cfg.host_timeout_s is not None:
            entry = host_consumer_entry(self.host_node_id, cfg.host_timeout_s)
            try:
                self.sdo_write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", entry))
            except SdoError as err:
                if err.abort_code not in VALUE_RANGE_ABORTS:
                    raise
                self.host_watch_problem = (f"{NO_HOST_WATCH}: node {self.node_id} refuses 0x1016:1 = 0x{entry:08X}"
                                           f" (watch node {self.host_node_id}): {sdo_abort_text(err.abort_code or 0)}")
            else:
                reaction = cfg.on_host_loss if has_object(self.od, OD.ABORT_CONNECTION_OPTION) else \
                    "the drive's own reaction (no 0x6007 to choose it)"
                self.host_watch = (f"heartbeat consumer 0x1016:1 watches node {self.host_node_id}"
                                   f" ({cfg.host_timeout_s * 1000:.0f} ms), then {reaction}")
                self.host_watch_problem = None
        if self.host_watch is None and cfg.allow_no_host_watch:
            logger.warning("node %d (%s): %s; allowed by allow_no_host_watch: if this process dies, hangs or"
                           " loses power while the drive is enabled, NOTHING stops it", self.node_id, self.name,
                           self.host_watch_problem)
        elif self.host_watch is None:
            logger.warning("node %d (%s): %s; it will not be enabled (allow_no_host_watch: true overrides)",
                           self.node_id, self.name, self.host_watch_problem)

    def watch_mode(self) -> str:
        """How this drive watches the host: ``heartbeat`` (0x1016) or ``guarding`` (0x100C/0x100D);
        ``auto`` takes the heartbeat consumer where the drive has one."""
        mode = self.config.host_watch
        if mode == "auto":
            guardable = has_object(self.od, OD.GUARD_TIME) and has_object(self.od, OD.LIFE_TIME_FACTOR)
            mode = "guarding" if guardable and not has_object(self.od, OD.CONSUMER_HEARTBEAT_TIME, 1) else "heartbeat"
        return mode

    def _configure_guarding(self) -> None:
        """Node guarding: guard time and life time factor written; the supervisor guards the drive
        from then on (never a kernel timer: a hung process must fall silent)."""
        cfg = self.config
        if not (has_object(self.od, OD.GUARD_TIME) and has_object(self.od, OD.LIFE_TIME_FACTOR)):
            self.host_watch_problem = f"{NO_HOST_WATCH}: host_watch: guarding, but the drive has no 0x100C/0x100D"
            return
        if not self.remote_frames:
            self.host_watch_problem = (f"{NO_HOST_WATCH}: node guarding needs remote frames, which this bus cannot"
                                       " carry (socketcand's rawmode has none); use a kernel bus (socketcan)")
            return
        guard_ms, factor = guard_settings(cfg)
        self._write_typed(OD.GUARD_TIME, 0, guard_ms)
        self._write_typed(OD.LIFE_TIME_FACTOR, 0, factor)
        reaction = cfg.on_host_loss if has_object(self.od, OD.ABORT_CONNECTION_OPTION) else \
            "the drive's own reaction (no 0x6007 to choose it)"
        self.host_watch = (f"node guarding every {guard_ms} ms, life time {guard_ms * factor} ms (0x100C x 0x100D),"
                           f" then {reaction}")
        self.host_watch_problem = None
        self._next_guard = 0.0
        self.guarding = True

    def guard(self, now: float) -> None:
        """Supervisor: the guard (a remote frame on 0x700 + id) when one is due. Its answer is the
        drive's 'heartbeat': a missing one makes the drive lost after heartbeat_timeout_ms."""
        if not self.guarding or now < self._next_guard:
            return
        self._next_guard = max(self._next_guard + self.config.heartbeat_period_s, now)
        try:
            self.network.send_message(FunctionCode.HEARTBEAT + self.node_id, b"", remote=True)
        except (can.CanError, OSError, RuntimeError) as err:  # a lost bus is the supervisor's to find
            logger.debug("node %d: guard not sent: %s", self.node_id, err)

    def release_host_watch(self) -> None:
        """Clean shutdown of a disabled drive: stop watching the host, so that its last heartbeat
        raises no EMCY. Kept on a drive that is still enabled (the watch is then its only stop)."""
        if self.host_watch is None or self.lost or self.state == State.OPERATION_ENABLED:
            return
        if self.guarding:
            self._write_typed(OD.LIFE_TIME_FACTOR, 0, 0)  # 0: life guarding off
            self.guarding = False
        else:
            self.sdo_write(OD.CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0))
        self.host_watch = None

    def check_heartbeat(self, now: float) -> None:
        """Supervisor: declare the drive lost when its heartbeat is overdue."""
        if self.booted and not self.lost and self.last_heartbeat and \
                now - self.last_heartbeat > self.config.heartbeat_timeout_s:
            self.lost = True
            self.velocity_commanded = False
            logger.error("node %d (%s): heartbeat lost (none for %.0f ms, consumer time %.0f ms)",
                         self.node_id, self.name, (now - self.last_heartbeat) * 1000,
                         self.config.heartbeat_timeout_s * 1000)

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
            if self.was_enabled and self.state == State.OPERATION_ENABLED:
                # two masters on one drive is no state to keep moving in: the last thing this
                # driver sends it is a quick stop (the watchdog no longer runs for it)
                stopped = True
                try:
                    self._stop_frame(Command.QUICK_STOP, "another master on the bus")
                except MotorError as err:
                    logger.error("%s: quick stop on losing control not sent: %s", self.name, err)
            self.velocity_commanded = False
            self.was_enabled = False
        elif not evidence and self.foreign_master:
            logger.warning("%s (node %d): the other master is gone; configuring the drive again (not enabled)",
                           self.name, self.node_id)
            self.booted = False
            self.rebooted.set()
        self.foreign_master = evidence
        return stopped

    def quick_stop_by_sdo(self, since: float) -> None:
        """Bus worker: the quick stop of losing control once more, as an SDO write of the
        controlword, where the RPDO cannot have reached the drive: its first heartbeat after
        ``since`` (when the other master was noticed) says PRE-OPERATIONAL. Not to a drive that
        reset meanwhile (a boot-up: the reset disabled it) or is still OPERATIONAL (it took the
        RPDO): the other master's SDO transfers use the same channel, and a needless write of
        ours breaks them (seen: a second driver's boot failed on our response). A reset is a
        boot-up after the drive's last OPERATIONAL heartbeat: it can come before the supervisor
        noticed the other master."""
        deadline = since + self.config.heartbeat_timeout_s  # a heartbeat by then, or the drive is lost
        while self.last_heartbeat <= since and time.monotonic() < deadline:
            time.sleep(0.01)
        if self._bootup_at > self._operational_at or self._reported_nmt != "PRE_OPERATIONAL":
            return
        try:
            self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        except MotorError as err:
            logger.error("%s: quick stop by SDO on losing control failed: %s", self.name, err)

    def mark_lost(self) -> None:
        """Supervisor: the drive's bus is gone; nothing is commanded until it is booted again."""
        self.lost = True
        self.booted = False
        self.velocity_commanded = False
        self.was_enabled = False
