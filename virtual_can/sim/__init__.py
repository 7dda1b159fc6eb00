"""Simulated CiA 402 drives (see :mod:`virtual_can.sim.drive`)."""

from virtual_can.sim.drive import MotorParams, SimulatedDrive, State
from virtual_can.sim.runner import DriveSimulator

__all__ = ["DriveSimulator", "MotorParams", "SimulatedDrive", "State"]
