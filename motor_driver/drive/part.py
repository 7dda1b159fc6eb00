"""What every part of a drive is handed, once: :class:`Ports`.

Owner: nothing here is written after construction. The facade builds one :class:`Ports` per
drive and hands it to each part; a part unpacks it into attributes of its own (plain lookups on
the hot paths, no indirection, no base class) and is handed any other part it needs by name.
"""

from __future__ import annotations

from typing import NamedTuple

from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from motor_driver.drive.channel import CommandChannel
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.state import DriveCache
from motor_driver.protocol.pdo import PdoPlan


class Ports(NamedTuple):
    """One drive's config, object dictionary and PDO plan, and the ports its parts share: the
    cache they read, the channel every frame that can move the motor leaves through, the SDO
    port. A part takes them as ``self.config, self._od, self._plan, self._cache, self._channel,
    self._sdo = ports``."""

    config: DriveConfig
    od: ObjectDictionary
    plan: PdoPlan
    cache: DriveCache
    channel: CommandChannel
    sdo: SdoPort
