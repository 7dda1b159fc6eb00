"""One CiA 402 drive on a CANopen network: boot, state machine, commands, PDO state.

A drive is composed of parts, as canopen's ``RemoteNode`` composes ``sdo``, ``pdo`` and ``nmt``:
each part owns its state, is handed only the ports it needs and offers methods; no part writes
another's attributes. Hot path: TPDO callbacks (canopen's notifier thread) unpack with one
precompiled struct and publish one immutable value; a command is decided and its frame sent
by the command channel under its lock. Every failure raises a typed error from
:mod:`can_config.errors`; nothing is logged and swallowed.

What lives where (each module's docstring names the thread that owns its state):

- :mod:`.state`: the state cache, the receive thread's only room (TPDO, heartbeat, EMCY), with
  :mod:`.position` (which position samples to believe), :mod:`.tpdo` (one TPDO's values, decoded
  alike for the recorder's view) and :mod:`.values` (what it publishes)
- :mod:`.verdict`: one verdict per drive, judged once from what the driver knows (pure); every
  consumer reads it, :mod:`.health` (the grade /diagnostics gives a drive and a bus) among them,
  with :mod:`.frameloss` (its TPDOs and heartbeats expected against received)
- :mod:`.ledger`: the supervisor's judgements of each drive and bus (its one writer) and the NMT
  ledger, which the parts read and post to
- :mod:`.sdo`: the SDO port, bounded, one typed codec; the objects no tool may write
- :mod:`.channel`: the command channel, owner of the controlword, the targets, the generation
  and the busy registry (:mod:`.busy`): the one way out for a controlword or a set-point, and
  a stop always wins; with :mod:`.setpoint` (the profile-position set-point handshake it and the
  receive thread share)
- :mod:`.power`: the CiA 402 power state machine (enable, stops, recover) and the mode switch,
  every controlword sent through the channel
- :mod:`.limits`: the stopping-distance limit guard and the velocity watchdog
- :mod:`.motion`: motion commands, one family per operation mode, with :mod:`.trajectory` (the
  streamed move's set-points, pure generators)
- :mod:`.homing`: homing
- :mod:`.hostwatch`: the drive's watch of the host (heartbeat consumer, node guarding) and the
  frames the supervisor sends a drive it stops hearing or loses to another master
- :mod:`.boot`: boot as a table of steps; re-configuration after a reset
- :mod:`.facade`: :class:`Drive`, the parts composed (``drive.cache``, ``drive.power``, ...)
  and the user's small API
- :mod:`.constants`: timeouts and fixed codes
"""

from motor_driver.drive.constants import SDO_TRANSFER_TIMEOUTS, SDO_UPLOAD_MAX_BYTES
from motor_driver.drive.facade import Drive
from motor_driver.drive.hostwatch import host_consumer_entry
from motor_driver.drive.sdo import PROTECTED_OBJECTS, protected_reason
from motor_driver.drive.values import DriveState, Emcy

__all__ = ["PROTECTED_OBJECTS", "SDO_TRANSFER_TIMEOUTS", "SDO_UPLOAD_MAX_BYTES", "Drive", "DriveState", "Emcy",
           "host_consumer_entry", "protected_reason"]
