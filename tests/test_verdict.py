"""The verdict on a drive (motor_driver/drive/verdict.py): every combination of what the driver knows
gives exactly one condition, the first of the documented precedence that holds; each condition
says its cause and what helps."""

from __future__ import annotations

import itertools
import math

from hypothesis import given
from hypothesis import strategies as st

from can_config.objects import EMCY_HEARTBEAT_LOST
from motor_driver.drive.verdict import PRECEDENCE, Condition, DriveFacts, Verdict, judge
from motor_driver.protocol.cia402 import State

#: Each condition's own test, written apart from judge(): which conditions hold for these facts.
HOLDS = {
    Condition.ANOTHER_MASTER: lambda f: bool(f.foreign_master),
    Condition.LOST: lambda f: f.lost,
    Condition.REBOOTING: lambda f: f.rebooting,
    Condition.NOT_CONFIGURED: lambda f: not f.booted,
    # never heard (an infinite or NaN age) is late under any bound, an infinite one too
    Condition.LATE: lambda f: math.isinf(f.data_age_s) or math.isnan(f.data_age_s) or math.isnan(f.stale_after_s)
    or f.data_age_s > f.stale_after_s,
    Condition.FAULTED: lambda f: f.state in (State.FAULT, State.FAULT_REACTION_ACTIVE) or f.fault_seen != 0,
    Condition.HELD: lambda f: bool(f.held),
    Condition.OUT: lambda f: bool(f.left_out),
    Condition.STOPPED_ITSELF: lambda f: f.state != State.OPERATION_ENABLED and (
        f.armed or f.emcy_code == EMCY_HEARTBEAT_LOST),
    Condition.NOT_ARMED: lambda f: f.state != State.OPERATION_ENABLED,
    Condition.USABLE: lambda f: True,
}

#: every default and infinity (and NaN) of the ages and the bound: a state made by hand is judged
#: with an infinite bound, and data never heard has an infinite age
AGES = st.one_of(st.just(math.inf), st.just(math.nan), st.just(0.0), st.floats(0.0, 5.0))
FACTS = st.builds(
    DriveFacts, name=st.just("wheel_x"),
    data_age_s=AGES,
    stale_after_s=st.one_of(st.just(math.inf), st.just(math.nan), st.just(-1.0), st.floats(0.01, 1.0)),
    heartbeat_age_s=AGES, fault_seen=st.sampled_from([0, 0x0008]), enables=st.integers(0, 3),
    nmt=st.sampled_from(["OPERATIONAL", "PRE_OPERATIONAL", "BOOTUP", "STOPPED"]),
    state=st.sampled_from(list(State)), lost=st.booleans(), booted=st.booleans(), rebooting=st.booleans(),
    foreign_master=st.sampled_from(["", "NMT frame 0x000 seen"]), armed=st.booleans(),
    stopped_by=st.sampled_from(["", "disarm"]), emcy_code=st.sampled_from([0, EMCY_HEARTBEAT_LOST, 0x2310]),
    emcy_stamp=st.floats(0.0, 2e9), left_out=st.sampled_from(["", "it was lost"]),
    held=st.sampled_from(["", "rovercan_lifecycle is inactive: activate it"]))


def expected(facts: DriveFacts) -> Condition:
    return next(c for c in PRECEDENCE if HOLDS[c](facts))


def test_precedence_names_every_condition_once() -> None:
    assert sorted(c.value for c in PRECEDENCE) == sorted(c.value for c in Condition)
    assert PRECEDENCE[-1] is Condition.USABLE


@given(FACTS)
def test_every_combination_gives_the_first_condition_that_holds(facts: DriveFacts) -> None:
    verdict = judge(facts)
    assert verdict.condition is expected(facts)
    assert verdict.usable == (verdict.condition is Condition.USABLE)
    assert verdict.age_s == facts.data_age_s or math.isnan(facts.data_age_s)
    assert verdict.cause and verdict.name == "wheel_x"
    assert verdict.condition is Condition.USABLE or verdict.helps  # every problem says what helps


