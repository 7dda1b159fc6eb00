"""The benchmarks' second try (benchmarks/stack_run.py ``two_tries``): a stack run the machine
starved gets one more, whether it was starved in its window (not carried) or at its start
(StartFailed). A quick run lost its whole 500 Hz section to one start that timed out, its second
try never made. And the start's wait for the drives' switch of mode (``start_streams``) sends the
first command again until it is seen, and names the drives that did not switch."""

from __future__ import annotations

import math
import sys
from types import SimpleNamespace
from typing import Any

import pytest

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import stack_run


def runs_of(*outcomes: Any) -> tuple[list[dict[str, Any]], dict[str, str], list[int]]:
    """two_tries over ``outcomes`` in turn (an exception is raised, a reason is returned with a
    run numbered by its try); the runs kept, ``invalid`` after, and the tries made."""
    made: list[int] = []
    invalid: dict[str, str] = {"x: emulator": "an earlier section's"}

    def run() -> tuple[dict[str, Any], str | None]:
        outcome = outcomes[len(made)]
        made.append(len(made) + 1)
        if isinstance(outcome, Exception):
            raise outcome
        return {"made": len(made)}, outcome

    return stack_run.two_tries("x", "x: emulator", invalid, "p_", run), invalid, made


def test_a_carried_first_run_is_the_only_one() -> None:
    runs, invalid, made = runs_of(None, None)
    assert runs == [{"made": 1, "p_run_try": 1, "p_start_failures": []}] and made == [1] and invalid == {}


def test_a_run_not_carried_is_tried_once_more() -> None:
    runs, invalid, made = runs_of("starved", None)
    assert [r["p_run_try"] for r in runs] == [1, 2] and made == [1, 2] and invalid == {}


def test_a_run_not_carried_twice_leaves_its_reason() -> None:
    runs, invalid, _ = runs_of("starved", "starved again")
    assert [r["made"] for r in runs] == [1, 2] and invalid == {"x: emulator": "starved again"}


def test_a_start_that_failed_is_tried_once_more_and_said() -> None:
    runs, invalid, made = runs_of(stack_run.StartFailed("the drives did not switch"), None)
    assert runs == [{"made": 2, "p_run_try": 2, "p_start_failures": ["run 1: the drives did not switch"]}]
    assert made == [1, 2] and invalid == {}


def test_a_start_that_failed_then_a_run_not_carried_leaves_its_reason() -> None:
    runs, invalid, _ = runs_of(stack_run.StartFailed("no switch"), "starved")
    assert [r["p_run_try"] for r in runs] == [2] and invalid == {"x: emulator": "starved"}


def test_a_start_that_failed_after_a_run_not_carried_keeps_that_run() -> None:
    runs, invalid, _ = runs_of("starved", stack_run.StartFailed("no switch"))
    assert runs == [{"made": 1, "p_run_try": 1, "p_start_failures": ["run 2: no switch"]}]
    assert invalid == {"x: emulator": "starved"}


def test_two_starts_that_failed_raise_the_second() -> None:
    with pytest.raises(stack_run.StartFailed, match="second"):
        runs_of(stack_run.StartFailed("first"), stack_run.StartFailed("second"))


@pytest.mark.parametrize("error", [RuntimeError("a failure after the start"), KeyError("a bug")])
def test_another_error_is_not_a_try(error: Exception) -> None:
    with pytest.raises(type(error)):
        runs_of(error, None)


def test_the_stops_are_named_by_their_try() -> None:
    import bus_limit

    runs = [{"p_run_try": 2, "p_emcy_in_window": ["node 3: 0x8130"]}]
    assert bus_limit.every_stop(runs, prefix="p_") == {"p_emcy_in_window": ["run 2: node 3: 0x8130"], "p_drive_stops": 1}


