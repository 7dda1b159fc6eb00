"""benchmarks/callback_cpu.py: the stack run's accounts of each callback's CPU. A callback counted
keeps the signature the supervision asks for, adds its own thread's CPU (not its wall time) to its
account, and a window is the difference of two snapshots."""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

import pytest

from .conftest import REPO

pytest.importorskip("rclpy")  # the node's supervision wraps rclpy's entities: skipped on a machine without ROS

from nodes.process import spinning

sys.path.insert(0, str(REPO / "benchmarks"))
import callback_cpu


@pytest.fixture(autouse=True)
def fresh_accounts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(callback_cpu, "ACCOUNTS", {})


def burn(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_a_counted_callback_keeps_its_arity_for_the_supervision() -> None:
    assert spinning._takes_one(callback_cpu.counted("one", lambda msg: None))
    assert not spinning._takes_one(callback_cpu.counted("two", lambda msg, info: None))


def test_a_callback_s_account_is_its_thread_s_cpu_not_its_wall_time() -> None:
    calls: list[Any] = []
    busy = callback_cpu.counted("subscription /busy", lambda msg: (calls.append(msg), burn(0.05)))
    wrapped = spinning._subscription_callback(type("Sub", (), {"topic_name": "/busy"})(), busy,
                                              spinning.CallbackFailures())
    wrapped("m")
    assert calls == ["m"]
    assert callback_cpu.ACCOUNTS["subscription /busy"] >= 0.05e9

    # a callback that waits while another thread burns 0.05 s of CPU: that CPU is not its own
    done = threading.Event()
    worker = threading.Thread(target=lambda: (burn(0.05), done.set()))
    waits = callback_cpu.counted("subscription /waits", lambda msg: (worker.start(), done.wait()))
    waits("m")
    worker.join()
    assert done.is_set()
    assert callback_cpu.ACCOUNTS["subscription /waits"] < 0.025e9


def test_a_raising_callback_is_still_counted_and_its_error_goes_on() -> None:
    def fails(msg: Any) -> None:
        burn(0.01)
        raise ValueError("bad message")

    with pytest.raises(ValueError, match="bad message"):
        callback_cpu.counted("subscription /fails", fails)("m")
    assert callback_cpu.ACCOUNTS["subscription /fails"] >= 0.01e9


def test_a_window_is_the_difference_of_its_first_and_last_snapshots() -> None:
    snapshots = [{"t": 10.0, "main_cpu_ns": 1_000_000_000, "accounts": {"timer a": 500_000_000}},
                 {"t": 11.0, "main_cpu_ns": 1_050_000_000, "accounts": {"timer a": 500_000_000}},
                 {"t": 12.0, "main_cpu_ns": 1_200_000_000, "accounts": {"timer a": 600_000_000,
                                                                        "subscription /b": 40_000_000}}]
    assert callback_cpu.window(snapshots) == {
        "cpu_by_callback": {"timer a": 0.05, "subscription /b": 0.02}, "cpu_in_callbacks": 0.07,
        "cpu_main_thread": 0.1, "cpu_main_outside_callbacks": 0.03}
    assert callback_cpu.window(snapshots[:1]) == {}  # no window without both ends
