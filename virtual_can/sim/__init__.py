"""Simulated CiA 402 drives, written from the standard on their own.

What lives where: :mod:`.drive` (one drive, layer on layer from the CiA 402 model up to
NMT/SDO/PDO), :mod:`.objects` (its object dictionary), :mod:`.sdo` (its SDO server) and
:mod:`.runner` (the one thread that serves every drive on a bus).
"""

from virtual_can.sim.drive import MotorParams, SimulatedDrive, State
from virtual_can.sim.runner import DriveSimulator

__all__ = ["DriveSimulator", "MotorParams", "SimulatedDrive", "State"]
