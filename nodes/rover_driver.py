"""``rover_driver``: the entry point of the driver's ROS 2 process (``python -m nodes.rover_driver``,
``ros2 run rovercan_bringup rover_driver``): every configured drive's topics, services and actions,
and the drive system, put together by :mod:`nodes.assembly` (the node itself:
:mod:`nodes.joints.driver_node`).

Owner: the process's main thread, until the assembly's executors own the nodes.
"""

from __future__ import annotations

import sys

from motor_driver.process.stop import StopSignal
from nodes.assembly import run
from nodes.process import spinning


def main(args: list[str] | None = None) -> int:
    spinning.init(args)
    with StopSignal() as stop:
        return run("rover_driver", stop)


if __name__ == "__main__":
    sys.exit(main())
