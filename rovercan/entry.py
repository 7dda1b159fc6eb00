"""The console entry point of ``rovercan``, kept free of heavy imports: a Ctrl-C at any moment,
while the interpreter still imports python-can, canopen and the rest, ends with one line and exit
130 instead of a KeyboardInterrupt traceback. Once a command runs, :func:`rovercan.cli.main`
handles the signals itself (drives stopped, one line)."""

from __future__ import annotations

import sys


def main() -> int:
    try:
        from rovercan.cli import main as cli_main

        return cli_main()
    except KeyboardInterrupt:
        print("rovercan: interrupted (Ctrl-C)", file=sys.stderr)
        return 130
