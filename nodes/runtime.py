"""Process life cycle of the rovercan nodes: one stop path, one teardown order.

rclpy's own signal handling shuts the context down (SIGTERM) or raises
``KeyboardInterrupt`` (SIGINT) under whatever is running, including an executor spinning on
another thread or an executor building its wait set. Both were seen to kill the node (an
``RCLError`` from a wait set, a segfault) before or while the drives were brought to a safe
state. Here rclpy installs no handlers; SIGINT/SIGTERM set an event, the spin loops return,
and the caller tears down in order: drives safe, executor threads joined, nodes destroyed,
context shut down.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence

import rclpy
from rclpy.context import Context
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from can_config.errors import ConfigError
from can_config.realtime import make_process_realtime
from motor_driver.process import heap
from motor_driver.process.stop import StopSignal

logger = logging.getLogger(__name__)

POLL_S = 0.1  # longest wait before a spin loop sees the stop event


def init(args: Sequence[str] | None) -> None:
    """``rclpy.init`` without rclpy's signal handlers (use :class:`StopSignal`)."""
    rclpy.init(args=list(args) if args is not None else None, signal_handler_options=SignalHandlerOptions.NO)


EXECUTORS = ("events", "single")


def make_executor(kind: str, context: Context | None = None) -> Executor:
    """The hot-path executor by name (the ``executor`` parameter).

    ``events``: rclpy's EventsExecutor (C++ dispatch, no wait set rebuilt in Python per
    wake-up); measured in the 6-drive run at about 0.25 of a core against 0.34 for ``single``
    (README, Performance). It is marked experimental in Jazzy; ``single`` is the fallback,
    and is used with a warning where the installed rclpy has no EventsExecutor.
    """
    if kind not in EXECUTORS:
        raise ConfigError(f"parameter executor: {kind!r} is not one of {list(EXECUTORS)}; set"
                          " -p executor:=events (default) or -p executor:=single")
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            logger.warning("this rclpy has no EventsExecutor; using the SingleThreadedExecutor")
        else:
            return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def go_realtime(node: Node) -> bool:
    """Every thread of this process (and every one it starts later) under SCHED_FIFO at the
    node's ``realtime_priority``, where the OS allows it; 0: ordinary. True if real-time now."""
    value = node.get_parameter("realtime_priority").value
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 99:
        raise ConfigError(f"parameter realtime_priority = {value!r}: expected a whole number from 0 (ordinary"
                          " scheduling) to 99; set -p realtime_priority:=20 (the default) or 0")
    return value > 0 and make_process_realtime(node.get_name(), value)


def spin_until(executor: Executor, stop: threading.Event, poll_s: float = POLL_S) -> None:
    """Spin ``executor`` until ``stop`` is set or the context is shut down by someone else,
    looking at both every ``poll_s`` at the latest (sooner where the stopper gives the executor work).

    The EventsExecutor dispatches everything that comes in ``poll_s`` in one call into C++
    (``spin_until_future_complete`` of a future nobody completes, a new one each time: that call
    adds a callback to it): ``spin_once`` would come back to Python after every single callback,
    and the loop's own checks were about 7 % of the hot thread's interpreter time in the six-drive
    profile (docs/performance.md)."""
    if isinstance(executor, Executor):
        def step() -> None:
            executor.spin_once(timeout_sec=poll_s)
    else:  # rclpy's EventsExecutor (C++; not an rclpy Executor subclass)
        def step() -> None:
            executor.spin_until_future_complete(Future(), timeout_sec=poll_s)
    try:
        while not stop.is_set() and executor.context.ok():
            step()
    except ExternalShutdownException:
        pass


def spin_node(node: Node, stop: threading.Event, *, on_stop: Callable[[], None] | None = None,
              executor: Executor | None = None) -> None:
    """One node on ``executor`` (default: a single-threaded one) until ``stop``; then ``on_stop``
    (drives safe), the executor shut down, the node destroyed and the context shut down, in that
    order, whatever happened."""
    if executor is None:
        executor = SingleThreadedExecutor()
    executor.add_node(node)
    heap.settle()  # the node is built: what exists now lives as long as the process
    try:
        spin_until(executor, stop)
    finally:
        try:
            if on_stop is not None:
                on_stop()
        finally:
            executor.shutdown(timeout_sec=0)
            node.destroy_node()
            rclpy.try_shutdown()


def give_work(executor: Executor) -> None:
    """Make an rclpy executor's waiting ``spin_once`` return now: a task is work (``wake()`` alone
    makes it wait again). What it resumes then (a goal's coroutine, its loop's stop check) runs at
    once instead of at its next poll."""
    executor.create_task(lambda: None)


#: How long a :class:`SpinThread` of an rclpy executor waits for work before it looks at its stop
#: event again: :meth:`SpinThread.stop` gives the executor a task, so this only bounds a missed wake-up. The three
#: mostly idle executors of the driver (stops, services, actions) each rebuilt their wait set in
#: Python ten times a second at POLL_S: about 0.003 of a core each.
IDLE_POLL_S = 2.0


class SpinThread:
    """An executor spinning on its own thread, stopped (the executor given a task) and joined by :meth:`stop`."""

    def __init__(self, executor: Executor, name: str) -> None:
        self.executor = executor
        self._stop = threading.Event()
        # rclpy's executors leave their wait at a task (stop() gives one); the EventsExecutor's timed spin does not
        poll_s = IDLE_POLL_S if isinstance(executor, Executor) else POLL_S
        self._thread = threading.Thread(target=spin_until, args=(executor, self._stop, poll_s), daemon=True, name=name)
        self._thread.start()

    def stop(self, timeout_s: float) -> bool:
        """Stop spinning; True once the thread has left the executor (then it may be destroyed)."""
        self._stop.set()
        if isinstance(self.executor, Executor):
            give_work(self.executor)  # out of its wait now, not at the next IDLE_POLL_S
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            logger.error("%s: still inside a callback after %.1f s", self._thread.name, timeout_s)
            return False
        self.executor.shutdown(timeout_sec=0)
        return True


__all__ = ["EXECUTORS", "IDLE_POLL_S", "POLL_S", "SpinThread", "StopSignal", "give_work", "go_realtime", "init", "make_executor",
           "spin_node", "spin_until"]
