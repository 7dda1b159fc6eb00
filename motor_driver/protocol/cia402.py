"""CiA 402 drive profile as data: states, controlword commands, the transition table.

Pure functions only; :class:`motor_driver.drive.Drive` does the I/O. Written from CiA 402
(IEC 61800-7-201) on its own, independently of the simulator's state machine.
"""

from __future__ import annotations

from enum import IntEnum

from can_config.objects import Cia402State

#: Power drive states (CiA 402 figure 'state machine'): their names are can_config's passive
#: definition; how a statusword codes them (below) is this module's own reading.
State = Cia402State


class Command(IntEnum):
    """Controlword device-control commands (bits 0-3 and 7)."""

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007  # the bits of SWITCH_ON (an alias: transition 5 rather than 3)
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


class SW(IntEnum):
    """Statusword bits."""

    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT = 1 << 11
    SETPOINT_ACK = 1 << 12  # PP; homing: attained; PV: speed zero
    FOLLOWING_ERROR = 1 << 13  # PP/CSP; homing: homing error


class CW(IntEnum):
    """Controlword bits beyond the device-control command."""

    NEW_SETPOINT = 1 << 4  # homing: start homing; interpolated position: enable ip mode
    CHANGE_IMMEDIATELY = 1 << 5
    RELATIVE = 1 << 6
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


#: (mask, value) of the statusword for each state (CiA 402 table 'state coding').
_STATE_CODING: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)


#: The states of a drive in fault (its reaction running, or done).
FAULT_STATES = frozenset({State.FAULT, State.FAULT_REACTION_ACTIVE})
#: The states whose drive function is on: the motor under torque, the drive in charge of its motion.
DRIVE_FUNCTION_ON = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE})
#: A quick stop's "target reached" counts as standstill only at this speed or under, deg/s (a word
#: that kept a velocity mode's "speed reached" into Quick Stop Active is no standstill).
STANDSTILL_DEG_S = 1.0


#: After a quick stop, the states that say nothing of a finished ramp: still on it, its fault
#: reaction's ramp, enabled again (another master's enable, or the stop not taken yet), no state.
_NOT_BRAKED = DRIVE_FUNCTION_ON | {State.UNKNOWN}


def braked(state: State, statusword: int, velocity_deg_s: float) -> bool:
    """After a quick stop: has the drive stopped braking? Its power stage off by itself (Switch On
    Disabled after the ramp, quick-stop options 1-4; Fault after a fault reaction; Ready to Switch
    On, Switched On), or Quick Stop Active with "target reached" (bit 10) at standstill (options 5-8
    hold there; bit 10 alone is not enough: some drives keep a velocity mode's "speed reached" set
    through the ramp). Until then its voltage disabled cuts the ramp short, and a real drive's shaft
    coasts from there. A drive without a velocity (0x606C unmapped, unread: 0) is judged by bit 10."""
    if state == State.QUICK_STOP_ACTIVE:
        return bool(statusword & SW.TARGET_REACHED and abs(velocity_deg_s) <= STANDSTILL_DEG_S)
    return state not in _NOT_BRAKED


def _decode_by_coding(statusword: int) -> State:
    for mask, value, state in _STATE_CODING:
        if statusword & mask == value:
            return state
    return State.UNKNOWN


#: The bits the state coding reads, and the state of each of their values: decode_state runs on
#: every statusword received and every command, one lookup instead of up to eight masks.
_CODING_BITS = 0
for _mask, _, _ in _STATE_CODING:
    _CODING_BITS |= _mask
_STATE_BY_BITS = tuple(_decode_by_coding(bits) for bits in range(_CODING_BITS + 1))


def decode_state(statusword: int) -> State:
    """The CiA 402 state a statusword reports."""
    return _STATE_BY_BITS[statusword & _CODING_BITS]


#: Transition table: (from, to) -> (transition number, command). Automatic transitions
#: (0, 1, 13, 14) have no command and are not listed.
TRANSITIONS: dict[tuple[State, State], tuple[int, Command]] = {
    (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON): (2, Command.SHUTDOWN),
    (State.READY_TO_SWITCH_ON, State.SWITCHED_ON): (3, Command.SWITCH_ON),
    (State.SWITCHED_ON, State.OPERATION_ENABLED): (4, Command.ENABLE_OPERATION),
    (State.OPERATION_ENABLED, State.SWITCHED_ON): (5, Command.DISABLE_OPERATION),
    (State.SWITCHED_ON, State.READY_TO_SWITCH_ON): (6, Command.SHUTDOWN),
    (State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED): (7, Command.DISABLE_VOLTAGE),
    (State.OPERATION_ENABLED, State.READY_TO_SWITCH_ON): (8, Command.SHUTDOWN),
    (State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED): (9, Command.DISABLE_VOLTAGE),
    (State.SWITCHED_ON, State.SWITCH_ON_DISABLED): (10, Command.DISABLE_VOLTAGE),
    (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE): (11, Command.QUICK_STOP),
    (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED): (12, Command.DISABLE_VOLTAGE),
    (State.FAULT, State.SWITCH_ON_DISABLED): (15, Command.FAULT_RESET),
    (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED): (16, Command.ENABLE_OPERATION),
}

#: The way up to Operation Enabled, one transition at a time.
_ENABLE_PATH: dict[State, State] = {
    State.SWITCH_ON_DISABLED: State.READY_TO_SWITCH_ON,
    State.READY_TO_SWITCH_ON: State.SWITCHED_ON,
    State.SWITCHED_ON: State.OPERATION_ENABLED,
    State.QUICK_STOP_ACTIVE: State.SWITCH_ON_DISABLED,
}


def next_step_to_enable(state: State) -> tuple[State, int, Command] | None:
    """The next (state, transition number, command) on the way to Operation Enabled.

    ``None`` when already enabled, or when the state needs something else first (fault:
    reset it; not ready / fault reaction: wait).
    """
    target = _ENABLE_PATH.get(state)
    if target is None:
        return None
    number, command = TRANSITIONS[(state, target)]
    return target, number, command


def controlword(command: Command, *, new_setpoint: bool = False, change_immediately: bool = False,
                relative: bool = False, halt: bool = False) -> int:
    """Build a controlword: a device-control command plus operation-mode bits."""
    cw = int(command)
    if new_setpoint:
        cw |= CW.NEW_SETPOINT
    if change_immediately:
        cw |= CW.CHANGE_IMMEDIATELY
    if relative:
        cw |= CW.RELATIVE
    if halt:
        cw |= CW.HALT
    return cw
