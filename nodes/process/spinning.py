"""Process life cycle of the rovercan nodes: one stop path, one teardown order, and no callback
that ends an executor.

rclpy's own signal handling shuts the context down (SIGTERM) or raises
``KeyboardInterrupt`` (SIGINT) under whatever is running, including an executor spinning on
another thread or an executor building its wait set. Both were seen to kill the node (an
``RCLError`` from a wait set, a segfault) before or while the drives were brought to a safe
state. Here rclpy installs no handlers; SIGINT/SIGTERM set an event, the spin loops return,
and the caller tears down in order: drives safe, executor threads joined, nodes destroyed,
context shut down.

Supervised callbacks (:func:`supervise`, :class:`CallbackFailures`): rclpy's executors end on a
callback's exception. The SingleThreaded and MultiThreadedExecutor raise it out of ``spin_once``
(the thread pool's future re-raised on the spinning thread at its next turn); the EventsExecutor
logs it (FATAL, with its trace) and raises it out of its spin; a service whose callback raised
sends no response, and its client waits for ever. One value a drive returned (an SDO read of NaN)
ended the services' executor: every joint's enable went unanswered. So every service, timer and
subscription callback of the assembly's nodes is wrapped where the assembly makes them: an
unexpected exception is logged once with its trace, counted (the driver's /diagnostics, status
"rovercan: driver": ``callback_failures``, ``last_callback_failure``), and a service answers a
failed response naming itself. What still escapes (an action server's internals, a node added
later) is caught by :func:`spin_until`, logged, counted, and the executor spins on.

Owner: :class:`CallbackFailures` is written by any executor thread (under its lock) and read by
the diagnostics timer; the rest keeps no state.
"""

from __future__ import annotations

import inspect
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters, SetParametersAtomically
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


#: How often a callback that keeps failing the same way is said again (its first failure is said
#: with its trace; each one is counted).
REPEAT_LOG_S = 10.0


