"""Bridge Python logging to a node's rclpy logger: the core's loggers, the nodes' own module
loggers (``nodes.*``: a worker's line, a refused goal) and the libraries' (canopen's "Transfer
aborted by client ...", python-can's). A logger with no handler of its own would otherwise reach
Python's last-resort handler, which writes to the terminal outside the ROS log; so would a
thread's uncaught exception (Python prints it): while bridged, it is logged instead. A record's
traceback is in its line.

Each record is said once: rclpy prints what it is given, so a process that also prints Python's
records (the CLI's root handler, in ``rovercan demo``) puts :class:`Unbridged` on that handler,
which passes only the records the bridge did not forward. The canopen library's records are
bridged at the node's level, at their own level (its aborts of this driver's own transfers are
DEBUG: :mod:`motor_driver.bus.library_log`); python-can's from WARNING (its INFO is its internals).

Owner: the handler is called on the thread that logs; it keeps no state but the node's logger."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from rclpy.node import Node


class RclpyLogHandler(logging.Handler):
    """Forwards records of the core's loggers to ``node.get_logger()``."""

    def __init__(self, node: Node) -> None:
        super().__init__()
        self._logger = node.get_logger()

    def emit(self, record: logging.LogRecord) -> None:
        setattr(record, BRIDGED, True)  # said by rclpy: Unbridged keeps it off another console
        try:
            text = f"[{record.name}] {record.getMessage()}"
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            if record.levelno >= logging.ERROR:
                self._logger.error(text)
            elif record.levelno >= logging.WARNING:
                self._logger.warning(text)
            elif record.levelno >= logging.INFO:
                self._logger.info(text)
            else:
                self._logger.debug(text)
        except Exception:  # logging must never raise into the caller
            self.handleError(record)


#: The attribute a record forwarded to rclpy carries (True).
BRIDGED = "rovercan_bridged"


class Unbridged(logging.Filter):
    """On a handler that prints beside rclpy (the CLI's root handler in ``rovercan demo``): only
    the records the bridge did not forward, so that each event is one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not getattr(record, BRIDGED, False)


@contextmanager
def consoles_print_once() -> Iterator[None]:
    """While inside: :class:`Unbridged` on the root logger's handlers (a CLI's console), which then
    leave out what rclpy prints already."""
    once = Unbridged()
    consoles = list(logging.getLogger().handlers)
    for handler in consoles:
        handler.addFilter(once)
    try:
        yield
    finally:
        for handler in consoles:
            handler.removeFilter(once)


#: Loggers bridged at the node's level: the core's and the nodes' own.
OWN_LOGGERS = ("motor_driver", "can_config", "virtual_can", "nodes")
#: The libraries' loggers and the level they are bridged from: canopen's at the node's (None), each
#: record at its own level (the aborts this driver causes on purpose are DEBUG:
#: motor_driver.bus.library_log); python-can's from WARNING (its INFO and DEBUG are its internals).
LIBRARY_LOGGERS: dict[str, int | None] = {"canopen": None, "can": logging.WARNING}


def bridge_core_logging(node: Node, level: int = logging.INFO) -> RclpyLogHandler:
    handler = RclpyLogHandler(node)
    for name in OWN_LOGGERS:
        core = logging.getLogger(name)
        core.addHandler(handler)
        core.setLevel(level)
    for name, least in LIBRARY_LOGGERS.items():
        library = logging.getLogger(name)
        library.addHandler(handler)
        library.setLevel(level if least is None else max(level, least))
    # python-can's socketcand client warns on every TCP read that splits a line: noise
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    if threading.excepthook is not _log_thread_exception:
        _hooks.append(threading.excepthook)
        threading.excepthook = _log_thread_exception
    return handler


_hooks: list[object] = []  # the thread exception hook the bridge replaced (restored by unbridge)


def _log_thread_exception(args: threading.ExceptHookArgs) -> None:
    """A thread's uncaught exception, logged (Python's own hook prints it to the terminal)."""
    if args.exc_type is SystemExit or args.exc_value is None:
        return
    name = args.thread.name if args.thread is not None else "?"
    logging.getLogger(__name__).error("thread %s ended: %s: %s", name, args.exc_type.__name__, args.exc_value,
                                      exc_info=args.exc_value)


def unbridge(handler: RclpyLogHandler) -> None:
    for name in (*OWN_LOGGERS, *LIBRARY_LOGGERS):
        logging.getLogger(name).removeHandler(handler)
    if threading.excepthook is _log_thread_exception and _hooks:
        threading.excepthook = _hooks.pop()  # type: ignore[assignment]
