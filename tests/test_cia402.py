"""Tier 1: the CiA 402 tables and controlwords against the standard, byte for byte."""

from __future__ import annotations

import pytest

from motor_driver.protocol.cia402 import (
    TRANSITIONS,
    Command,
    State,
    braked,
    controlword,
    decode_state,
    next_step_to_enable,
)


@pytest.mark.parametrize(("statusword", "state"), [
    (0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x0240, State.SWITCH_ON_DISABLED),
    (0x0740, State.SWITCH_ON_DISABLED),  # maxon EPOS (machinekit issue 589 table)
    (0x0721, State.READY_TO_SWITCH_ON),
    (0x0723, State.SWITCHED_ON),
    (0x0737, State.OPERATION_ENABLED),
    (0x0637, State.OPERATION_ENABLED),  # ros2_canopen issue 298 trace
    (0x0617, State.QUICK_STOP_ACTIVE),
    (0x021F, State.FAULT_REACTION_ACTIVE),
    (0x0638, State.FAULT),  # ros2_canopen issue 298 trace, after EMCY 0x5201
    (0x0208, State.FAULT),
])
def test_statusword_decodes_to_the_standard_state(statusword: int, state: State) -> None:
    assert decode_state(statusword) is state


def test_transition_table_carries_the_standard_numbers_and_commands() -> None:
    assert TRANSITIONS[(State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON)] == (2, Command.SHUTDOWN)
    assert TRANSITIONS[(State.READY_TO_SWITCH_ON, State.SWITCHED_ON)] == (3, Command.SWITCH_ON)
    assert TRANSITIONS[(State.SWITCHED_ON, State.OPERATION_ENABLED)] == (4, Command.ENABLE_OPERATION)
    assert TRANSITIONS[(State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)] == (11, Command.QUICK_STOP)
    assert TRANSITIONS[(State.FAULT, State.SWITCH_ON_DISABLED)] == (15, Command.FAULT_RESET)
    numbers = sorted(n for n, _ in TRANSITIONS.values())
    assert numbers == [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16]


def test_controlword_values() -> None:
    # the enable sequence of the maxon EPOS table: 06 -> 07 -> 0F
    assert [int(Command.SHUTDOWN), int(Command.SWITCH_ON), int(Command.ENABLE_OPERATION)] == [0x06, 0x07, 0x0F]
    assert int(Command.QUICK_STOP) == 0x02
    assert int(Command.FAULT_RESET) == 0x80
    assert controlword(Command.ENABLE_OPERATION, new_setpoint=True, change_immediately=True) == 0x3F
    assert controlword(Command.ENABLE_OPERATION, halt=True) == 0x10F
    assert controlword(Command.ENABLE_OPERATION, relative=True) == 0x4F


def test_enable_path_walks_2_3_4() -> None:
    steps = []
    state = State.SWITCH_ON_DISABLED
    while (step := next_step_to_enable(state)) is not None:
        state, number, command = step
        steps.append((number, int(command)))
    assert steps == [(2, 0x06), (3, 0x07), (4, 0x0F)]
    assert state is State.OPERATION_ENABLED
    assert next_step_to_enable(State.FAULT) is None


@pytest.mark.parametrize(("statusword", "velocity_deg_s", "done"), [
    (0x0240, 0.0, True),     # Switch On Disabled by itself after the ramp (options 1-3)
    (0x0240, 50.0, True),    # ... whatever a stale velocity says: the power stage is off already
    (0x0617, 0.0, True),     # Quick Stop Active, target reached at standstill (options 5-7 hold there)
    (0x0617, -1.0, True),    # the standstill bound, either way round
    (0x0617, 30.0, False),   # bit 10 at speed: a velocity mode's "speed reached" kept into the ramp
    (0x0617, -1.5, False),
    (0x0217, 0.0, False),    # Quick Stop Active without bit 10: still on its ramp
    (0x0237, 0.0, False),    # Operation Enabled: the stop not taken yet, or another master's enable
    (0x021F, 0.0, False),    # Fault Reaction Active: on its fault reaction's ramp
    (0x0638, 10.0, True),    # Fault: its reaction ended, the power stage off
    (0x0221, 5.0, True),     # Ready to Switch On: the power stage off
    (0x0001, 0.0, False),    # no state (a garbled word): nothing said of the ramp
])
def test_a_quick_stop_has_braked_only_off_its_ramp_or_at_standstill(statusword: int, velocity_deg_s: float,
                                                                     done: bool) -> None:
    assert braked(decode_state(statusword), statusword, velocity_deg_s) is done
