"""rovercan: the command-line tool of the CANopen / CiA 402 motor driver stack.

What lives where: :mod:`rovercan.entry` (the console entry point, free of heavy imports; also
``python -m rovercan``, :mod:`rovercan.__main__`), :mod:`rovercan.cli` (the parser),
:mod:`rovercan.bench` (bench commands, one module per family), :mod:`rovercan.sim_cli` (``sim``)
with :mod:`rovercan.sim_processes` (its drives in processes of their own), :mod:`rovercan.demo`
(``demo``), :mod:`rovercan.launch` (``launch``), :mod:`rovercan.audit` (``audit``),
:mod:`rovercan.decode` (one frame as CANopen text), :mod:`rovercan.argtypes` (checked numbers), :mod:`rovercan.exits` (the exit codes).

Owner: the CLI's main thread, throughout (a command's own threads say so in their module).
"""

__version__ = "0.1.0"
