"""SDO access to one drive: bounded reads, typed writes, and the objects no tool may write.

Owner: this object; its lock (one per node) serialises every transfer to the drive, whatever
thread asks (canopen's SdoClient has no lock of its own: two threads' transfers on one node
answer each other's requests). Called from the bus's worker (boot), command threads
(operations that wait), the supervisor's worker jobs and the bench CLI; never from the receive
thread (which never waits) nor the supervisor thread, never under the command channel's lock.
One typed codec (:mod:`motor_driver.protocol.codec`, by the EDS's data type) is used for every read and
write, here and by the bench CLI (which builds an :class:`SdoPort` for each node it talks to).
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from can_config.config import SdoSetting
from can_config.eds import has_object, variable
from can_config.errors import BootError, BusLostError, CommandRejected, SdoError, SdoTimeoutError
from can_config.objects import OD, sdo_abort_text
from motor_driver.bus.adapters import receive_behind
from motor_driver.bus.sdo_client import ReceiveBehindError
from motor_driver.drive.constants import SDO_ABORT_OUT_OF_MEMORY, SDO_ABORT_TIMEOUT, SDO_TRANSFER_TIMEOUTS, SDO_UPLOAD_MAX_BYTES
from motor_driver.process.held import LATE_READER_HELPS, HeldDeadline
from motor_driver.protocol.codec import pack_value, unpack_value, value_format

logger = logging.getLogger(__name__)


#: Objects no tool or service may write by SDO (see SdoPort.write_checked), each with why:
#: they move the motor, bypass a limit, or undo what stops the drive when the host is gone.
_TARGET = "it is a motion target; use move/jog (limits enforced)"
_UNITS = ("it sets the drive's units, on which the driver's scale from boot rests: its limits in degrees and"
          " newton-metres would no longer hold; set counts_per_rev, gear_ratio or rated_torque_nm in the config, or"
          " store the object on the drive with the vendor's tool and boot it again")
PROTECTED_OBJECTS: dict[int, str] = {
    OD.CONTROLWORD: "it drives the state machine (enable, quick stop); use enable/disable",
    OD.MODES_OF_OPERATION: "it changes the operation mode under the driver",
    OD.TARGET_POSITION: _TARGET, OD.TARGET_VELOCITY: _TARGET, OD.TARGET_TORQUE: _TARGET,
    OD.VELOCITY_OFFSET: _TARGET, OD.TORQUE_OFFSET: _TARGET, OD.POSITION_OFFSET: _TARGET,
    OD.INTERPOLATION_DATA: _TARGET,
    # the unit objects (read at boot: protocol/units.py), and the factors and notation indexes of
    # older CiA 402 editions (0x6089-0x608E, 0x6093-0x6097), which scale the same values
    **dict.fromkeys((OD.POSITION_ENCODER_RESOLUTION, OD.GEAR_RATIO, OD.FEED_CONSTANT, OD.SI_UNIT_POSITION,
                     OD.SI_UNIT_VELOCITY, OD.SI_UNIT_ACCELERATION, OD.RATED_TORQUE, *range(0x6089, 0x608F),
                     *range(0x6093, 0x6098)), _UNITS),
    OD.POLARITY: "it reverses the motor's direction under the driver's limits and commands; set invert in the config",
    OD.HOME_OFFSET: "it moves the zero the next homing sets, under the driver's limits in degrees; set offset_deg in"
                    " the config",
    OD.SOFTWARE_POSITION_LIMIT: "it is the drive's position limit; set min_deg/max_deg in the config",
    OD.MAX_PROFILE_VELOCITY: "it is a velocity limit; set max_velocity_deg_s in the config",
    OD.MAX_TORQUE: "it is the torque limit; set max_torque_nm in the config",
    OD.PROFILE_VELOCITY: "it is the speed of every profile move, checked against max_velocity_deg_s; use move --speed",
    OD.PROFILE_ACCELERATION: "it is the ramp of every profile move; set profile_acceleration_deg_s2 in the config",
    OD.PROFILE_DECELERATION: "it is the ramp of every profile move; set profile_acceleration_deg_s2 in the config",
    OD.QUICK_STOP_DECELERATION: "the drive's quick stop (and its stop when the host is gone) brakes by it",
    OD.QUICK_STOP_OPTION: "it decides what the drive's quick stop does (the host-loss stop relies on it)",
    OD.ABORT_CONNECTION_OPTION: "it decides what the drive does when the host is gone (on_host_loss in the config)",
    OD.CONSUMER_HEARTBEAT_TIME: "it is how the drive watches the host's heartbeat (the stop when the host dies)",
    **dict.fromkeys((OD.GUARD_TIME, OD.LIFE_TIME_FACTOR), "it is how a guarded drive watches the host (the stop when"
                    " the host dies; 0 turns it off); set heartbeat_period_ms and host_timeout_ms in the config"),
    OD.HOMING_METHOD: "homing moves the motor by it; set homing in the config",
    OD.HOMING_SPEEDS: "homing moves the motor by it; set homing in the config",
    OD.PRODUCER_HEARTBEAT_TIME: "the driver watches the drive's heartbeat at the configured period; a change makes"
                                " it declare the drive lost, or miss a loss (heartbeat_period_ms in the config)",
    OD.COB_ID_SYNC: "it moves the SYNC every PDO of the drive runs on",
}


def protected_reason(index: int) -> str | None:
    """Why writing ``index`` by SDO is refused, or None when it may be written."""
    if 0x1400 <= index <= 0x1BFF:
        return "it changes the PDO set the driver configured (a PDO could then carry motion targets)"
    return PROTECTED_OBJECTS.get(index)


class SdoPort:
    """SDO access to one node, bounded in size and time, with one typed codec, one transfer at a time."""

    def __init__(self, name: str, node: canopen.RemoteNode, od: ObjectDictionary, timeout_s: float,
                 admit: Callable[[str], None] | None = None) -> None:
        self.name, self.node_id = name, node.id
        self.od = od
        self._node = node
        self._admit = admit  # the drive's verdict on motion (its channel's): a tool's write is refused while held
        self._timeout_s = timeout_s
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        self._lock = threading.Lock()

    def receive_behind(self) -> bool | None:
        """Whether the receive thread of this drive's bus has yet to hand on what came
        (:func:`motor_driver.bus.adapters.receive_behind`; None: the bus cannot tell)."""
        return receive_behind(getattr(self._node.network, "bus", None))

    @contextmanager
    def _sdo_errors(self, what: str, index: int, subindex: int) -> Iterator[None]:
        """canopen's SDO exceptions -> this project's, with the abort code and its meaning; a
        malformed answer (canopen's parsing raising anything) is an SdoError too, never a
        struct.error reaching the caller."""
        where = f"node {self.node_id}: SDO {what} 0x{index:04X}:{subindex}"
        try:
            yield
        except canopen.SdoAbortedError as err:
            raise SdoError(f"{where} aborted with 0x{err.code:08X} ({sdo_abort_text(err.code)})",
                           node_id=self.node_id, index=index, subindex=subindex, abort_code=err.code) from err
        except ReceiveBehindError as err:
            raise SdoTimeoutError(f"{where}: no answer read ({err}). This driver was late, not the drive silent:"
                                  f" {LATE_READER_HELPS}",
                                  node_id=self.node_id, index=index, subindex=subindex) from err
        except canopen.SdoCommunicationError as err:
            if "No SDO response" not in str(err):  # an answer came, but not a valid one
                raise SdoError(f"{where}: the drive answered wrongly ({err}); the transfer was aborted",
                               node_id=self.node_id, index=index, subindex=subindex) from err
            raise SdoTimeoutError(f"{where} got no answer ({err}); check power, node id, bitrate and termination",
                                  node_id=self.node_id, index=index, subindex=subindex) from err
        except (can.CanError, OSError) as err:
            raise BusLostError(f"{where}: the bus is gone ({err})") from err
        except (struct.error, ValueError, IndexError, KeyError, TypeError) as err:
            raise SdoError(f"{where}: malformed answer from the drive ({type(err).__name__}: {err})",
                           node_id=self.node_id, index=index, subindex=subindex) from err

    def read(self, index: int, subindex: int = 0) -> bytes:
        """An SDO upload, bounded in size and in time: at most the object's size where its type
        has one (else SDO_UPLOAD_MAX_BYTES), and SDO_TRANSFER_TIMEOUTS x the SDO timeout in all,
        whatever the drive announces or keeps sending (a transfer past either is aborted)."""
        with self._lock, self._sdo_errors("read", index, subindex):
            try:
                return self._bounded_upload(index, subindex)
            except canopen.SdoCommunicationError as err:
                self._crossed(err, "read", index, subindex)
                return self._bounded_upload(index, subindex)

    def _bounded_upload(self, index: int, subindex: int) -> bytes:
        var = variable(self.od, index, subindex)
        fixed = len(var) // 8 if var is not None and var.fixed_size else None
        cap = max(8, fixed) if fixed else SDO_UPLOAD_MAX_BYTES  # some drives send a U32 for a smaller type
        sdo = self._node.sdo
        where = f"node {self.node_id}: SDO read 0x{index:04X}:{subindex}"
        # a hold of the whole process at the end of the transfer is not the drive's: one more look
        # (a gap between two segments longer than a hold's also counts as one: at most 2 x 0.25 s)
        deadline = HeldDeadline(SDO_TRANSFER_TIMEOUTS * self._timeout_s)
        data = bytearray()
        with sdo.open(index, subindex, buffering=0) as stream:
            if stream.size is not None and stream.size > cap:
                sdo.abort(SDO_ABORT_OUT_OF_MEMORY)
                raise SdoError(f"{where}: the drive announced {stream.size} bytes, more than the {cap} this object"
                               " can hold; the transfer was aborted", node_id=self.node_id, index=index,
                               subindex=subindex)
            while chunk := stream.read(7):
                data += chunk
                if len(data) > cap:
                    sdo.abort(SDO_ABORT_OUT_OF_MEMORY)
                    raise SdoError(f"{where}: the drive sent more than {cap} bytes; the transfer was aborted",
                                   node_id=self.node_id, index=index, subindex=subindex)
                if deadline.remaining() <= 0.0:
                    sdo.abort(SDO_ABORT_TIMEOUT)
                    raise SdoTimeoutError(f"{where}: the transfer took over {SDO_TRANSFER_TIMEOUTS} x the SDO timeout"
                                          f" ({self._timeout_s:g} s){deadline.said()}; aborted", node_id=self.node_id,
                                          index=index, subindex=subindex)
        return bytes(data[:fixed] if fixed and len(data) > fixed else data)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        with self._lock, self._sdo_errors("write", index, subindex):
            try:
                self._node.sdo.download(index, subindex, data)
            except canopen.SdoCommunicationError as err:
                self._crossed(err, "write", index, subindex)
                self._node.sdo.download(index, subindex, data)

    def _crossed(self, err: canopen.SdoCommunicationError, what: str, index: int, subindex: int) -> None:
        """An answer that was not to this request and that the node's client could not tell
        apart (it drops those naming another object or of another kind: see
        :mod:`motor_driver.bus.sdo_client`), such as a segment of another transfer, gets the
        transfer tried once more: canopen has aborted it and empties its queue of answers before
        the next request. No answer at all is raised (a silent node is not waited for twice)."""
        if "No SDO response" in str(err):
            raise err
        logger.info("node %d: SDO %s 0x%04X:%d: an answer not to this request (%s); trying once more",
                    self.node_id, what, index, subindex, err)

    def write_checked(self, index: int, subindex: int, value: int) -> None:
        """SDO write for tools and services: refuses the objects that move the motor or set its
        limits and PDOs, which only the driver's own checked paths may write."""
        reason = protected_reason(index)
        if reason is not None:
            raise CommandRejected(f"{self.name}: writing 0x{index:04X} by SDO is refused: {reason}.")
        if self._admit is not None:
            self._admit(f"SDO write 0x{index:04X}:{subindex}")
        self.write_typed(index, subindex, value)

    def read_value(self, index: int, subindex: int = 0) -> int | float | bytes:
        raw = self.read(index, subindex)
        value = unpack_value(value_format(self.od, index, subindex), raw)
        return raw if value is None else value

    def write_typed(self, index: int, subindex: int, value: int) -> None:
        """A number written as its EDS type says (INTEGER32 for an object the EDS does not list)."""
        self.write(index, subindex, pack_value(value_format(self.od, index, subindex) or "<i", value))

    def write_setting(self, setting: SdoSetting) -> None:
        """One entry of the config's ``sdo:`` list: typed by the EDS (or ``size`` bytes), read
        back when ``check``. Objects the driver owns are refused with the reason."""
        where = f"sdo setting 0x{setting.index:04X}:{setting.sub}"
        reason = protected_reason(setting.index)
        if reason is not None:
            raise BootError(f"node {self.node_id} ({self.name}): {where} is refused: {reason}.", node_id=self.node_id,
                            step="sdo settings", index=setting.index, subindex=setting.sub)
        fmt = value_format(self.od, setting.index, setting.sub)
        if fmt is None and setting.size is None:
            raise BootError(f"node {self.node_id} ({self.name}): {where} is not in the drive's EDS; give its size"
                            " (size: 1, 2, 4 or 8 bytes) in the config", node_id=self.node_id, step="sdo settings",
                            index=setting.index, subindex=setting.sub)
        try:
            if fmt is not None:
                data = pack_value(fmt, setting.value)
            else:
                size = int(setting.size or 4)
                data = int(setting.value).to_bytes(size, "little", signed=int(setting.value) < 0)
        except (struct.error, OverflowError) as err:
            raise BootError(f"node {self.node_id} ({self.name}): {where}: value {setting.value} does not fit the"
                            f" object ({fmt or f'{setting.size} bytes'}): {err}", node_id=self.node_id,
                            step="sdo settings", index=setting.index, subindex=setting.sub) from err
        self.write(setting.index, setting.sub, data)
        if setting.check:
            back = self.read(setting.index, setting.sub)[:len(data)]
            if back != data:
                raise BootError(f"node {self.node_id} ({self.name}): {where}: wrote {data.hex(' ')}, read back"
                                f" {back.hex(' ')}; the drive did not keep the value (range, or writable only in"
                                " another state?)", node_id=self.node_id, step="sdo settings",
                                index=setting.index, subindex=setting.sub)

    def read_int(self, index: int, subindex: int) -> int | None:
        """An integer object read by SDO, or None where the drive's EDS has no such object."""
        if not has_object(self.od, index, subindex):
            return None
        value = self.read_value(index, subindex)
        return int(value) if isinstance(value, (int, float)) else None

    def read_optional(self, index: int, subindex: int) -> bytes | None:
        """An object read by SDO whatever the EDS lists, or None where the drive aborts (it has
        no such object). No answer at all is an error, not an absence."""
        try:
            return self.read(index, subindex)
        except SdoTimeoutError:
            raise
        except SdoError:
            return None

    def read_number(self, index: int, subindex: int = 0) -> int:
        """A numeric object read by SDO (typed by the EDS); anything else is an SdoError."""
        value = self.read_value(index, subindex)
        if not isinstance(value, (int, float)):
            raise SdoError(f"node {self.node_id}: SDO read 0x{index:04X}:{subindex}: not a number ({value!r})",
                           node_id=self.node_id, index=index, subindex=subindex)
        return int(value)
