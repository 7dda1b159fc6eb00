"""Tier 1: what the drive system says of a wheel and its book of wheels left out (pure)."""

from __future__ import annotations

import dataclasses
import math

from motor_driver.drive import DriveState
from motor_driver.protocol.cia402 import State
from nodes.wheels import WheelsOut, odometry_sample, problems, wheel_problem

BASE = DriveState(name="w1", node_id=1, angle_deg=90.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0x0637,
                  state=State.OPERATION_ENABLED, mode=9, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
                  error_code=0, error_text="", stamp=100.0, heartbeat_age_s=0.01, target_reached=False,
                  data_age_s=0.01, stale=False, foreign_master="", reference=1)


def state(**changes: object) -> DriveState:
    return dataclasses.replace(BASE, **changes)  # type: ignore[arg-type]


def test_each_cause_is_named_with_what_helps() -> None:
    assert wheel_problem(BASE) == ""
    lost = wheel_problem(state(enabled=False, lost=True, fault=True, heartbeat_age_s=0.75))
    assert "w1 is lost (no heartbeat for 750 ms)" in lost and "cable" in lost and "arm the rover" not in lost
    stale = wheel_problem(state(enabled=False, stale=True, data_age_s=0.12))
    assert "stale (no PDO for 120 ms)" in stale and "/arm does not help" in stale
    fault = wheel_problem(state(enabled=False, state=State.FAULT, fault=True, error_code=0x2310,
                                error_text="continuous over-current"))
    assert "FAULT, EMCY 0x2310 continuous over-current" in fault and "w1/recover" in fault
    foreign = wheel_problem(state(enabled=False, foreign_master="NMT stop from elsewhere"))
    assert "another master" in foreign
    assert "not armed (SWITCH_ON_DISABLED)" in wheel_problem(state(enabled=False, state=State.SWITCH_ON_DISABLED))
    said = problems([state(name="a", enabled=False, lost=True), BASE, state(name="b", enabled=False, stale=True)])
    assert said.startswith("a is lost") and said.endswith("(and 1 more: b)")


def test_odometry_takes_a_fresh_wheel_keeps_a_late_one_and_forgets_a_lost_one() -> None:
    fresh = odometry_sample(BASE)
    assert fresh.trusted and math.isclose(fresh.angle_rad, math.pi / 2) and fresh.reference == 1
    late = odometry_sample(state(stale=True, enabled=False))
    assert not late.trusted and not late.forget and "stale" in late.why_not
    lost = odometry_sample(state(lost=True, fault=True, enabled=False))
    assert not lost.trusted and lost.forget and "lost" in lost.why_not


def test_a_wheel_out_comes_back_only_stopped_then_enabled_again() -> None:
    book = WheelsOut(["a", "b"], ["c"])
    states = {"a": state(name="a"), "b": state(name="b"), "c": state(name="c")}
    assert book.update(states, driving=True) == ([], [])
    states["a"] = state(name="a", stale=True, enabled=False)  # only late: not out (it hears the commands)
    assert book.update(states, driving=True) == ([], []) and book.share() == 1.0
    states["a"] = state(name="a", lost=True, enabled=False, fault=True)
    assert book.update(states, driving=True) == (["a"], [])
    assert book.share() == 0.5 and "a out (a is lost" in book.summary()
    # heard again, still Operation Enabled from before (our stop never reached it): not back, told again
    states["a"] = state(name="a")
    assert book.update(states, driving=True) == ([], []) and book.still_running(states) == ["a"]
    states["a"] = state(name="a", state=State.SWITCH_ON_DISABLED, enabled=False)  # stopped now
    assert book.update(states, driving=True) == ([], []) and book.still_running(states) == []
    states["a"] = state(name="a")  # armed again (/arm, recover)
    assert book.update(states, driving=True) == ([], ["a"]) and book.share() == 1.0


def test_idle_wheels_are_not_taken_out_and_a_side_with_none_left_has_no_share() -> None:
    book = WheelsOut(["a"], ["c"])
    states = {"a": state(name="a", enabled=False, state=State.SWITCH_ON_DISABLED), "c": state(name="c")}
    assert book.update(states, driving=False) == ([], [])  # not driving: nothing is out
    assert book.update(states, driving=True) == (["a"], [])
    assert book.share() == 0.0
