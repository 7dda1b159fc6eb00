"""The error stack of the simulated drive: EMCY producer, error register, pre-defined error
field (0x1003), fault injection. Runner thread only.
"""

from __future__ import annotations

import logging
import struct

import can

from can_config.objects import OD, FunctionCode
from virtual_can.sim.drive.base import DriveBase
from virtual_can.sim.drive.model import ERROR_REGISTER_BITS, POWERED, State

logger = logging.getLogger(__name__)


class ErrorStack(DriveBase):
    """Layer 1: EMCY and the error history."""

    def raise_fault(self, code: int) -> None:
        """Fault injection: the drive detects an error with this EMCY code at its next tick."""
        self.faults.pending.append(code)

    def _raise_fault(self, code: int, now: float | None) -> list[can.Message]:
        self.error_code = code
        self.store.set(OD.ERROR_CODE, 0, code)
        register = 0x01 | ERROR_REGISTER_BITS.get(code >> 12, 0)
        if code >> 8 == 0x86 or code >> 8 == 0x85:
            register |= 0x20  # device profile specific
        self.store.set(OD.ERROR_REGISTER, 0, register)
        self._record_error(code)
        if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self.state = State.FAULT_REACTION_ACTIVE if self.state in POWERED else State.FAULT
        self.counters["emcy"] += 1
        return [self._emcy(code, register)]

    def _record_error(self, code: int) -> None:
        """Push ``code`` onto the pre-defined error field (0x1003), newest at sub 1."""
        if self.store.has(OD.PREDEFINED_ERROR_FIELD, 1):
            depth = sum(1 for k in self.store.vars if k[0] == OD.PREDEFINED_ERROR_FIELD and k[1] > 0)
            for sub in range(depth, 1, -1):
                self.store.set(OD.PREDEFINED_ERROR_FIELD, sub, self.store.get(OD.PREDEFINED_ERROR_FIELD, sub - 1))
            self.store.set(OD.PREDEFINED_ERROR_FIELD, 1, code)
            count = int(self.store.get(OD.PREDEFINED_ERROR_FIELD, 0))  # type: ignore[arg-type]
            self.store.set(OD.PREDEFINED_ERROR_FIELD, 0, min(depth, count + 1))

    def _clear_error(self) -> None:
        self.error_code = 0
        self.store.set(OD.ERROR_CODE, 0, 0)
        self.store.set(OD.ERROR_REGISTER, 0, 0)
        self._pending_emcy_reset = True

    def _emcy(self, code: int, register: int) -> can.Message:
        cob = int(self.store.get(OD.COB_ID_EMCY, 0, FunctionCode.EMCY + self.node_id)) & 0x7FF  # type: ignore[arg-type]
        return self._msg(cob, struct.pack("<HB5x", code, register))

    def _warning_emcy(self, code: int) -> can.Message:
        """An EMCY that reports an error without a fault state (communication error bit set)."""
        self._record_error(code)
        self.counters["emcy"] += 1
        return self._emcy(code, 0x11)
