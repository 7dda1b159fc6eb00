"""Bridge Python logging (the core's loggers) to a node's rclpy logger."""

from __future__ import annotations

import logging

from rclpy.node import Node


class RclpyLogHandler(logging.Handler):
    """Forwards records of the core's loggers to ``node.get_logger()``."""

    def __init__(self, node: Node) -> None:
        super().__init__()
        self._logger = node.get_logger()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = f"[{record.name}] {record.getMessage()}"
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


def bridge_core_logging(node: Node, level: int = logging.INFO) -> RclpyLogHandler:
    handler = RclpyLogHandler(node)
    for name in ("motor_driver", "can_config", "virtual_can"):
        core = logging.getLogger(name)
        core.addHandler(handler)
        core.setLevel(level)
    # python-can's socketcand client warns on every TCP read that splits a line: noise
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
    return handler


def unbridge(handler: RclpyLogHandler) -> None:
    for name in ("motor_driver", "can_config", "virtual_can"):
        logging.getLogger(name).removeHandler(handler)
