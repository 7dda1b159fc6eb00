"""The SYNC of python-can's thread-based task: its error handler is in place before its thread
sends the first SYNC, so a bus that died during start-up ends the task with one log line, never
with an unhandled exception in that thread (seen on a busy runner: BrokenPipeError)."""

from __future__ import annotations

import threading
from typing import Any

import can

from motor_driver.bus.handle import BusHandle

from .conftest import wait_for


class DeadBus(can.BusABC):
    """A bus whose every send fails at once, as a socketcand connection whose server died does."""

    def __init__(self) -> None:
        super().__init__(channel="dead")
        self.sends = 0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sends += 1
        raise can.CanOperationError("Broken pipe", error_code=32)

    def _send_periodic_internal(self, msgs: Any, period: float, duration: float | None = None,
                                autostart: bool = True, modifier_callback: Any = None) -> Any:
        task = super()._send_periodic_internal(msgs, period, duration, autostart, modifier_callback)
        if autostart:  # its thread runs at once: let it send first, as on a busy machine it may
            wait_for(lambda: task.stopped, 10.0, "the SYNC thread's first send and its end")
        return task

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        threading.Event().wait(min(timeout or 0.01, 0.01))
        return None, False


def test_a_sync_thread_on_a_dead_bus_ends_without_an_unhandled_error() -> None:
    unhandled: list[Any] = []
    previous = threading.excepthook
    threading.excepthook = unhandled.append
    bus = DeadBus()
    handle = BusHandle("can0", bus, owned=True, sync_period_s=0.001)
    try:
        handle.start_sync()
        task = handle.sync_task
        assert isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask)
        assert task.on_error is not None
        wait_for(lambda: bus.sends > 0 and task.stopped, 10.0, "the SYNC thread tried and stopped")
        assert task.thread is not None
        task.thread.join(10.0)
        assert not task.thread.is_alive()
    finally:
        threading.excepthook = previous
        handle.disconnect()
        handle.worker.shutdown()
    assert not unhandled, [u.exc_value for u in unhandled]


class LockWatchingBus(can.BusABC):
    """A bus that notes, for each frame sent, whether the lock it is given was held."""

    def __init__(self) -> None:
        super().__init__(channel="watched")
        self.lock: Any = None
        self.held: list[tuple[int, bool]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.held.append((msg.arbitration_id, self.lock is not None and self.lock.locked()))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        threading.Event().wait(min(timeout or 0.01, 0.01))
        return None, False


def test_the_host_heartbeat_and_the_sync_thread_send_under_the_networks_lock() -> None:
    """Every writer of a bus's socket takes the canopen network's send lock (the RPDOs and SDOs do):
    the host heartbeat (the supervisor's) and python-can's SYNC thread too, so that two threads'
    text never interleaves on a TCP bus (the review: both wrote without it)."""
    bus = LockWatchingBus()
    handle = BusHandle("can0", bus, owned=True, sync_period_s=0.001)
    bus.lock = handle.network.send_lock
    try:
        assert handle.beat(0x7F) is None
        handle.start_sync()
        wait_for(lambda: any(cob == 0x080 for cob, _ in bus.held), 10.0, "a SYNC sent by the thread")
        handle.stop_sync()
        assert bus.held and all(held for _, held in bus.held), bus.held
        assert {cob for cob, _ in bus.held} == {0x77F, 0x080}
    finally:
        handle.disconnect()
        handle.worker.shutdown()
