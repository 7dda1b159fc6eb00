"""rovercan: the command-line tool of the CANopen / CiA 402 motor driver stack."""

__version__ = "0.1.0"
