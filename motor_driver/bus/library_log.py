"""The canopen library's log records at the level they have for this driver: canopen logs at
ERROR every SDO transfer its client aborts ("Transfer aborted by client with code 0x05040000" on
each timeout of a lost drive), and the client is always this driver: it aborts on purpose (no
answer in time, an answer not to its request, an upload past its bound) and raises the transfer's
error to its caller, which says it at the level it deserves (an SdoTimeoutError, a refused
service, a lost drive's one warning). That line is DEBUG here. Every other canopen record keeps
its level.

No state of its own: :func:`install` (idempotent; called where a bus is opened,
:mod:`motor_driver.bus.connect`) puts :class:`CanopenLevels` on canopen's SDO client logger; the
filter runs on the thread that logs.
"""

from __future__ import annotations

import logging

#: The logger of canopen's SDO client (``canopen/sdo/client.py``).
SDO_CLIENT_LOGGER = "canopen.sdo.client"
#: canopen's records that this driver says itself, by the start of their message, and their level here.
DEMOTED = (("Transfer aborted by client", logging.DEBUG),)


class CanopenLevels(logging.Filter):
    """A record of :data:`DEMOTED` at its level here, passed on only where its logger logs that
    level (a logger's own level is checked before its filters: the demoted record is checked again)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        for start, level in DEMOTED:
            if message.startswith(start) and record.levelno > level:
                record.levelno, record.levelname = level, logging.getLevelName(level)
                return logging.getLogger(record.name).isEnabledFor(level)
        return True


def install() -> None:
    """:class:`CanopenLevels` on canopen's SDO client logger, once."""
    sdo = logging.getLogger(SDO_CLIENT_LOGGER)
    if not any(isinstance(f, CanopenLevels) for f in sdo.filters):
        sdo.addFilter(CanopenLevels())


__all__ = ["DEMOTED", "SDO_CLIENT_LOGGER", "CanopenLevels", "install"]
