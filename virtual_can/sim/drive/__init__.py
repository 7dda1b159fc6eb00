"""A simulated CiA 402 servo drive, written from CiA 301 / CiA 402 on its own.

What lives where (every class is a layer on the one below; all on the runner thread):

- :mod:`.model`: states, bits, the pure transition, motor parameters, PDO layout, fault switches
- :mod:`.base`: every attribute of a drive, declared once; units; helpers
- :mod:`.errors`: EMCY producer, error register and history
- :mod:`.statemachine`: the CiA 402 state machine and statusword
- :mod:`.plant`: set-point generator per mode, servo loops, motor and load, limits
- :mod:`.comm`: NMT, SDO, PDO engine, heartbeat consumer, node guarding
- :mod:`.facade`: :class:`SimulatedDrive`, with the tick
"""

from virtual_can.sim.drive.facade import SimulatedDrive
from virtual_can.sim.drive.model import LIMIT_TOLERANCE_REV, Faults, MotorParams, State, next_state

__all__ = ["LIMIT_TOLERANCE_REV", "Faults", "MotorParams", "SimulatedDrive", "State", "next_state"]
