"""The frames a command sends: controlword, position / velocity / torque targets, each in the
drive's RPDO where the plan mapped it, else by SDO.

Owner: command threads, under ``_lock`` (``_cw``, ``_enable_sent_at``, ``_target_counts``);
the set-point handshake (:mod:`motor_driver.setpoint`) calls ``_send_setpoint`` and
``_clear_setpoint`` under its own lock, from a command thread or the receive thread (its
acknowledge reply).
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable

from can_config.objects import OD
from motor_driver.cia402 import CW, Command, controlword
from motor_driver.drive.sdo import SdoAccess
from motor_driver.pdo import encode_rpdo
from motor_driver.setpoint import SetpointHandshake

logger = logging.getLogger(__name__)


class CommandFrames(SdoAccess):
    """Layer 2: the frames a command sends (controlword, targets), RPDO where mapped, else SDO."""

    def _init_state(self) -> None:
        super()._init_state()
        self._lock = threading.RLock()  # serialises commands; never held while waiting for the drive
        self._cw = 0  # last device-control controlword (no edge bits); written under _lock only
        self._enable_sent_at = 0.0  # when this driver last sent Enable Operation (under _lock)
        self._target_counts = 0  # the last position target (command threads, under _lock)
        self._handshake = SetpointHandshake(self._send_setpoint, self._clear_setpoint)
        #: tests only: called at named points of the state machine to force an interleaving (_hook)
        self.interleave: Callable[[str], None] | None = None

    def _hook(self, point: str) -> None:
        """A seam for tests that force an interleaving: ``interleave`` is called at named points
        of the state machine (never set in production; None costs one attribute read)."""
        if self.interleave is not None:
            self.interleave(point)

    def _send_cw(self, cw: int) -> None:
        pdo = self.plan.rpdo_with(OD.CONTROLWORD)
        if pdo is None:
            self.sdo_write(OD.CONTROLWORD, 0, struct.pack("<H", cw))
            return
        values: dict[int, int] = {OD.CONTROLWORD: cw, OD.TARGET_POSITION: self._target_counts, OD.TARGET_VELOCITY: 0}
        self._send(pdo.cob_id, encode_rpdo(pdo, values))

    def _send_setpoint(self, counts: int) -> None:
        """A target with controlword bit 4 rising (called by the handshake, under its lock)."""
        self._target_counts = counts
        pdo = self.plan.rpdo_with(OD.TARGET_POSITION)
        cw = controlword(Command.ENABLE_OPERATION, new_setpoint=True, change_immediately=True)
        cw |= self._cw & CW.HALT
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw,
                                                                    OD.TARGET_POSITION: counts}))
        else:  # 0x607A not PDO-mappable (SCHUNK PRL120): move_to wrote it by SDO; the edge only
            self._send_cw(cw)

    def _clear_setpoint(self) -> None:
        """Controlword bit 4 back to 0 after the acknowledge (called by the handshake)."""
        self._send_cw(int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT))

    def _send_velocity(self, counts_s: int) -> None:
        pdo = self.plan.rpdo_with(OD.TARGET_VELOCITY)
        cw = int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT)
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw,
                                                                    OD.TARGET_VELOCITY: counts_s}))
        else:
            self._write_typed(OD.TARGET_VELOCITY, 0, counts_s)

    def _send_torque(self, permille: int) -> None:
        pdo = self.plan.rpdo_with(OD.TARGET_TORQUE)
        cw = int(Command.ENABLE_OPERATION) | (self._cw & CW.HALT)
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw, OD.TARGET_TORQUE: permille}))
        else:
            self._write_typed(OD.TARGET_TORQUE, 0, permille)
