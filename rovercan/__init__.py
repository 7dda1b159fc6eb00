"""rovercan: the command-line tool of the CANopen / CiA 402 motor driver stack.

What lives where: :mod:`rovercan.cli` (the parser, sim, demo, launch), :mod:`rovercan.bench`
(bench commands, one module per family), :mod:`rovercan.audit`, :mod:`rovercan.decode`,
:mod:`rovercan.launch`, :mod:`rovercan.argtypes`."""

__version__ = "0.1.0"
