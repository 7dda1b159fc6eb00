"""A virtual SocketCAN-style CAN bus with simulated CiA 402 drives and fault injection.

* :mod:`virtual_can.engine` - named channels, wire time (:mod:`virtual_can.wire`), frame faults
* :mod:`virtual_can.bus` - in-process python-can bus (interface ``rovercan``)
* :mod:`virtual_can.server` - socketcand-protocol server (python-can ``socketcand`` client),
  with :mod:`virtual_can.client` (one client) and :mod:`virtual_can.cyclic_jobs` (the broadcast
  manager's jobs), timed by :mod:`virtual_can.bcm_timer` (a process of its own)
* :mod:`virtual_can.sim` - simulated drives from any CiA 402 EDS (:mod:`virtual_can.sim.drive`,
  layers from the CiA 402 model up to NMT/SDO/PDO) and their runner thread
* :mod:`virtual_can.scenario` - fault-injection scenarios from YAML
* :mod:`virtual_can.service` - all of it as one service (``rovercan sim``)

Never imports ``motor_driver``: the driver and the emulator meet only on the bus.
"""

from virtual_can.bus import VirtualBus
from virtual_can.engine import BusEngine, Channel
from virtual_can.server import SocketcandServer
from virtual_can.service import SimDriveSpec, SimService

__all__ = ["BusEngine", "Channel", "SimDriveSpec", "SimService", "SocketcandServer", "VirtualBus"]