class CallbackFailures:
    """Callbacks that raised an unexpected exception: how many, and the last one named. Each is
    logged once, with its trace the first time a callback fails with an exception of its type,
    then at most every REPEAT_LOG_S (a timer failing at 50 Hz is one line, not fifty a second).
    Written by any executor thread under its lock; read by the diagnostics timer."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count = 0
        self._last = ""
        self._at = 0.0  # when the last one failed (monotonic)
        self._said: dict[tuple[str, type], float] = {}  # (where, type) -> when said last (monotonic)

    def record(self, where: str, err: BaseException, *, logged: bool = False) -> str:
        """Count ``err``, raised by the callback ``where``; log it (unless ``logged``: rclpy said it
        already). Returns the sentence a failed response carries."""
        text = f"{where} failed unexpectedly: {err!r}"
        now = time.monotonic()
        key = (where, type(err))
        with self._lock:
            self._count += 1
            self._last, self._at = text, now
            said = self._said.get(key)
            say = not logged and (said is None or now - said >= REPEAT_LOG_S)
            if say:
                self._said[key] = now
            count = self._count
        if say and said is None:
            logger.error("%s (callback failure %d; the executor carries on: a bug, please report it with this"
                         " trace)", text, count, exc_info=err)
        elif say:
            logger.error("%s again (callback failure %d; its trace logged before)", text, count)
        return f"{text} (logged with its trace; counted in /diagnostics: callback_failures)"

    def snapshot(self) -> tuple[int, str, float]:
        """How many callbacks failed, the last one ("" none) and how long ago (s; inf: none)."""
        with self._lock:
            return self._count, self._last, time.monotonic() - self._at if self._count else math.inf


def supervise(node: Node, failures: CallbackFailures) -> int:
    """Wrap every service, timer and subscription callback of ``node`` not wrapped yet (see the
    module's docstring): an unexpected exception is recorded in ``failures`` and a service answers
    a failed response naming itself. Returns how many were wrapped now."""
    wrapped = 0
    for entity in (*node.services, *node.timers, *node.subscriptions):
        callback = entity.callback
        if getattr(callback, "__supervised__", False):
            continue
        if hasattr(entity, "srv_type"):
            entity.callback = _service_callback(entity, callback, failures)
        elif hasattr(entity, "msg_type"):
            entity.callback = _subscription_callback(entity, callback, failures)
        else:
            entity.callback = _timer_callback(node, callback, failures)
        wrapped += 1
    return wrapped


def failed_response(srv_type: Any, text: str, request: Any = None, partial: Any = None) -> Any:
    """A fresh response of ``srv_type``: ``success`` False and ``message`` ``text`` where it has them.
    A parameter service's as rclpy's parameter service answers what it cannot do (its
    ``_set_parameters_callback``): SetParameters the results rclpy had made (``partial``: those
    parameters were set) and a failed one, ``text`` the reason, for each other parameter of
    ``request`` (a client such as ``ros2 param set`` reads ``results[0]``); SetParametersAtomically
    a failed result; the get, describe and list services no values, as rclpy answers a name it does
    not know."""
    response = srv_type.Response()
    if hasattr(response, "success"):
        response.success = False
    if hasattr(response, "message"):
        response.message = text
    if srv_type is SetParametersAtomically:
        response.result = SetParametersResult(successful=False, reason=text)
    elif srv_type is SetParameters and request is not None:
        done = list(getattr(partial, "results", []))[:len(request.parameters)]
        response.results = done + [SetParametersResult(successful=False, reason=text)
                                   for _ in request.parameters[len(done):]]
    return response


def _mark(wrapper: Callable[..., Any]) -> Callable[..., Any]:
    wrapper.__supervised__ = True  # type: ignore[attr-defined]
    return wrapper


def _service_callback(service: Any, callback: Callable[..., Any], failures: CallbackFailures) -> Callable[..., Any]:
    where = f"service {service.service_name}"
    response_type = service.srv_type.Response

    def answered(response: Any, request: Any) -> Any:
        if isinstance(response, response_type):
            return response
        return failed_response(service.srv_type, failures.record(where, TypeError(f"the callback returned {response!r}")),
                               request)

    if inspect.iscoroutinefunction(callback):
        async def call_async(request: Any, response: Any) -> Any:
            try:
                return answered(await callback(request, response), request)
            except Exception as err:
                return failed_response(service.srv_type, failures.record(where, err), request, response)
        return _mark(call_async)

    def call(request: Any, response: Any) -> Any:
        try:
            return answered(callback(request, response), request)
        except Exception as err:
            return failed_response(service.srv_type, failures.record(where, err), request, response)
    return _mark(call)


def _subscription_callback(subscription: Any, callback: Callable[..., Any],
                           failures: CallbackFailures) -> Callable[..., Any]:
    where = f"subscription {subscription.topic_name}"
    if not _takes_one(callback):  # rclpy gives the message info too (its own test of the callback's arity)
        def with_info(msg: Any, info: Any) -> None:
            try:
                callback(msg, info)
            except Exception as err:
                failures.record(where, err)
        return _mark(with_info)

    def on_message(msg: Any) -> None:
        try:
            callback(msg)
        except Exception as err:
            failures.record(where, err)
    return _mark(on_message)


def _takes_one(callback: Callable[..., Any]) -> bool:
    try:
        inspect.signature(callback).bind(object())
    except TypeError:
        return False
    return True


def _timer_callback(node: Node, callback: Callable[..., Any], failures: CallbackFailures) -> Callable[..., Any]:
    where = f"timer {node.get_name()}: {getattr(callback, '__qualname__', repr(callback))}"
    if inspect.iscoroutinefunction(callback):
        async def tick_async() -> None:
            try:
                await callback()
            except Exception as err:
                failures.record(where, err)
        return _mark(tick_async)

    def tick() -> None:
        try:
            callback()
        except Exception as err:
            failures.record(where, err)
    return _mark(tick)


def spin_until(executor: Executor, stop: threading.Event, poll_s: float = POLL_S,
               failures: CallbackFailures | None = None) -> None:
    """Spin ``executor`` until ``stop`` is set or the context is shut down by someone else,
    looking at both every ``poll_s`` at the latest (sooner where the stopper gives the executor work).
    A callback's exception that reaches here (one :func:`supervise` did not wrap) is logged, counted
    in ``failures`` (None: those of the executor's driver node, when it has one then, else of this
    loop alone) and the executor spins on: a failure never ends the loop. A failure that comes
    back at the next step, none passing between (a timer that raises each time, or not a
    callback's at all: a node destroyed while still added), is waited on for ``poll_s`` before
    the next step, so that the loop never turns busy on a real-time core; each is counted.

    The EventsExecutor dispatches everything that comes in ``poll_s`` in one call into C++
    (``spin_until_future_complete`` of a future nobody completes, a new one each time: that call
    adds a callback to it): ``spin_once`` would come back to Python after every single callback,
    and the loop's own checks were about 7 % of the hot thread's interpreter time in the six-drive
    profile (docs/performance.md)."""
    own = CallbackFailures()
    if isinstance(executor, Executor):
        def step() -> None:
            executor.spin_once(timeout_sec=poll_s)
    else:  # rclpy's EventsExecutor (C++; not an rclpy Executor subclass)
        def step() -> None:
            executor.spin_until_future_complete(Future(), timeout_sec=poll_s)
    failing = 0  # steps in a row that raised
    while not stop.is_set() and executor.context.ok():
        try:
            step()
            failing = 0
        except ExternalShutdownException:
            return
        except Exception as err:  # a callback's, re-raised by the executor: logged, counted, spun on
            counted = failures if failures is not None else next((n.callback_failures for n in executor.get_nodes()
                                        if isinstance(getattr(n, "callback_failures", None), CallbackFailures)), own)
            counted.record(f"a callback of {type(executor).__name__}", err,
                           logged=not isinstance(executor, Executor))  # the EventsExecutor logged it with its trace
            failing += 1
            if failing > 1:
                stop.wait(poll_s)  # failing at every step: never a busy loop on a real-time core


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

    def __init__(self, executor: Executor, name: str, failures: CallbackFailures | None = None) -> None:
        self.executor = executor
        self._stop = threading.Event()
        # rclpy's executors leave their wait at a task (stop() gives one); the EventsExecutor's timed spin does not
        poll_s = IDLE_POLL_S if isinstance(executor, Executor) else POLL_S
        self._thread = threading.Thread(target=spin_until, args=(executor, self._stop, poll_s, failures), daemon=True,
                                        name=name)
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


__all__ = ["EXECUTORS", "IDLE_POLL_S", "POLL_S", "CallbackFailures", "SpinThread", "StopSignal", "failed_response",
           "give_work", "go_realtime", "init", "make_executor", "spin_node", "spin_until", "supervise"]
