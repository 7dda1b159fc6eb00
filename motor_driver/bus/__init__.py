"""One CAN bus of the driver: opening it, the python-can bus and its canopen network, the SYNC
on the bus daemon's timer, what its traffic and its kernel link say, what a config makes of its
load, and the one module that leans on a dependency's internals.

What lives where: :mod:`.connect` (python-can's bus from config, a socketcand server waited for),
:mod:`.handle` (one bus: its network, SYNC producer and worker thread), :mod:`.traffic` (bus
statistics and evidence of another master), :mod:`.link` (the kernel's view of the link:
controller state, error counters), :mod:`.cyclic` (a cyclic frame on the daemon's timer),
:mod:`.load` (bus-load planning, pure), :mod:`.sdo_client` (an SDO client that takes only its own
answers), :mod:`.adapters` (every reach into python-can's or canopen's internals), :mod:`.library_log`
(canopen's log records at their level here).

Owner: each module's docstring names its threads; the bus's receive thread (python-can's
notifier) feeds :mod:`.traffic`, the bus's worker runs the blocking jobs of :mod:`.handle`.
"""
