"""The :class:`Drive` every caller uses: the parts of one drive composed.

Each part owns its state and is handed only the ports it needs, as canopen's ``RemoteNode``
composes ``sdo``, ``pdo``, ``nmt`` and ``emcy``:

- ``cache`` (:class:`DriveCache`): what the receive thread knows, published per frame;
- ``sdo`` (:class:`SdoPort`): bounded SDO, one transfer at a time;
- ``channel`` (:class:`CommandChannel`): the one way out for a controlword or a set-point;
- ``watch`` (:class:`HostWatch`), ``power``, ``limits``, ``motion``, ``homing``, ``boot``:
  collaborators built on those.

Lost, booted and another master are the driver's supervisor's judgement (``record``, a
:class:`motor_driver.drive.ledger.DriveRecord` the parts read); the parts hand it what they find
through ``port``. This class adds no state and no rule: it builds the parts in order, connects the cache to the
channel, and hands the drive's COB-IDs to the receive thread last, so that a frame never meets
a half-built drive. Its few methods are the user's API (enable, the stops, moves, streams,
velocity, torque, SDO, a snapshot); everything else is asked of the part that owns it
(``drive.cache.received.statusword``, ``drive.power.supported_modes()``, ``drive.boot.boot_count``).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from can_config.errors import BusLostError
from can_config.objects import OD, FunctionCode, OperationMode
from motor_driver.bus.sdo_client import OwnAnswersNode
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.drive.command.homing import Homing
from motor_driver.drive.command.limits import LimitGuard
from motor_driver.drive.command.motion import Motion
from motor_driver.drive.command.power import PowerStateMachine
from motor_driver.drive.constants import TRANSITION_TIMEOUT_S
from motor_driver.drive.ledger import DriveRecord, NmtLedger, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.setup.boot import Boot
from motor_driver.drive.setup.hostwatch import Host, HostWatch
from motor_driver.drive.values import DriveState
from motor_driver.drive.verdict import Verdict
from motor_driver.protocol.pdo import PdoPlan, plan_pdos
from motor_driver.protocol.units import Scale

logger = logging.getLogger(__name__)


class Drive:
    """One drive. Created by :class:`motor_driver.runtime.driver.MotorDriver`; methods are thread-safe."""

    def __init__(self, config: DriveConfig, network: canopen.Network, od: ObjectDictionary, *,
                 host_node_id: int = 127, sync_period_s: float = 0.01, record: DriveRecord,
                 port: SupervisorPort, host_beats: Callable[[], int], host_heartbeat_s: float) -> None:
        self.config = config
        self.name, self.node_id = config.name, config.node_id
        self.network = network
        self.od = od
        self.node = OwnAnswersNode(config.node_id, od)  # its SDO client takes only its own answers
        network.add_node(self.node)
        # the driver decodes EMCY itself (the cache); canopen's consumer would keep every EMCY in
        # a list that is never trimmed, for as long as the process runs
        network.unsubscribe(FunctionCode.EMCY + config.node_id, self.node.emcy.on_emcy)
        self.plan: PdoPlan = plan_pdos(od, config.node_id)
        for index in self.plan.sdo_only:
            logger.warning("node %d: 0x%04X cannot be PDO-mapped on this drive; using SDO for it", config.node_id, index)
        scale = Scale(config.counts_per_deg, config.rated_torque_nm, config.gear_ratio, invert=config.invert,
                      offset_deg=config.offset_deg)
        self.cache = DriveCache(config, network, self.plan, scale, sync_period_s=sync_period_s, record=record,
                                port=port)
        self.channel = CommandChannel(config.name, config.node_id, self.plan, self._send, self._write_cw_sdo,
                                      self.cache.wake, port.wake)
        self.sdo = SdoPort(config.name, self.node, od, config.sdo_timeout_s, admit=self._admit_tool_write)
        cache, channel, sdo = self.cache, self.channel, self.sdo  # each part is handed those it uses
        self.watch = HostWatch(config, od, cache, channel, sdo, network, Host(host_node_id, host_heartbeat_s, host_beats),
                               record=record, nmt=NmtLedger(config.node_id, self._send))
        self.power = PowerStateMachine(config, od, cache, channel, sdo, self.watch)
        self.limits = LimitGuard(config, cache, channel)
        self.motion = Motion(config, self.plan, cache, channel, sdo, self.power, self.limits)
        self.homing = Homing(config, od, cache, channel, sdo, self.power)
        self.boot = Boot(config, od, self.plan, cache, channel, sdo, self.power, self.watch, port)
        self.cache.connect(self.channel)
        self.cache.subscribe()

    # ------------------------------------------------------------------ the channel's ports
    def _send(self, cob_id: int, data: bytes) -> None:
        """One frame out; a dead bus becomes BusLostError (the supervisor reconnects)."""
        try:
            self.network.send_message(cob_id, data)
        except (can.CanError, OSError, RuntimeError) as err:
            raise BusLostError(f"{self.name} (node {self.node_id}): cannot send 0x{cob_id:03X}: the bus is"
                               f" gone ({err}); nothing moves until it is back and the drive is enabled again") from err

    def _write_cw_sdo(self, word: int) -> None:
        self.sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", word))

    # ------------------------------------------------------------------ the user's API
    def snapshot(self) -> DriveState:
        return self.power.snapshot()

    def verdict(self) -> Verdict:
        """The one judgement of this drive (:mod:`motor_driver.drive.verdict`)."""
        return self.power.verdict()

    def close(self) -> None:
        """The driver shuts down: no command is taken from here on (stops still are)."""
        self.channel.close()

    def enable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        self.power.enable(timeout_s)

    def disable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        self.power.disable(timeout_s)

    def quick_stop(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        self.power.quick_stop(timeout_s)

    def disable_voltage(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        self.power.disable_voltage(timeout_s)

    def halt(self, on: bool = True) -> None:
        self.power.halt(on)

    def recover(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        self.power.recover(timeout_s)

    def set_mode(self, mode: OperationMode | int) -> None:
        self.power.set_mode(mode)

    def _admit_tool_write(self, doing: str) -> None:
        """A tool's SDO write: refused while motion is held, and to a drive that cannot hear this
        driver as configured (lost, re-booting, not configured, another master's)."""
        self.channel.admit(doing)
        self.power.require_usable(doing)

    def home(self, timeout_s: float | None = None) -> None:
        self.homing.home(timeout_s)

    def move_to(self, angle_deg: float, *, wait: bool = False, timeout_s: float | None = None) -> float:
        return self.motion.move_to(angle_deg, wait=wait, timeout_s=timeout_s)

    def wait_target_reached(self, timeout_s: float | None = None) -> None:
        self.motion.wait_target_reached(timeout_s)

    # at_once: frames only; a command that would wait for the drive (a mode switch, a target by
    # SDO) raises CommandWouldWait before anything is sent (motor_driver/drive/command/motion.py)
    def set_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        self.motion.set_velocity(velocity_deg_s, at_once=at_once)

    def set_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        self.motion.set_torque(torque_nm, at_once=at_once)

    def stream_position(self, angle_deg: float, *, max_step_deg: float | None = None, at_once: bool = False) -> None:
        self.motion.stream_position(angle_deg, max_step_deg=max_step_deg, at_once=at_once)

    def stream_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        self.motion.stream_velocity(velocity_deg_s, at_once=at_once)

    def stream_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        self.motion.stream_torque(torque_nm, at_once=at_once)

    def command_position(self, angle_deg: float, *, at_once: bool = False) -> None:
        self.motion.command_position(angle_deg, at_once=at_once)

    def command_velocity(self, velocity_deg_s: float, *, at_once: bool = False) -> None:
        self.motion.command_velocity(velocity_deg_s, at_once=at_once)

    def command_torque(self, torque_nm: float, *, at_once: bool = False) -> None:
        self.motion.command_torque(torque_nm, at_once=at_once)

    def sdo_read(self, index: int, subindex: int = 0) -> bytes:
        return self.sdo.read(index, subindex)

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        self.sdo.write(index, subindex, data)