def test_every_flag_combination_exhaustively() -> None:
    """The flags crossed in full (the property test samples; this covers every corner)."""
    base = DriveFacts("w", data_age_s=0.0, stale_after_s=0.1)
    for foreign, lost, reboot, booted, late, state, out, armed, emcy, held in itertools.product(
            ("", "x"), (False, True), (False, True), (False, True), (False, True), list(State), ("", "x"),
            (False, True), (0, EMCY_HEARTBEAT_LOST), ("", "held")):
        facts = base._replace(foreign_master=foreign, lost=lost, rebooting=reboot, booted=booted,
                        data_age_s=1.0 if late else 0.0, state=state, left_out=out, armed=armed, emcy_code=emcy,
                        held=held)
        assert judge(facts).condition is expected(facts), facts


def _usable(**changes: object) -> DriveFacts:
    facts = DriveFacts("wheel_x", data_age_s=0.005, stale_after_s=0.05, heartbeat_age_s=0.05, nmt="OPERATIONAL",
                       state=State.OPERATION_ENABLED, booted=True, armed=True)
    return facts._replace(**changes)  # type: ignore[arg-type]


def test_usable() -> None:
    assert judge(_usable()) == Verdict("wheel_x", Condition.USABLE, 0.005, "usable")


def test_late_says_how_long_and_what_stalled() -> None:
    verdict = judge(_usable(data_age_s=0.24))
    assert verdict.condition is Condition.LATE and not verdict.fresh
    assert verdict.text().startswith("wheel_x: no data for 240 ms (bus or drive stalled)")
    assert judge(_usable(data_age_s=math.inf)).cause == "no data for ever (bus or drive stalled)"


def test_a_host_watch_stop_is_named_as_such() -> None:
    stamp = 1_700_000_000.25  # 22:13:20.250 UTC
    verdict = judge(_usable(state=State.QUICK_STOP_ACTIVE, emcy_code=EMCY_HEARTBEAT_LOST, emcy_stamp=stamp))
    assert verdict.condition is Condition.STOPPED_ITSELF
    assert verdict.text().startswith("wheel_x: stopped itself: host heartbeat lost at 22:13:20.250")
    assert verdict.text().endswith("; /arm enables it again")
    # the host watch may take it to SWITCH ON DISABLED with the EMCY, after this driver's own stop too
    assert judge(_usable(state=State.SWITCH_ON_DISABLED, armed=False, stopped_by="x",
                         emcy_code=EMCY_HEARTBEAT_LOST)).condition is Condition.STOPPED_ITSELF


def test_a_stop_of_this_drivers_is_not_armed_and_says_who() -> None:
    verdict = judge(_usable(state=State.SWITCHED_ON, armed=False, stopped_by="disarm"))
    assert verdict.condition is Condition.NOT_ARMED
    assert "stopped by disarm" in verdict.cause and "/arm" in verdict.helps


def test_a_rebooted_drive_is_not_usable_even_if_its_old_state_was_enabled() -> None:
    verdict = judge(_usable(rebooting=True, booted=False, nmt="PRE_OPERATIONAL"))
    assert verdict.condition is Condition.REBOOTING and not verdict.usable and not verdict.fresh


def test_fresh_data_of_a_drive_that_cannot_be_driven_is_still_news() -> None:
    assert judge(_usable(state=State.SWITCH_ON_DISABLED, armed=False)).fresh
    assert judge(_usable(state=State.FAULT)).fresh
    assert not judge(_usable(lost=True)).fresh


def test_held_motion_is_said_with_what_lets_it_go() -> None:
    """The lifecycle node inactive: not usable, its reason the remedy, whatever the drive still shows."""
    verdict = judge(_usable(held="rovercan_lifecycle is inactive: activate it"))
    assert verdict.condition is Condition.HELD and not verdict.usable and verdict.fresh
    assert verdict.text() == "wheel_x: motion held; rovercan_lifecycle is inactive: activate it"


@given(st.builds(DriveFacts, name=st.just("wheel_x"), data_age_s=st.sampled_from([math.inf, math.nan]),
                 stale_after_s=st.one_of(st.just(math.inf), st.just(math.nan), st.floats(-1.0, 1e9)),
                 heartbeat_age_s=AGES, state=st.just(State.OPERATION_ENABLED), booted=st.just(True),
                 armed=st.booleans()))
def test_a_drive_never_heard_is_never_usable_whatever_its_bound(facts: DriveFacts) -> None:
    """No data ever (an infinite age: the default) is never usable, under an infinite staleness
    bound too (a state made by hand is judged with one: inf > inf is false, and it was usable)."""
    assert not judge(facts).usable
