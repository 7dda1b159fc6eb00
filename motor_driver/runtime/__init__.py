"""The driver at run time: every bus and drive of a config started, supervised and stopped, and
what the driver has judged of each.

What lives where: :mod:`.driver` (:class:`MotorDriver`: start, safe stop, close), :mod:`.supervisor`
(the period that never blocks: heartbeats, watchdog, limit guard, another master) with
:mod:`.supervise_bus` (its work on buses: the host heartbeat, connection, SYNC, reconnect).

Owner: the supervisor thread (``rovercan-supervisor``) alone writes the ledger of its judgements
(:mod:`motor_driver.drive.ledger`); each bus's worker runs boots and reconnects and reports
their results to it; the caller's thread starts and closes.
"""
