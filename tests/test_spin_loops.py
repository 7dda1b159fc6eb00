"""The node's spin loops (nodes/process/spinning.py): an idle executor's thread waits for work, not for a
poll, and still leaves at once when stopped; the hot EventsExecutor runs every callback that
comes within one call and still sees its stop event."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from .conftest import HAVE_ROS, requires_ros, wait_for

pytestmark = requires_ros

if HAVE_ROS:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    from nodes.process import spinning


@pytest.fixture
def context() -> Iterator[Any]:
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def test_an_idle_spin_thread_leaves_at_once_when_stopped_not_at_its_next_poll(
        context: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(spinning, "IDLE_POLL_S", 600.0)  # a poll would keep it in its wait for ten minutes
    node = rclpy.create_node("idle", context=context)
    served = threading.Event()
    node.create_service(Trigger, "poke", lambda _req, resp: served.set() or resp)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spin = spinning.SpinThread(executor, "test-idle")
    client = rclpy.create_node("client", context=context)
    poke = client.create_client(Trigger, "poke")
    assert poke.wait_for_service(timeout_sec=10.0)
    poke.call_async(Trigger.Request())
    wait_for(served.is_set, 10.0, "the idle executor to serve a request (work wakes it)")
    assert spin.stop(60.0), "the stopped thread stayed in its executor's wait"
    client.destroy_node()
    node.destroy_node()


def test_the_hot_loop_runs_a_burst_of_callbacks_and_still_stops(context: Any) -> None:
    node = rclpy.create_node("hot", context=context)
    executor = spinning.make_executor("events", context)
    executor.add_node(node)
    stop = threading.Event()
    ticks: list[int] = []

    def tick() -> None:
        ticks.append(1)
        if len(ticks) == 50:
            stop.set()
    node.create_timer(0.001, tick)
    thread = threading.Thread(target=spinning.spin_until, args=(executor, stop))
    thread.start()
    thread.join(60.0)
    assert not thread.is_alive() and len(ticks) >= 50
    executor.shutdown(timeout_sec=0)
    node.destroy_node()
