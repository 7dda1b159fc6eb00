"""Homing (CiA 402 mode 6) with the configured method and speed.

Threads: a command thread, with the drive marked busy for the whole run (commands refused,
a stop preempts it); no lock is held while it waits for 'homing attained'.
"""

from __future__ import annotations

import logging
import time

from can_config.eds import has_object
from can_config.errors import CommandRejected, DriveStateError, DriveTimeoutError
from can_config.objects import OD, SUPPORTED_MODE_BIT, OperationMode
from motor_driver.cia402 import CW, FAULT_STATES, SW, Command, State
from motor_driver.drive.constants import STATE_POLL_S
from motor_driver.drive.motion import Motion

logger = logging.getLogger(__name__)


class Homing(Motion):
    """Layer 6: homing (CiA 402 mode 6)."""

    def home(self, timeout_s: float | None = None) -> None:
        """Homing with the configured method and speed; waits for 'homing attained'. The drive
        is busy meanwhile: commands are refused, a stop preempts it."""
        cfg = self.config
        self._require_resolution("homing")
        if not has_object(self.od, OD.HOMING_METHOD) or \
                not self.supported_modes() >> SUPPORTED_MODE_BIT[OperationMode.HOMING] & 1:
            raise CommandRejected(f"{self.name}: this drive has no homing mode ("
                                  f"{'no 0x6098 in its EDS' if not has_object(self.od, OD.HOMING_METHOD) else '0x6502 lists no homing'});"
                                  " nothing was sent. Home it with the vendor's tool, or set offset_deg in the config.")
        with self._operation("home") as generation:
            self._require_usable("home")
            self.set_mode(OperationMode.HOMING)
            self._write_typed(OD.HOMING_METHOD, 0, cfg.homing_method)
            if has_object(self.od, OD.HOMING_SPEEDS, 1):
                self._write_typed(OD.HOMING_SPEEDS, 1, self.scale.magnitude_to_drive(cfg.homing_speed_deg_s))
            if self.state != State.OPERATION_ENABLED:
                self.enable()
            self._transition(generation, "home", Command.ENABLE_OPERATION)
            self._transition(generation, "home", Command.ENABLE_OPERATION, edge=CW.NEW_SETPOINT)
            deadline = time.monotonic() + (timeout_s or cfg.homing_timeout_s)
            while True:
                sw = self.statusword
                if sw & SW.FOLLOWING_ERROR:
                    raise DriveStateError(f"{self.name}: homing error reported (statusword 0x{sw:04X})",
                                          node_id=self.node_id, statusword=sw)
                if sw & SW.SETPOINT_ACK and sw & SW.TARGET_REACHED:
                    break
                if self.state in FAULT_STATES:
                    raise self._fault_error("home")
                self._check_not_preempted(generation, "home")
                if time.monotonic() > deadline:
                    raise DriveTimeoutError(f"{self.name}: homing not attained within"
                                            f" {timeout_s or cfg.homing_timeout_s:g} s", node_id=self.node_id,
                                            statusword=sw)
                time.sleep(STATE_POLL_S)
            self._position_t = 0.0  # homing moves the zero: the next position is trusted as it comes
            seq = self._position_seq
            settle = time.monotonic() + 3 * self.sync_period_s + 0.05
            while self._position_seq == seq and time.monotonic() < settle:
                time.sleep(0.001)
            self._transition(generation, "home", Command.ENABLE_OPERATION)
            self.set_mode(OperationMode.PROFILE_POSITION)
            self._target_counts = self.position_counts
