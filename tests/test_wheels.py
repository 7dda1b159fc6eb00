"""Tier 1: what the drive system says of a wheel, what the odometry may count of it, and its book
of wheels left out (pure): each from the wheel's verdict."""

from __future__ import annotations

import dataclasses
import math

from motor_driver.drive import DriveState
from motor_driver.drive.verdict import judge
from motor_driver.protocol.cia402 import State
from nodes.rover.wheels import WheelsOut, odometry_sample, problems, wheel_problem

from .drive_states import drive_state

BASE_FIELDS: dict[str, object] = dict(
    name="w1", node_id=1, angle_deg=90.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0x0637,
    state=State.OPERATION_ENABLED, mode=9, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
    error_code=0, error_text="", stamp=100.0, heartbeat_age_s=0.01, target_reached=False,
    data_age_s=0.01, stale=False, foreign_master="", reference=1, rx_monotonic=50.0)
BASE = drive_state(**BASE_FIELDS)


def state(**changes: object) -> DriveState:
    return drive_state(**(BASE_FIELDS | changes))


def test_each_cause_is_named_with_what_helps() -> None:
    assert wheel_problem(BASE) == ""
    lost = wheel_problem(state(enabled=False, lost=True, fault=True, heartbeat_age_s=0.75))
    assert "w1: heartbeat lost: none for 750 ms" in lost and "cable" in lost and "arm the rover" not in lost
    stale = wheel_problem(state(enabled=False, stale=True, data_age_s=0.12))
    assert stale.startswith("w1: no data for 120 ms (bus or drive stalled)") and "/arm does not help" in stale
    fault = wheel_problem(state(enabled=False, state=State.FAULT, fault=True, error_code=0x2310,
                                error_text="continuous over-current"))
    assert "FAULT: EMCY 0x2310 continuous over-current" in fault and "w1/recover" in fault
    foreign = wheel_problem(state(enabled=False, foreign_master="NMT stop from elsewhere"))
    assert "another master" in foreign
    assert "not armed (SWITCH_ON_DISABLED)" in wheel_problem(state(enabled=False, state=State.SWITCH_ON_DISABLED))
    said = problems([state(name="a", enabled=False, lost=True), BASE, state(name="b", enabled=False, stale=True)])
    assert said.startswith("a: heartbeat lost") and said.endswith("(and 1 more: b)")


PDO_S = 0.015


def test_odometry_takes_a_fresh_wheel_keeps_a_late_one_and_forgets_a_lost_one() -> None:
    fresh = odometry_sample(BASE, PDO_S)
    assert fresh.trusted and math.isclose(fresh.angle_rad, math.pi / 2) and fresh.reference == 1
    assert fresh.stamp == BASE.rx_monotonic  # ordered by the receive thread's clock, not the frame's
    late = odometry_sample(state(stale=True, enabled=False), PDO_S)
    assert not late.trusted and not late.forget and not late.silent and "no data" in late.why_not
    silent = odometry_sample(state(data_age_s=0.03), PDO_S)  # usable, but its PDO is a period late
    assert not silent.trusted and not silent.forget and silent.silent and "silent for 30 ms" in silent.why_not
    lost = odometry_sample(state(lost=True, fault=True, enabled=False), PDO_S)
    assert not lost.trusted and lost.forget and "heartbeat lost" in lost.why_not
    # a frame of its other SYNC TPDO lost: the data whole as of 30 ms ago (the verdict's age counts
    # from then), its position fresh: measured, not silent
    gap = odometry_sample(state(data_age_s=0.03, whole_rx=49.98, rx_monotonic=50.0, position_rx=50.0), PDO_S)
    assert gap.trusted, gap.why_not
    older = odometry_sample(state(data_age_s=0.03, whole_rx=49.98, rx_monotonic=50.0, position_rx=49.98), PDO_S)
    assert not older.trusted and older.silent and "its position silent for 30 ms" in older.why_not


def test_a_wheel_out_disabled_quick_stopped_or_rebooting_counts_for_nothing() -> None:
    """Each forgets its last sample: its next one starts anew (it adds nothing meanwhile)."""
    for changes in ({"enabled": False, "state": State.SWITCH_ON_DISABLED},
                    {"enabled": False, "state": State.QUICK_STOP_ACTIVE}):
        sample = odometry_sample(state(**changes), PDO_S)
        assert not sample.trusted and sample.forget, changes
    rebooting = BASE.facts._replace(rebooting=True, booted=False)
    sample = odometry_sample(dataclasses.replace(BASE, judged=(rebooting, judge(rebooting))), PDO_S)
    assert not sample.trusted and sample.forget and "re-booting" in sample.why_not
    out = BASE.facts._replace(left_out="it was lost")
    sample = odometry_sample(dataclasses.replace(BASE, judged=(out, judge(out))), PDO_S)
    assert not sample.trusted and sample.forget and "out of the drive system" in sample.why_not


