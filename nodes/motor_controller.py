"""``motor_controller``: the team's demo node. One joint (parameter ``joint``, which it requires:
nothing moves on a guess) served by the driver node of ``rover_driver`` restricted to it: its
``<joint>/...`` topics and services, and the demo topics ``/motor_degree_cmd`` (the joint's
``degree_cmd``: the same command path, honouring its ``position_mode``) and ``/motor_state``.

The process is the same assembly as ``rover_driver`` (:mod:`nodes.assembly`): the same
executors, callback groups, start order and safe stop.

Owner: the process's executors (nodes/assembly.py), as for ``rover_driver``.
"""

from __future__ import annotations

import sys

from motor_driver.process.stop import StopSignal
from nodes.assembly import run
from nodes.process import spinning

NODE_NAME = "motor_controller"


def main(args: list[str] | None = None) -> int:
    spinning.init(args)
    with StopSignal() as stop:
        return run(NODE_NAME, stop, name=NODE_NAME, one_joint=True)


if __name__ == "__main__":
    sys.exit(main())
