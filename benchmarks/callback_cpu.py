"""The measured node with each callback's CPU counted: ``python benchmarks/callback_cpu.py OUT.json
[--ros-args ...]`` runs ``nodes.rover_driver`` as deployed, with every subscription's and timer's
callback (as ``nodes.process.spinning.supervise`` wraps them) adding the CPU of its thread
(``CLOCK_THREAD_CPUTIME_ID``) to its name's account. Each SIGUSR1 takes a snapshot of the accounts
and of the main thread's CPU; OUT.json gets the snapshots when the process ends.

The stack run uses it with ``$ROVERCAN_CALLBACK_CPU=OUT.json`` (a snapshot at each end of its
window: ``cpu_by_callback``). py-spy's ``--gil`` samples had shown a fifth of the main thread's CPU
(its Python frames while it held the interpreter); these accounts split all of it into the node's
callbacks and what rclpy's executor spends around them. Not for deployment: two clock reads a
callback.
"""

from __future__ import annotations

import functools
import inspect
import json
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from nodes import rover_driver
from nodes.process import spinning

ACCOUNTS: dict[str, int] = {}
SNAPSHOTS: list[dict[str, Any]] = []


def counted(where: str, callback: Callable[..., Any]) -> Callable[..., Any]:
    """``callback`` adding its thread's CPU (ns) to ``ACCOUNTS[where]``; its signature kept (the
    wrapper of a subscription asks how many arguments it takes)."""
    if inspect.iscoroutinefunction(callback):
        return callback  # a coroutine's CPU is spent where the executor resumes it: not counted
    clock = time.thread_time_ns

    @functools.wraps(callback)
    def run(*args: Any) -> Any:
        t0 = clock()
        try:
            return callback(*args)
        finally:
            ACCOUNTS[where] = ACCOUNTS.get(where, 0) + clock() - t0
    return run


def install() -> None:
    subscription, timer = spinning._subscription_callback, spinning._timer_callback

    def counted_subscription(sub: Any, callback: Callable[..., Any], failures: Any) -> Callable[..., Any]:
        return subscription(sub, counted(f"subscription {sub.topic_name}", callback), failures)

    def counted_timer(node: Any, callback: Callable[..., Any], failures: Any) -> Callable[..., Any]:
        name = f"timer {node.get_name()}: {getattr(callback, '__qualname__', repr(callback))}"
        return timer(node, counted(name, callback), failures)

    spinning._subscription_callback = counted_subscription  # type: ignore[assignment]
    spinning._timer_callback = counted_timer  # type: ignore[assignment]

    def snapshot(_signum: int, _frame: Any) -> None:  # runs on the main thread, between two callbacks
        SNAPSHOTS.append({"t": time.monotonic(), "main_cpu_ns": time.thread_time_ns(), "accounts": dict(ACCOUNTS)})

    assert threading.current_thread() is threading.main_thread()
    signal.signal(signal.SIGUSR1, snapshot)


def main() -> int:
    out = Path(sys.argv[1])
    install()
    try:
        return rover_driver.main(sys.argv[2:])
    finally:
        out.write_text(json.dumps(SNAPSHOTS))


def window(snapshots: list[dict[str, Any]]) -> dict[str, Any]:
    """The first and last snapshots' difference, as shares of a core: each callback's, their sum,
    and the main thread's CPU outside them (rclpy's executor: taking messages, dispatching). The
    accounts are of every thread's callbacks; on the rover's node the hot executor's, on the main thread."""
    if len(snapshots) < 2:
        return {}
    first, last = snapshots[0], snapshots[-1]
    wall = last["t"] - first["t"]
    by = {k: (v - first["accounts"].get(k, 0)) / 1e9 / wall for k, v in last["accounts"].items()}
    inside = sum(by.values())
    main_cpu = (last["main_cpu_ns"] - first["main_cpu_ns"]) / 1e9 / wall
    return {"cpu_by_callback": {k: round(v, 4) for k, v in sorted(by.items(), key=lambda kv: -kv[1]) if v >= 0.0005},
            "cpu_in_callbacks": round(inside, 4), "cpu_main_thread": round(main_cpu, 4),
            "cpu_main_outside_callbacks": round(main_cpu - inside, 4)}


if __name__ == "__main__":
    sys.exit(main())
