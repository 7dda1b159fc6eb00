"""The console entry point of ``rovercan``, kept free of heavy imports: a Ctrl-C at any moment,
while the interpreter still imports python-can, canopen and the rest, ends with one line and exit
130 instead of a KeyboardInterrupt traceback. Once a command runs, :func:`rovercan.cli.main`
handles the signals itself (drives stopped, one line).

The handler is installed as this module is imported: the console script imports it and only then
calls :func:`main`, and a Ctrl-C in between (seen under load) would otherwise be Python's own
KeyboardInterrupt outside any ``try``.

Owner: the CLI's main thread.
"""

from __future__ import annotations

import os
import signal
import sys

INTERRUPTED = "rovercan: interrupted (Ctrl-C)"


def _interrupted(signum: int, frame: object) -> None:
    """Ends the process at once: nothing has touched a bus before the command's own handlers. Not
    SystemExit: a signal handled while the interpreter runs a callback of its own (an import
    lock's weakref callback, seen under load) has its exception printed as "Exception ignored"
    with a traceback, and the command then ran on as if no Ctrl-C had come."""
    sys.stderr.write(INTERRUPTED + "\n")
    sys.stderr.flush()
    os._exit(130)


signal.signal(signal.SIGINT, _interrupted)


def main() -> int:
    try:
        from rovercan.cli import main as cli_main

        return cli_main()
    except KeyboardInterrupt:  # a handler of Python's own, restored by a library: the same line
        print(INTERRUPTED, file=sys.stderr)
        return 130
