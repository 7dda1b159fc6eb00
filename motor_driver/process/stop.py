"""Process stop requests: SIGINT, SIGTERM and SIGHUP.

Two ways, one per kind of program:

- :class:`StopSignal` sets an event instead of raising. Long-running entry points (the
  simulator, ROS nodes, ``record``) wait on the event and then tear down in one order they
  own: drives to a safe state, threads joined, buses closed.
- :func:`stop_on_signals` raises :class:`StopRequested` in the main thread, wherever it is
  (waiting for a move, sleeping in a jog loop), so the ``with`` blocks around it unwind and a
  ``MotorDriver``'s ``close()`` quick-stops and disables every drive before the process exits.
  The API's one call for a script::

      with stop_on_signals() as stop, MotorDriver(load_config("rover.yaml")) as driver:
          ...                      # SIGTERM / SIGINT / SIGHUP: drives stopped, block left
      if stop.signum is not None:  # the block was left on a signal
          ...

  Only the first signal raises; a second one during the teardown is ignored, so the stop
  cannot be interrupted half-way. A first one raised inside an interpreter callback (where an
  exception is only printed) is sent again until it reaches the block. SIGKILL, a hang or a power cut run no handler at all: for
  those the drives watch the host's heartbeat themselves (see the README, Safety).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

logger = logging.getLogger(__name__)

#: What systemd / docker stop (SIGTERM), Ctrl+C (SIGINT) and a closed terminal (SIGHUP) send.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


#: After a stop lost in an interpreter callback, its signal is sent again this much later (s).
REDELIVER_S = 0.05


class StopSignal:
    """Context manager: while active, SIGINT/SIGTERM/SIGHUP set :attr:`event` (main thread only)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signum: int | None = None
        self._old: dict[int, object] = {}

    def __enter__(self) -> StopSignal:
        for sig in STOP_SIGNALS:
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.signum = signum
        self.event.set()

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._old.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._old.clear()


class StopRequested(BaseException):
    """Raised in the main thread by :func:`stop_on_signals` on a stop signal. A BaseException,
    like KeyboardInterrupt, so that ``except Exception`` in user code does not swallow it."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


class _Stop:
    signum: int | None = None


@contextmanager
def stop_on_signals() -> Iterator[_Stop]:
    """While active (main thread), SIGINT/SIGTERM/SIGHUP raise :class:`StopRequested`; the
    block is left (its ``with`` exits run) and the exception ends here: ``.signum`` tells."""
    state = _Stop()

    def handle(signum: int, frame: FrameType | None) -> None:
        if state.signum is None:  # the first one stops; later ones must not break the teardown
            state.signum = signum
            raise StopRequested(signum)

    previous_hook = sys.unraisablehook

    def dropped(unraisable: Any) -> None:
        """The stop raised while the interpreter ran a callback of its own (a weakref's, a
        finalizer's) is printed as "Exception ignored" and lost, and the block would run on with
        every later signal ignored: the signal is sent again, from a thread once this hook has
        returned (a handler run inside the hook would be lost the same way), to reach the block."""
        if isinstance(unraisable.exc_value, StopRequested) and state.signum is not None:
            signum, state.signum = state.signum, None
            again = threading.Timer(REDELIVER_S, os.kill, (os.getpid(), signum))
            again.daemon = True
            again.start()
            return
        previous_hook(unraisable)

    old = {sig: signal.signal(sig, handle) for sig in STOP_SIGNALS}
    sys.unraisablehook = dropped
    try:
        yield state
    except StopRequested:
        pass
    finally:
        sys.unraisablehook = previous_hook
        for sig, handler in old.items():
            signal.signal(sig, handler)


def teardown(what: str, steps: Iterable[Callable[[], object]]) -> None:
    """Each of ``steps`` in order, whatever an earlier one raised: a teardown that stops half-way
    leaves buses open, threads running and nodes in the graph (a lifecycle node's cleanup then
    said all was released, and every configure after it met its own SYNC as another master's).
    A step that raises is logged with its trace; the first exception is raised again at the end."""
    first: Exception | None = None
    for step in steps:
        try:
            step()
        except Exception as err:
            logger.exception("%s: %s failed; the rest of the teardown goes on", what, getattr(step, "__name__", step))
            first = first or err
    if first is not None:
        raise first
