"""The benchmarks' second try (benchmarks/stack_run.py ``two_tries``): a stack run the machine
starved gets one more, whether it was starved in its window (not carried) or at its start (a
RuntimeError). A quick run lost its whole 500 Hz section to one start that timed out, its second
try never made. And the start's wait for the drives' modes (``modes_off``) names the drives that
did not switch."""

from __future__ import annotations

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
        return {"try": len(made)}, outcome

    return stack_run.two_tries("x", "x: emulator", invalid, run), invalid, made


def test_a_carried_first_run_is_the_only_one() -> None:
    runs, invalid, made = runs_of(None, None)
    assert runs == [{"try": 1}] and made == [1] and invalid == {}


def test_a_run_not_carried_is_tried_once_more() -> None:
    runs, invalid, made = runs_of("starved", None)
    assert runs == [{"try": 1}, {"try": 2}] and made == [1, 2] and invalid == {}


def test_a_run_not_carried_twice_leaves_its_reason() -> None:
    runs, invalid, _ = runs_of("starved", "starved again")
    assert runs == [{"try": 1}, {"try": 2}] and invalid == {"x: emulator": "starved again"}


def test_a_start_that_failed_is_tried_once_more() -> None:
    runs, invalid, made = runs_of(RuntimeError("the drives did not switch"), None)
    assert runs == [{"try": 2}] and made == [1, 2] and invalid == {}


def test_a_start_that_failed_after_a_run_not_carried_keeps_that_run() -> None:
    runs, invalid, _ = runs_of("starved", RuntimeError("the drives did not switch"))
    assert runs == [{"try": 1}] and invalid == {"x: emulator": "starved"}


def test_two_starts_that_failed_raise_the_second() -> None:
    with pytest.raises(RuntimeError, match="second"):
        runs_of(RuntimeError("first"), RuntimeError("second"))


def test_another_error_is_not_a_try() -> None:
    with pytest.raises(KeyError):
        runs_of(KeyError("a bug"), None)


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