def test_with_no_wheel_driven_every_measured_wheel_counts() -> None:
    """The rover disarmed (standing, or pushed): what the wheels measure is all the motion there is."""
    idle = state(enabled=False, state=State.SWITCH_ON_DISABLED)
    assert odometry_sample(idle, PDO_S, driven=False).trusted
    assert not odometry_sample(state(lost=True, enabled=False), PDO_S, driven=False).trusted


def enabled(name: str, enables: int) -> DriveState:
    """Armed, Operation Enabled and fresh, after the driver completed ``enables`` enables of it."""
    facts = state(name=name).facts._replace(enables=enables)
    return dataclasses.replace(BASE, name=name, judged=(facts, judge(facts)))


def test_a_held_rover_leaves_no_wheel_out() -> None:
    """on_wheel_loss: continue, /cmd_vel fresh while the lifecycle node is inactive (motion held):
    every wheel's verdict is HELD, the rover's state and no wheel's loss; it booked every wheel
    out and told each to stop (six "degraded" warnings for a refusal that sent nothing)."""
    book = WheelsOut(["a"], ["b"])
    held = {n: state(name=n) for n in ("a", "b")}
    held = {n: dataclasses.replace(s, judged=(f := s.facts._replace(held="inactive: activate it"), judge(f)))
            for n, s in held.items()}
    assert all(not s.verdict.usable for s in held.values())
    assert book.update(held, driving=True) == ([], []) and not book.out


def test_a_wheel_out_comes_back_only_after_an_enable_since_it_went_out() -> None:
    book = WheelsOut(["a", "b"], ["c"])
    states = {"a": state(name="a"), "b": state(name="b"), "c": state(name="c")}  # enabled at start
    assert book.update(states, driving=True) == ([], [])
    states["b"] = state(name="b", stale=True, enabled=False)  # late: out like a lost one (it is not measured)
    assert book.update(states, driving=True) == (["b"], []) and book.share() == 0.5
    assert "b out (b: no data for" in book.summary()
    states["a"] = state(name="a", lost=True, enabled=False, fault=True)
    assert book.update(states, driving=True) == (["a"], [])
    assert book.share() == 0.0 and book.empty_side() == "left" and "a out (a: heartbeat lost" in book.summary()
    states["b"] = state(name="b", state=State.QUICK_STOP_ACTIVE, enabled=False)  # fresh again, stopped as told
    assert book.update(states, driving=True) == ([], [])
    states["b"] = enabled("b", 1)  # /arm
    assert book.update(states, driving=True) == ([], ["b"])
    # heard again, still Operation Enabled and armed from before (no stop of ours reached it, no
    # enable since): not back, told again, however long it stays so
    states["a"] = state(name="a")
    for _ in range(3):
        assert book.update(states, driving=True) == ([], []) and book.still_running(states) == ["a"]
    # /arm under way: Operation Enabled (usable) before its enable is counted; not told to stop
    assert book.still_running(states, enabling=["a"]) == []
    # /arm stopped and enabled it between two looks (its way down never seen): back all the same
    states["a"] = enabled("a", 1)
    assert book.update(states, driving=True) == ([], ["a"]) and book.share() == 1.0


def test_an_enable_that_a_stop_followed_takes_no_wheel_back() -> None:
    book = WheelsOut(["a"], ["c"])
    states = {"a": state(name="a", stale=True, enabled=False), "c": state(name="c")}
    assert book.update(states, driving=True) == (["a"], [])
    facts = state(name="a", state=State.QUICK_STOP_ACTIVE, enabled=False).facts._replace(enables=1)
    states["a"] = dataclasses.replace(BASE, name="a", judged=(facts, judge(facts)))  # enabled, then stopped
    assert book.update(states, driving=True) == ([], []) and book.still_running(states) == []


def test_idle_wheels_are_not_taken_out_and_a_side_with_none_left_has_no_share() -> None:
    book = WheelsOut(["a"], ["c"])
    states = {"a": state(name="a", enabled=False, state=State.SWITCH_ON_DISABLED), "c": state(name="c")}
    assert book.update(states, driving=False) == ([], [])  # not driving: nothing is out
    assert book.update(states, driving=True) == (["a"], [])
    assert book.share() == 0.0