def diagnostics(*statuses: tuple[str, str | None]) -> Any:
    """One /diagnostics array: a status per (name, mode), no mode key when the mode is None."""
    return SimpleNamespace(status=[
        SimpleNamespace(name=name, values=[] if mode is None else [SimpleNamespace(key="mode", value=mode)])
        for name, mode in statuses])


WANTED = {"rovercan: a": frozenset({"CSP"}), "rovercan: b": frozenset({"PP"})}


def test_no_array_with_modes_is_not_yet_switched() -> None:
    assert stack_run.modes_off([], WANTED) is None
    assert stack_run.modes_off([diagnostics(("rovercan: a", None))], WANTED) is None


def test_the_newest_array_with_modes_names_the_drives_not_switched() -> None:
    older = diagnostics(("rovercan: a", "CSP"), ("rovercan: b", "PP"))
    newer = diagnostics(("rovercan: a", "CSP"), ("rovercan: b", "HM"))
    assert stack_run.modes_off([older, newer, diagnostics(("drive system", None))], WANTED) == {"rovercan: b": "HM"}
    assert stack_run.modes_off([newer, older], WANTED) == {}
    assert stack_run.modes_off([diagnostics(("rovercan: a", "CSP"))], WANTED) == {"rovercan: b": "none"}


class Stack:
    """What start_streams waits on: the first command (counted), the /diagnostics arrays, an
    executor whose turns bring arrays (``after`` turns: the switch done), a measured process."""

    def __init__(self, after: float, exit_status: int | None = None) -> None:
        self.firsts = 0
        self.turns = 0
        self.after = after
        self.diags: list[Any] = []
        self.exit_status = exit_status
        self.shipped = SimpleNamespace(drives=[SimpleNamespace(name="a", position_mode="cyclic"),
                                               SimpleNamespace(name="b", position_mode="profile")])

    def first(self) -> None:
        self.firsts += 1

    def spin_once(self, timeout_sec: float) -> None:
        self.turns += 1
        self.diags.append(diagnostics(("rovercan: a", "8" if self.turns >= self.after else "0"), ("rovercan: b", "1")))

    def poll(self) -> int | None:
        return self.exit_status

    @property
    def returncode(self) -> int | None:
        return self.exit_status

    def start(self) -> None:
        stack_run.start_streams(self.first, self.shipped, self.diags, self, self)  # type: ignore[arg-type]


def test_the_first_command_goes_out_again_until_the_switch_is_seen(monkeypatch: pytest.MonkeyPatch) -> None:
    """Sent again at every turn (its period 0 here, no clock), it stops once every drive reports its mode."""
    monkeypatch.setattr(stack_run, "FIRST_SWITCH_WAIT_S", math.inf)
    monkeypatch.setattr(stack_run, "FIRST_COMMAND_AGAIN_S", -1.0)
    stack = Stack(after=4)
    stack.start()
    assert stack.turns == 4 and stack.firsts == 5  # once, then again before each turn until the switch is seen


def test_a_switch_not_seen_names_the_drive_and_its_mode(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(stack_run, "FIRST_SWITCH_WAIT_S", math.inf)
    monkeypatch.setattr(stack_run, "FIRST_COMMAND_AGAIN_S", math.inf)
    stack = Stack(after=3)
    stack.start()
    assert stack.firsts == 1  # not again within its period
    monkeypatch.setattr(stack_run, "FIRST_SWITCH_WAIT_S", -1.0)
    stack = Stack(after=math.inf)
    stack.diags.append(diagnostics(("rovercan: a", "0"), ("rovercan: b", "1")))
    with pytest.raises(stack_run.StartFailed, match=r"\(rovercan: a in 0; 0 commands refused\)"):
        stack.start()


def test_a_measured_process_that_ended_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(stack_run, "FIRST_SWITCH_WAIT_S", math.inf)
    with pytest.raises(stack_run.StartFailed, match="ended \\(exit status 3\\)"):
        Stack(after=2, exit_status=3).start()
