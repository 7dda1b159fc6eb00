"""Bridge Python logging to a node's rclpy logger: the core's loggers, the nodes' own module
loggers (``nodes.*``: a worker's line, a refused goal) and the libraries' (canopen's "Transfer
aborted by client ...", python-can's). A logger with no handler of its own would otherwise reach
Python's last-resort handler, which writes to the terminal outside the ROS log; so would a
thread's uncaught exception (Python prints it): while bridged, it is logged instead. A record's
traceback is in its line."""

from __future__ import annotations

import logging
import threading

from rclpy.node import Node


class RclpyLogHandler(logging.Handler):
    """Forwards records of the core's loggers to ``node.get_logger()``."""

    def __init__(self, node: Node) -> None:
        super().__init__()
        self._logger = node.get_logger()

    def emit(self, record: logging.LogRecord) -> None:
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


#: Loggers bridged at the node's level: the core's and the nodes' own.
OWN_LOGGERS = ("motor_driver", "can_config", "virtual_can", "nodes")
#: The libraries' loggers, bridged from WARNING (their INFO and DEBUG are their internals).
LIBRARY_LOGGERS = ("canopen", "can")


def bridge_core_logging(node: Node, level: int = logging.INFO) -> RclpyLogHandler:
    handler = RclpyLogHandler(node)
    for name in OWN_LOGGERS:
        core = logging.getLogger(name)
        core.addHandler(handler)
        core.setLevel(level)
    for name in LIBRARY_LOGGERS:
        library = logging.getLogger(name)
        library.addHandler(handler)
        library.setLevel(max(level, logging.WARNING))
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
    for name in OWN_LOGGERS + LIBRARY_LOGGERS:
        logging.getLogger(name).removeHandler(handler)
    if threading.excepthook is _log_thread_exception and _hooks:
        threading.excepthook = _hooks.pop()  # type: ignore[assignment]
