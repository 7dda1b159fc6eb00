"""Homing (CiA 402 mode 6) with the configured method and speed.

Owner: no state of its own. A command thread runs it as one operation of the command channel
for the whole run (commands refused meanwhile, a stop preempts it); the mode switches and the
enable it needs run under that same operation, so a stop that lands during any of its SDO
writes ends every one of them, and nothing of homing's reaches the drive after the stop.
No lock is held while it waits for 'homing attained'.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from can_config.eds import has_object
from can_config.errors import CommandRejected, DriveStateError, MotorError
from can_config.objects import OD, SUPPORTED_MODE_BIT, OperationMode
from motor_driver.drive.command.busy import Op
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.drive.command.power import PowerStateMachine
from motor_driver.drive.constants import TRANSITION_TIMEOUT_S
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.sdo import SdoPort
from motor_driver.protocol.cia402 import CW, FAULT_STATES, SW, Command, State

logger = logging.getLogger(__name__)


@dataclass(eq=False)
class Homing:
    """Homing of one drive (CiA 402 mode 6), through the parts of the drive it is handed."""

    config: DriveConfig
    _od: ObjectDictionary
    _cache: DriveCache
    _channel: CommandChannel
    _sdo: SdoPort
    _power: PowerStateMachine

    def home(self, timeout_s: float | None = None) -> None:
        """Homing with the configured method and speed; waits for 'homing attained'. The drive
        is busy meanwhile: commands are refused, a stop preempts it."""
        cfg = self.config
        if not self._cache.scale.resolution_known:
            raise CommandRejected(f"{self.config.name} (node {self.config.node_id}): homing refused: the position resolution is"
                                  " unknown (no counts_per_rev in the config, no 0x608F or 0x60A8 on the drive)."
                                  " Set counts_per_rev for this drive. Nothing was sent.")
        if not has_object(self._od, OD.HOMING_METHOD) or \
                not self._power.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.HOMING] & 1:
            why = "no 0x6098 in its EDS" if not has_object(self._od, OD.HOMING_METHOD) else "0x6502 lists no homing"
            raise CommandRejected(f"{self.config.name}: this drive has no homing mode ({why}); nothing was sent. Home it"
                                  " with the vendor's tool, or set offset_deg in the config.")
        with self._channel.operation("home") as op:
            self._power.require_usable("home", fresh=True)  # it moves the drive: not on late data
            self._power.set_mode(OperationMode.HOMING, parent=op)
            self._channel.check(op, "home")
            self._sdo.write_typed(OD.HOMING_METHOD, 0, cfg.homing_method)
            if has_object(self._od, OD.HOMING_SPEEDS, 1):
                self._sdo.write_typed(OD.HOMING_SPEEDS, 1, self._cache.scale.magnitude_to_drive(cfg.homing_speed_deg_s))
            self._channel.point("home: parameters written")
            if self._cache.state != State.OPERATION_ENABLED:
                self._power.enable(parent=op)
            self._channel.transition(op, "home", Command.ENABLE_OPERATION)
            self._channel.transition(op, "home", Command.ENABLE_OPERATION, edge=CW.NEW_SETPOINT)
            self._channel.point("home: start sent")
            self._wait_attained(op, timeout_s or cfg.homing_timeout_s, *self._after_start())
            self._cache.trust_next_position()  # homing moves the zero: the next position is taken as it comes
            self._channel.point("home: attained")
            self._wait_new_position()
            self._channel.transition(op, "home", Command.ENABLE_OPERATION)
            self._power.set_mode(OperationMode.PROFILE_POSITION, parent=op)
            self._channel.forget(self._cache.received.position_counts)

    def _wait_new_position(self) -> None:
        """The first position after homing (the new zero), waited for by its arrival: a
        snapshot taken before it would still show the position before homing (under load the
        next TPDO can be later than a few SYNC periods)."""
        seq = self._cache.position_seq
        bound_s = max(TRANSITION_TIMEOUT_S, 10 * self._cache.sync_period_s)
        behind = self._power.read_behind()
        if not self._cache.wait_until(lambda: self._cache.position_seq != seq, bound_s, behind=behind):
            name = self.config.name
            raise self._power.timed_out(
                behind, (f"{name}: homing attained, but no position after it was read within {bound_s:g} s",
                         "; its new zero is unknown: home again."),
                (f"{name}: homing attained, but no position came from the drive within {bound_s:g} s after it",
                 "; its new zero is unknown. Check the bus and the drive's TPDOs, then home again."))

    def _after_start(self) -> tuple[int, int]:
        """The drive's statusword after it saw the start, and the count of statuswords received by
        then: an SDO read of 0x6041, which the drive answers after the start's RPDO (it takes frames
        in order). Statuswords counted later were sent later. One already on its way when the start
        went out (the last mode's bits 10 and 12, an earlier homing's 'attained') is not this
        homing's answer."""
        word = self._sdo.read_number(OD.STATUSWORD)
        return self._cache.status_seq, word

    def _wait_attained(self, op: Op, timeout_s: float, since: int, answered: int) -> None:
        cache = self._cache

        def attained() -> bool:
            sw = cache.received.statusword if cache.status_seq != since else answered
            if sw & SW.FOLLOWING_ERROR:
                raise DriveStateError(f"{self.config.name}: homing error reported (statusword 0x{sw:04X})",
                                      node_id=self.config.node_id, statusword=sw)
            if sw & SW.SETPOINT_ACK and sw & SW.TARGET_REACHED:
                return True
            if cache.state in FAULT_STATES:
                raise self._power.fault_error("home")
            self._channel.check(op, "home")
            stopped = self._power.stopped_itself("homing")
            if stopped is not None:
                raise stopped
            return False

        behind = self._power.read_behind()
        if not cache.wait_until(attained, timeout_s, behind=behind):
            name, statusword = self.config.name, cache.received.statusword
            raise self._power.timed_out(
                behind, (f"{name}: homing: attained not read within {timeout_s:g} s", f"; {self._stop()}."),
                (f"{name}: homing not attained within {timeout_s:g} s",
                 f"; {self._stop()}. Check the homing method, its speed and the switches it looks for (or raise"
                 " homing_timeout_s for a long search), then home again."), statusword)

    def _stop(self) -> str:
        """A homing that timed out is still searching: the drive is quick-stopped (a stop wins
        over the homing's operation). What was done, for the error."""
        try:
            self._power.quick_stop()
        except MotorError as err:
            logger.error("%s: the quick stop after homing timed out was not confirmed: %s", self.config.name, err)
            return f"a quick stop was tried but not confirmed ({err})"
        except Exception as err:  # a fault of this driver's: said, never in place of the timeout
            logger.exception("%s: the quick stop after homing timed out failed unexpectedly", self.config.name)
            return f"a quick stop was tried and failed unexpectedly ({type(err).__name__}: {err})"
        return "the drive was quick-stopped"
