"""The bench commands of ``rovercan``: thin functions over the library and python-can.

Every command takes python-can's standard bus arguments (``-i/-c/-b/--bus-kwargs``); a
command that addresses a drive also takes ``--config FILE`` or ``--eds FILE`` with
``--counts-per-rev`` / ``--gear-ratio``. Human tables by default, ``--json`` for scripts.

What lives where (each module has its commands and their ``add_parsers``):

- :mod:`.common`: bus and drive arguments, opening the bus, SDO helpers, ``emit``, ``CliError``
- :mod:`.nodes`: scan, info, sdo, save, nmt (CiA 301 services to one node)
- :mod:`.motion`: enable, disable, fault-reset, home, move, jog, step-test (through the driver)
- :mod:`.traffic`: monitor, record, replay, decode, incident
- :mod:`.views`: the bus as ROS 2 messages for :mod:`.traffic` (MCAP, the live Foxglove view),
  :mod:`.liveview` the live view's server (a bounded queue per client)
- :mod:`.checks`: safety-check, check, plan, can-up

Owner: the CLI's main thread (a command that starts threads names them in its module).
"""

from rovercan.bench.checks import can_up_commands
from rovercan.bench.common import CliError, emit, open_bus

__all__ = ["CliError", "can_up_commands", "emit", "open_bus"]
