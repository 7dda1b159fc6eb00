"""A :class:`DriveState` made by hand for a test, with the facts its verdict is judged from.

DriveState offers no flags (a reader reads its verdict); a test that wants a lost, late or armed
drive says so here, and the state carries those facts and the verdict judged from them, as the
driver's own snapshot does."""

from __future__ import annotations

import dataclasses
from typing import Any

from motor_driver.drive.values import DriveState
from motor_driver.drive.verdict import judge
from motor_driver.protocol.cia402 import FAULT_STATES


def drive_state(*, enabled: bool = False, fault: bool = False, lost: bool = False, stale: bool = False,
                **values: Any) -> DriveState:
    """``DriveState(**values)`` judged with these facts: ``enabled`` (armed by this driver),
    ``lost`` (no heartbeat), ``stale`` (its data older than its bound). ``fault`` is the
    statusword's (``state``), accepted and ignored, as the driver's snapshot derives it. Its
    position is of its newest TPDO unless given (``position_stamp``, ``position_rx``)."""
    del fault
    values.setdefault("position_stamp", values.get("stamp", 0.0))
    values.setdefault("position_rx", values.get("rx_monotonic", 0.0))
    values.setdefault("whole_rx", values.get("rx_monotonic", 0.0))
    state = DriveState(**values)
    facts = state.facts._replace(lost=lost, armed=enabled,
                                 stale_after_s=-1.0 if stale else state.facts.stale_after_s)
    return dataclasses.replace(state, judged=(facts, judge(facts)))


def stale(state: DriveState) -> bool:
    """Its values are old: its data older than its bound, or never heard (what the flag said)."""
    age, bound = state.facts.data_age_s, state.facts.stale_after_s
    return not age <= bound


def fault(state: DriveState) -> bool:
    """Its statusword says FAULT or FAULT REACTION ACTIVE, or it is lost (what the flag said)."""
    return state.state in FAULT_STATES or state.facts.lost


def lost(state: DriveState) -> bool:
    """No heartbeat within its consumer time: the supervisor's fact the verdict was judged from."""
    return state.facts.lost
