"""The simulated drive's CiA 402 state machine: controlword, mode switch, set-point acceptance
per mode, statusword bits, and its reaction to losing the master (0x6007). Runner thread only.
"""

from __future__ import annotations

import logging
import random

import can

from can_config.objects import EMCY_HEARTBEAT_LOST, OD, OperationMode
from virtual_can.sim.drive.errors import ErrorStack
from virtual_can.sim.drive.model import (
    CW_NEW_SETPOINT,
    CW_RELATIVE,
    ENABLING,
    POWERED,
    STANDSTILL_COUNTS_S,
    STATUS_BITS,
    SW_OMS12,
    SW_OMS13,
    SW_REMOTE,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    VELOCITY_MODES,
    State,
    next_state,
)

logger = logging.getLogger(__name__)


class StateMachine(ErrorStack):
    """Layer 2: the CiA 402 state machine."""

    def _apply_controlword(self) -> None:
        cw = int(self.store.get(OD.CONTROLWORD, 0))  # type: ignore[arg-type]
        new = next_state(self.state, cw, self.prev_cw, voltage_ok=not self.faults.sto_low,
                         quick_stop_option=self.quick_stop_option)
        pending, self._slow_transition = self._slow_transition, None  # a new controlword overrides it
        if new != self.state:
            if self.faults.enable_step_delay_s > 0 and new in ENABLING and self.state in (State.SWITCH_ON_DISABLED,
                                                                                        *ENABLING):
                self._slow_transition = pending if pending is not None and pending[0] == new else \
                    (new, self._now + self.faults.enable_step_delay_s)  # a slow drive
            else:
                self._enter(new)
        mode = self.mode
        rising = cw & ~self.prev_cw
        if self.state == State.OPERATION_ENABLED:
            if mode == OperationMode.PROFILE_POSITION and rising & CW_NEW_SETPOINT:
                self._new_pp_setpoint(cw)
            elif mode == OperationMode.HOMING and rising & CW_NEW_SETPOINT:
                self._start_homing()
            elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
                self._csp_target()
        self.prev_cw = cw

    def _enter(self, new: State) -> None:
        if self.state in POWERED and new not in POWERED and abs(self.sp_vel) > STANDSTILL_COUNTS_S:
            self.cut_at_speed.append(abs(self.sp_vel))
            logger.info("node %d: power stage off at %.0f counts/s (%s -> %s): a real shaft coasts from here",
                        self.node_id, abs(self.sp_vel), self.state.name, new.name)
        if self.state == State.FAULT:
            self._clear_error()
        if new == State.OPERATION_ENABLED and self.state != State.QUICK_STOP_ACTIVE:
            self._hold_position()
        self.state = new

    def _set_mode(self) -> None:
        requested = int(self.store.get(OD.MODES_OF_OPERATION, 0))  # type: ignore[arg-type]
        supported = int(self.store.get(OD.SUPPORTED_DRIVE_MODES, 0, 0))  # type: ignore[arg-type]
        bit = {1: 0, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}.get(requested)
        if requested != 0 and (bit is None or not supported >> bit & 1):
            return  # unsupported: the display keeps the old mode, as real drives do
        self.store.set(OD.MODES_OF_OPERATION_DISPLAY, 0, requested)
        self.pp_target = None
        self.homing_active = False
        self._hold_position()
        self._update_status()  # 0x6061 and the statusword's mode bits change in one cycle

    def _hold_position(self) -> None:
        self.sp_pos = self.position_counts
        self.sp_vel = 0.0
        self.sp_acc = 0.0
        self.pp_target = None
        self._csp_last = None
        self._vel_integral = 0.0

    def _new_pp_setpoint(self, cw: int) -> None:
        target = float(self.store.get(OD.TARGET_POSITION, 0))  # type: ignore[arg-type]
        if cw & CW_RELATIVE:
            target += self.pp_target if self.pp_target is not None else self.sp_pos
        self.pp_target = target
        self._setpoint_ack = True
        if self.faults.ack_delay_max_s > 0:
            self._ack_at = self._now + random.uniform(0.0, self.faults.ack_delay_max_s)
        if self.accepted_targets is not None:
            self.accepted_targets.append(target)

    def _csp_target(self) -> None:
        """CSP: follow 0x607A; IP: follow 0x60C1:1 while controlword bit 4 (enable ip) is set."""
        if self.state != State.OPERATION_ENABLED:
            return
        if self.mode == OperationMode.CYCLIC_SYNC_POSITION:
            self.pp_target = float(self.store.get(OD.TARGET_POSITION, 0))  # type: ignore[arg-type]
        elif self.mode == OperationMode.INTERPOLATED_POSITION and self._ip_enabled:
            self.pp_target = float(self.store.get(OD.INTERPOLATION_DATA, 1, 0))  # type: ignore[arg-type]
        else:
            return
        # the SYNC it came with: the cycles between the set-point followed (held while written
        # again unchanged) and a new one (plant._cyclic_position_step). A pause in the stream (IP
        # with bit 4 off, set-points not written) spreads the next one over it, up to CYCLIC_GAP_S
        self._csp_written = self._syncs
        if self.pp_target == self._csp_last:
            self._csp_sync = self._syncs

    @property
    def _ip_enabled(self) -> bool:
        return bool(int(self.store.get(OD.CONTROLWORD, 0)) & CW_NEW_SETPOINT)  # type: ignore[arg-type]

    def _start_homing(self) -> None:
        method = int(self.store.get(OD.HOMING_METHOD, 0, 35))  # type: ignore[arg-type]
        self.homing_done = self.homing_error = False
        if method in (35, 37):
            self._home_here()
        else:
            self.homing_active = True
            self._homing_start = self.position_counts

    def _home_here(self) -> None:
        raw = self.theta / self._rad_per_count
        self.position_offset = -raw
        self.homing_active = False
        self.homing_done = True
        self._hold_position()
        self._publish_position()  # 'attained' and the new zero in one cycle: a SYNC before the next tick sends it

    def _publish_position(self) -> None:
        """The position actual (0x6064) into the object dictionary, in the drive's units."""
        self.store.values[(OD.POSITION_ACTUAL, 0)] = self._as_type(OD.POSITION_ACTUAL, self.position_counts)

    def _update_status(self) -> None:
        sw = STATUS_BITS[self.state] | SW_REMOTE
        if not self.faults.sto_low and self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                                                      *POWERED):
            sw |= SW_VOLTAGE_ENABLED
        if self.state == State.OPERATION_ENABLED:
            sw |= self._mode_status_bits(self.mode)
        elif self.state == State.QUICK_STOP_ACTIVE and (abs(self.sp_vel) < 1e-6 or (
                self.faults.speed_reached_in_quick_stop and self.mode in VELOCITY_MODES)):
            sw |= SW_TARGET_REACHED  # halted (options 5-7 hold here); or the quirk's "speed reached"
        if self.following_since is not None:
            sw |= SW_WARNING
        if self.faults.garbled_statusword:  # bits 0-3, 5, 6: "ready to switch on" alone is no state
            sw = (sw & ~0x6F) | 0x01
        self.store.values[(OD.STATUSWORD, 0)] = sw

    def _pp_status_bits(self) -> int:
        """Profile position: target reached (bit 10) and the set-point acknowledge (bit 12)."""
        bits = 0
        if self.pp_target is None or (abs(self.sp_pos - self.pp_target) < 0.5 and self.sp_vel == 0.0
                                      and abs(self.position_counts - self.pp_target) <= self._window()):
            bits |= SW_TARGET_REACHED
        cw = int(self.store.get(OD.CONTROLWORD, 0))  # type: ignore[arg-type]
        if cw & CW_NEW_SETPOINT and self._setpoint_ack:
            if self._now >= self._ack_at:  # a slow drive acknowledges later (fault injection)
                bits |= SW_OMS12
        else:
            self._setpoint_ack = False
        return bits

    def _mode_status_bits(self, mode: int) -> int:
        """Statusword bits 10, 12 and 13 of Operation Enabled, as the mode defines them (CiA 402)."""
        bits = 0
        if mode == OperationMode.PROFILE_POSITION:
            bits |= self._pp_status_bits()
        elif mode == OperationMode.PROFILE_VELOCITY:
            target_v = self._v(OD.TARGET_VELOCITY, 0, 0)
            if abs(self.omega / self._rad_per_count - target_v) < max(10.0, abs(target_v) * 0.02):
                bits |= SW_TARGET_REACHED
            if abs(self.omega / self._rad_per_count) < 10.0:
                bits |= SW_OMS12
        elif mode == OperationMode.HOMING:
            if self.homing_done:
                bits |= SW_OMS12 | SW_TARGET_REACHED
            if self.homing_error:
                bits |= SW_OMS13
        elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.CYCLIC_SYNC_VELOCITY,
                      OperationMode.CYCLIC_SYNC_TORQUE):
            bits |= SW_OMS12  # the drive follows the cyclic target
        elif mode == OperationMode.INTERPOLATED_POSITION:
            if self._ip_enabled:
                bits |= SW_OMS12  # ip mode active
            if self.pp_target is None or abs(self.pp_target - self.position_counts) <= self._window():
                bits |= SW_TARGET_REACHED
        else:
            bits |= SW_TARGET_REACHED
        return bits

    def _connection_lost(self, now: float) -> list[can.Message]:
        """CiA 402 0x6007: the drive's own reaction to losing its master. A drive without 0x6007
        reacts as its vendor decided; the model takes the common choice, a fault."""
        option = int(self.store.get(OD.ABORT_CONNECTION_OPTION, 0, 1))  # type: ignore[arg-type]
        if option == 1:
            return self._raise_fault(EMCY_HEARTBEAT_LOST, now)
        if option == 2 and self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, *POWERED):
            self.state = State.SWITCH_ON_DISABLED
        elif option == 3:
            if self.state == State.OPERATION_ENABLED:
                self.state = State.QUICK_STOP_ACTIVE
            elif self.state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
                self.state = State.SWITCH_ON_DISABLED
        return [self._warning_emcy(EMCY_HEARTBEAT_LOST)]
