"""The :class:`Drive` every caller uses: the layers of :mod:`motor_driver.drive` stacked.

Each layer is a class in its own module and builds on the ones below it only (state cache,
SDO, command frames, power state machine, limit guard, motion, homing, host watch, boot);
this one adds nothing but the moment the drive's frames reach the receive thread: after every
layer has set up its state, so that a frame never meets a half-built drive.
"""

from __future__ import annotations

import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from motor_driver.drive.boot import Boot


class Drive(Boot):
    """One drive. Created by :class:`motor_driver.driver.MotorDriver`; methods are thread-safe."""

    def __init__(self, config: DriveConfig, network: canopen.Network, od: ObjectDictionary, *,
                 host_node_id: int = 127, sync_period_s: float = 0.01) -> None:
        super().__init__(config, network, od, host_node_id=host_node_id, sync_period_s=sync_period_s)
        self.subscribe()
