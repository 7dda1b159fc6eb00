"""One CiA 402 drive on a CANopen network: boot, state machine, commands, PDO state.

A drive is composed of parts, as canopen's ``RemoteNode`` composes ``sdo``, ``pdo`` and ``nmt``:
each part owns its state, is handed only the ports it needs and offers methods; no part writes
another's attributes. Hot path: TPDO callbacks (canopen's notifier thread) unpack with one
precompiled struct and publish one immutable value; a command is decided and its frame sent
by the command channel under its lock. Every failure raises a typed error from
:mod:`can_config.errors`; nothing is logged and swallowed.

What lives where: a room for each thread that owns state, named after its owner (each module's
docstring names the thread and keeps it true), and the drive's face at the top, where every
consumer reads it:

- :mod:`.received`: what the bus's receive thread owns: the state cache (TPDO, heartbeat, EMCY),
  which position samples to believe, one TPDO's values
- :mod:`.command`: what the command channel owns, under its lock: the controlword, the targets,
  the generation and the busy registry, the set-point handshake; and the parts that command
  through it (power, limits, motion, homing): the one way out, and a stop always wins
- :mod:`.setup`: what the bus's worker owns while the drive is not booted: boot as a table of
  steps, and the host watch it configures
- the face, immutable or pure, read from any thread: :mod:`.verdict` (one verdict per drive,
  judged once), :mod:`.values` (what the cache publishes: :class:`DriveState`, the values with
  their verdict), :mod:`.facade` (:class:`Drive`: the parts composed, ``drive.cache``,
  ``drive.power``, ..., and the user's small API)
- shared by the rooms: :mod:`.ledger` (the supervisor's records of each drive and bus, its
  thread their one writer; the parts read them and post to it), :mod:`.sdo` (the SDO port: its
  own lock serialises every transfer, whatever thread asks), :mod:`.constants` (timeouts and
  fixed codes, read only)

The rooms build on each other in one order, received, command, setup, and the face's modules
import none of them but the facade (tests/test_module_maps.py holds the order and its one
crossing, with its reason).
"""

from motor_driver.drive.constants import SDO_TRANSFER_TIMEOUTS, SDO_UPLOAD_MAX_BYTES
from motor_driver.drive.facade import Drive
from motor_driver.drive.sdo import PROTECTED_OBJECTS, protected_reason
from motor_driver.drive.setup.hostwatch import host_consumer_entry
from motor_driver.drive.values import DriveState, Emcy

__all__ = ["PROTECTED_OBJECTS", "SDO_TRANSFER_TIMEOUTS", "SDO_UPLOAD_MAX_BYTES", "Drive", "DriveState", "Emcy",
           "host_consumer_entry", "protected_reason"]
