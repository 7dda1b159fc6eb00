"""A driver in a process of its own, for the host-loss tests: boots a config, enables every
drive and commands a velocity until it is killed (drives without profile velocity stay enabled
and still). Prints READY when every drive runs.

    python tests/clients/hold_velocity.py CONFIG VELOCITY_DEG_S [--helper] [--keep-commanding]

``--helper`` runs under ``stop_on_signals()``, the API's documented way to stop the drives on
SIGTERM/SIGINT/SIGHUP; without it the process has Python's default signal handling.
``--keep-commanding``: an application that goes on through a lost bus, as a ROS node does: a
refused command is printed (``REFUSED`` and the reason, once per reason in a row) and the next
one is sent; it never enables a drive again.
"""

from __future__ import annotations

import logging
import sys
import time
from contextlib import ExitStack, nullcontext

from can_config import load_config
from can_config.errors import MotorError
from motor_driver import MotorDriver, stop_on_signals


def main() -> int:
    config = load_config(sys.argv[1])
    velocity = float(sys.argv[2])
    helper = "--helper" in sys.argv[3:]
    keep_commanding = "--keep-commanding" in sys.argv[3:]
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    with ExitStack() as stack:
        stop = stack.enter_context(stop_on_signals() if helper else nullcontext())
        driver = stack.enter_context(MotorDriver(config).start())
        for drive in driver:
            drive.enable()
        moving = [d for d in driver if d.power.supported_modes() >> 2 & 1]  # profile velocity (others stay enabled, still)
        announced = False
        refused = ""
        while True:
            for drive in moving:
                try:
                    drive.set_velocity(velocity)
                    refused = ""
                except MotorError as err:
                    if not keep_commanding:
                        raise
                    if type(err).__name__ != refused:
                        refused = type(err).__name__
                        print(f"REFUSED {refused}: {err}", flush=True)
            if not announced and all(abs(d.snapshot().velocity_deg_s - velocity) < 0.1 * abs(velocity) for d in moving):
                print("READY", flush=True)
                announced = True
            time.sleep(0.05)
    print(f"STOPPED {getattr(stop, 'signum', None)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
