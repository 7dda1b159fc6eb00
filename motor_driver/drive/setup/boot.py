"""Boot of one drive as a table of steps, and its re-configuration after a reset.

Owner: the bus's worker (or the caller of :meth:`Boot.boot`), while the drive is not booted:
nothing else commands it meanwhile (the cache says not booted, so every command is refused).
Its own state: the safety check's result, the boot count, the host-loss stops it found, the
object a step is at (for its error), the unit objects the drive reported (replaced whole at each
boot; the flight recorder reads them for its incidents), the boot-ups heard when a try began and
its 0x1020 stamp, the unexpected failures of re-configuration in a row. Whether the drive is
booted is the supervisor's: a boot reports its beginning and its end
(:class:`motor_driver.drive.ledger.Booting`, ``Booted``) and a
failed re-configuration (``RebootFailed``), and goes on once the supervisor has taken it in.
A drive is called booted only with its configuration confirmed (:meth:`Boot._held`): a
boot-up heard at any step, or objects that do not hold what was written, start the configuration
again (:class:`motor_driver.drive.ledger.BootRestarted`, at most BOOT_RESTARTS_MAX times). Tests
hook in through the command channel's hook: ``boot: <step>`` before each step, ``boot: started``
before the Booted report.
Each step reads or writes by SDO through the drive's SDO port; what the steps read (statusword,
position, mode, units) is handed to the state cache and the command channel through their
methods, in one place at the end.
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Callable
from pathlib import Path

import can
from canopen.objectdictionary import ObjectDictionary

from can_config.config import GENERIC_EDS, DriveConfig
from can_config.eds import consumer_subs, has_object, variable
from can_config.errors import BootError, BusLostError, DriveStateError, DriveTimeoutError, MotorError, SdoError, UnitError
from can_config.objects import CIA402_PROFILE, EMCY_HEARTBEAT_LOST, OD, SUPPORTED_MODE_BIT, NmtCommand, OperationMode
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.drive.command.power import PowerStateMachine
from motor_driver.drive.constants import (
    BOOT_RESTARTS_MAX,
    HOST_LOSS_CHECK_WAIT_S,
    REBOOT_BACKOFF_MAX_S,
    REBOOT_RETRY_S,
    STATE_POLL_S,
    TRANSITION_TIMEOUT_S,
)
from motor_driver.drive.ledger import Booted, Booting, BootRestarted, RebootFailed, RestoreFailed, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.setup.hostwatch import HostWatch
from motor_driver.process.jobs import cause_of
from motor_driver.protocol.cia402 import Command, State, braked, decode_state
from motor_driver.protocol.codec import value_format
from motor_driver.protocol.pdo import PdoPlan, mapping_writes
from motor_driver.protocol.safety import ALLOWED, FAIL, SafetyCheck, judge
from motor_driver.protocol.unit_ranges import check_drive_value
from motor_driver.protocol.units import read_unit_objects, scale_from_objects

logger = logging.getLogger(__name__)


class Boot:
    """Boot of one drive, a table of steps, and re-configuration after a reset."""

    def __init__(self, config: DriveConfig, od: ObjectDictionary, plan: PdoPlan, cache: DriveCache,
                 channel: CommandChannel, sdo: SdoPort, power: PowerStateMachine, watch: HostWatch, port: SupervisorPort) -> None:
        self.config, self._od, self._plan, self._cache, self._channel, self._sdo = config, od, plan, cache, channel, sdo
        self.name, self.node_id = config.name, config.node_id
        self._power = power
        self._watch = watch
        self._port = port
        self.safety: tuple[SafetyCheck, ...] = ()  # read back after each boot (motor_driver.protocol.safety)
        self.host_loss_stops = 0  # boots that found the drive stopped by its host watch
        self.boot_count = 0
        self._boot_object = (0, 0)  # the object the running boot step is at (for its error)
        self._mode = 0  # the mode the boot left the drive in (0x6061)
        self.unit_objects: dict[tuple[int, int], int] = {}  # what the drive reported at the last boot
        self._bootups = 0  # the drive's boot-ups heard when the running try began
        self._stamp: tuple[int, int] | None = None  # 0x1020 as the running try wrote it (None: not written)
        self._unexpected_in_row = 0  # re-configurations that failed unexpectedly, in a row (the back-off)

    def boot(self, *, reset: bool = True) -> None:
        """Reset (NMT), check identity, configure PDOs and parameters, confirm them, NMT start.
        Does not enable. A drive that resets during it (a boot-up heard, at any step) or does
        not hold what was written is configured again from the start (without an NMT reset when
        it has just reset itself), at most BOOT_RESTARTS_MAX times; then a BootError."""
        self._port.report(Booting(self.name))
        restarts = 0
        while why := self._configure(reset):
            restarts += 1
            if restarts > BOOT_RESTARTS_MAX:
                raise BootError(f"node {self.node_id} ({self.name}): configured {restarts} times, and each time"
                                f" it did not hold (the last: {why}). A drive that keeps resetting: check its supply"
                                " (a brown-out), its own watchdog and error history (0x1003), and that no other tool"
                                " sends it NMT reset; one that does not keep what is written or shows no CiA 402"
                                " state: its firmware and its EDS. It is left unconfigured and is not enabled.",
                                node_id=self.node_id, step="confirm configuration")
            logger.warning("node %d (%s): %s; configuring it again from the start (%d of at most %d)",
                           self.node_id, self.name, why, restarts, BOOT_RESTARTS_MAX)
            self._port.report(BootRestarted(self.name, why))
            reset = self._cache.bootups == self._bootups  # it reset itself: it is fresh already

    def _configure(self, reset: bool) -> str:
        """One try: '' once the drive is started with its configuration confirmed, else why it
        must be configured again."""
        self._power.forget_modes()  # a replaced drive may support other modes
        if reset:
            self._reset_node()
        self._bootups = self._cache.bootups  # a boot-up numbered above this is a reset during the try
        self._boot_object = (OD.IDENTITY, 1)
        for step, run in self._boot_steps():
            if why := self._run_step(step, run):
                return why
        self._started()
        return ""

    def _run_step(self, step: str, run: Callable[[], str | None]) -> str:
        """One step: '' or why the configuration must start again (what the step found, or a
        boot-up heard by the end of it). A step that failed after the drive reset is that reset;
        any other failure is a BootError naming the step and the object."""
        self._channel.point(f"boot: {step}")
        try:
            why = run()
        except MotorError as err:
            if reset := self._reset_why():
                return f"{reset} during boot step '{step}', which then failed ({err})"
            if isinstance(err, BootError) or not isinstance(err, (SdoError, DriveStateError)):
                raise
            index, sub = self._boot_object
            raise BootError(f"node {self.node_id} ({self.name}): boot step '{step}' failed at"
                            f" 0x{index:04X}:{sub}: {err}", node_id=self.node_id, step=step, index=index,
                            subindex=sub, abort_code=getattr(err, "abort_code", None)) from err
        return why or self._reset_why(f" during boot step '{step}'")

    def _reset_why(self, during: str = "") -> str:
        """A boot-up heard since the try began: the drive reset and its objects are back to their
        defaults. The receive thread counts boot-ups in the order frames come, and a drive sends
        its boot-up before it answers anything after its reset: a step's SDO answer seen here
        comes with every boot-up sent before it."""
        return f"it sent boot-up{during} (it reset)" if self._cache.bootups != self._bootups else ""

    def _boot_steps(self) -> tuple[tuple[str, Callable[[], str | None]], ...]:
        """The steps of a boot in order, each named as a BootError names it. The last but two
        reads back what the others wrote, the last starts the drive and reads its statusword:
        each says why the configuration must start again, or ''."""
        return (("identity", self._check_identity), ("device type", self._check_device_type),
                ("configuration stamp", self._write_stamp),
                ("disarm", self._disarm), ("units", self._read_units), ("PDO mapping", self._write_pdo_mapping),
                ("heartbeat", self._write_heartbeat), ("host watch", self._watch.configure),
                ("position limits", self._write_position_limits), ("profile parameters", self._write_profile),
                ("sdo settings", self._write_settings), ("operation mode", self._boot_mode),
                ("read state", self._read_state), ("confirm configuration", self._held),
                ("safety check", self._safety_check), ("stop ramp", self._note_stop_ramp),
                ("start", self._start_confirmed))

    def _at(self, index: int, subindex: int) -> None:
        """The object the boot step is at: a failure names it."""
        self._boot_object = (index, subindex)

    def _reset_node(self) -> None:
        self._note_host_loss_stop()
        self._cache.expect_bootup()
        self._send_nmt(NmtCommand.RESET_NODE)
        if not self._cache.wait_bootup(self.config.boot_timeout_s):
            raise BootError(f"node {self.node_id} ({self.name}): no boot-up message within"
                            f" {self.config.boot_timeout_s:g} s after NMT reset (boot_timeout_ms); check power, node"
                            " id, bitrate and termination", node_id=self.node_id, step="boot-up")

    def _check_device_type(self) -> None:
        self._at(OD.DEVICE_TYPE, 0)
        device_type = struct.unpack("<I", self._sdo.read(OD.DEVICE_TYPE, 0)[:4].ljust(4, b"\0"))[0]
        if device_type & 0xFFFF != CIA402_PROFILE:
            logger.warning("node %d: device type 0x%08X is not a CiA 402 drive profile", self.node_id, device_type)

    def _disarm(self) -> None:
        if has_object(self._od, OD.STATUSWORD) and has_object(self._od, OD.CONTROLWORD):
            self._at(OD.STATUSWORD, 0)
            self._disarm_by_sdo()

    def _write_pdo_mapping(self) -> None:
        for index, sub, data, what in mapping_writes(self._plan):
            self._at(index, sub)
            var = variable(self._od, index, sub)
            if var is not None and var.access_type in ("ro", "const"):
                logger.info("node %d: %s: 0x%04X:%d is read-only in the EDS; keeping the device's"
                            " value", self.node_id, what, index, sub)
                continue
            try:
                self._sdo.write(index, sub, data)
            except SdoError as err:
                raise BootError(f"node {self.node_id} ({self.name}): boot step 'PDO mapping' failed at"
                                f" {what} (0x{index:04X}:{sub}): {err}", node_id=self.node_id,
                                step="PDO mapping", index=index, subindex=sub, abort_code=err.abort_code) from err

    def _write_heartbeat(self) -> None:
        self._at(OD.PRODUCER_HEARTBEAT_TIME, 0)
        # CiA 301: a node with a heartbeat is not guarded; one that cannot be guarded here (no
        # remote frames) keeps its heartbeat, which tells the driver it is alive
        guarded = self._watch.choose()
        self._sdo.write(OD.PRODUCER_HEARTBEAT_TIME, 0,
                        struct.pack("<H", 0 if guarded else int(self.config.heartbeat_period_s * 1000)))

    def _write_position_limits(self) -> None:
        cfg = self.config
        if not cfg.is_continuous and has_object(self._od, OD.SOFTWARE_POSITION_LIMIT, 2):
            low, high = self._cache.scale.limits_to_counts(cfg.min_deg, cfg.max_deg)  # type: ignore[arg-type]
            if not -(2**31) <= low <= high < 2**31:
                raise BootError(f"node {self.node_id} ({self.name}): boot step 'position limits' refused: min_deg/"
                                f"max_deg are {low}..{high} in the drive's units, beyond INTEGER32; its unit objects"
                                " or the limits are wrong. Nothing was written.", node_id=self.node_id,
                                step="position limits", index=OD.SOFTWARE_POSITION_LIMIT, subindex=1)
            self._at(OD.SOFTWARE_POSITION_LIMIT, 1)
            self._sdo.write_typed(OD.SOFTWARE_POSITION_LIMIT, 1, low)
            self._at(OD.SOFTWARE_POSITION_LIMIT, 2)
            self._sdo.write_typed(OD.SOFTWARE_POSITION_LIMIT, 2, high)

    def _write_profile(self) -> None:
        cfg = self.config
        to_drive, accel_to_drive = self._cache.scale.magnitude_to_drive, self._cache.scale.acceleration_to_drive
        for index, value, key in ((OD.PROFILE_VELOCITY, to_drive(cfg.profile_velocity_deg_s), "profile_velocity_deg_s"),
                                  (OD.PROFILE_ACCELERATION, accel_to_drive(cfg.profile_acceleration_deg_s2),
                                   "profile_acceleration_deg_s2"),
                                  (OD.PROFILE_DECELERATION, accel_to_drive(cfg.profile_acceleration_deg_s2),
                                   "profile_acceleration_deg_s2"),
                                  (OD.MAX_PROFILE_VELOCITY, to_drive(cfg.max_velocity_deg_s), "max_velocity_deg_s")):
            if has_object(self._od, index):
                self._at(index, 0)
                self._sdo.write_typed(index, 0, self._checked(index, value, key))
        if has_object(self._od, OD.QUICK_STOP_DECELERATION):
            self._at(OD.QUICK_STOP_DECELERATION, 0)
            self._sdo.write_typed(OD.QUICK_STOP_DECELERATION, 0,
                                  self._checked(OD.QUICK_STOP_DECELERATION, self._quick_stop_decel(),
                                                "quick_stop_decel_deg_s2"))

    def _checked(self, index: int, value: float, key: str) -> int:
        """A profile value in drive units: never 0, never beyond its type (a boot error, not a write)."""
        try:
            return check_drive_value(index, value, f"({key})", value_format(self._od, index, 0))
        except UnitError as err:
            raise BootError(f"node {self.node_id} ({self.name}): boot step 'profile parameters' refused: {err}",
                            node_id=self.node_id, step="profile parameters", index=index, subindex=0) from err

    def _write_settings(self) -> None:
        for setting in self.config.sdo:
            self._at(setting.index, setting.sub)
            self._sdo.write_setting(setting)

    def _boot_mode(self) -> None:
        self._at(OD.SUPPORTED_DRIVE_MODES, 0)
        supported = self._power.supported_modes()
        self._at(OD.MODES_OF_OPERATION, 0)
        if supported >> SUPPORTED_MODE_BIT[OperationMode.PROFILE_POSITION] & 1:
            self._power.switch_mode_sdo(OperationMode.PROFILE_POSITION)
            self._mode = int(OperationMode.PROFILE_POSITION)
        else:
            logger.warning("node %d (%s): 0x6502 = 0x%08X lists no profile position mode; the"
                           " drive boots without a mode; move_to() will be refused (stream_position uses IP where listed)",
                           self.node_id, self.name, supported)
            self._mode = self._sdo.read_number(OD.MODES_OF_OPERATION_DISPLAY)

    def _read_state(self) -> None:
        self._at(OD.STATUSWORD, 0)
        statusword = self._sdo.read_number(OD.STATUSWORD)
        self._at(OD.POSITION_ACTUAL, 0)
        position = self._sdo.read_number(OD.POSITION_ACTUAL)
        self._cache.seed(statusword, position, self._mode)
        self._channel.reset(position)

    def _safety_check(self) -> None:
        try:
            self.safety = tuple(judge(self.config, self._watch.host_node_id, self._cache.scale, self._sdo.read_int,
                                      consumer_subs=consumer_subs(self._od), guarding=self._watch.guardable))
        except SdoError as err:
            raise BootError(f"node {self.node_id} ({self.name}): boot step 'safety check' failed: {err}",
                            node_id=self.node_id, step="safety check", index=err.index, subindex=err.subindex,
                            abort_code=err.abort_code) from err
        for check in self.safety:
            if check.failed:
                logger.error("node %d (%s): safety check failed: %s: %s is %s, expected %s", self.node_id,
                             self.name, check.check, check.object, check.actual, check.expected)
            # what was written did not hold (allowed: the config arms a drive without a watch): no watch
            if check.status in (FAIL, ALLOWED) and check.check.startswith("host watch"):
                self._watch.read_back_wrong(f"its host watch read back wrong after boot ({check.object} is {check.actual},"
                                            f" expected {check.expected}: the drive refused or changed the values)")

    def _write_stamp(self) -> None:
        """Where the drive has 0x1020 (CiA 301 verify configuration) to write: a stamp, the
        configuration's date and time, written before any configuration and read back after it
        (:meth:`_held`). A reset in between restores its saved value, which this stamp never
        is (it differs from the value found here, after any reset of this boot)."""
        self._stamp = None
        if not all(writable(self._od, OD.VERIFY_CONFIGURATION, sub) for sub in (1, 2)):
            return
        self._at(OD.VERIFY_CONFIGURATION, 1)
        found = (self._sdo.read_int(OD.VERIFY_CONFIGURATION, 1), self._sdo.read_int(OD.VERIFY_CONFIGURATION, 2))
        stamp = configuration_stamp(time.time())
        if stamp == found:
            stamp = (stamp[0], (stamp[1] + 1) % MS_PER_DAY)
        for sub, value in zip((1, 2), stamp, strict=True):
            self._at(OD.VERIFY_CONFIGURATION, sub)
            self._sdo.write_typed(OD.VERIFY_CONFIGURATION, sub, value)
        self._stamp = stamp

    def _held(self) -> str:
        """What the drive holds before it may ever be enabled: the stamp of 0x1020 where it has
        one, else every PDO object this boot wrote, read back. A reset since the stamp or the
        PDO writes restored them, whether its boot-up was heard or not. '' or why not."""
        return self._stamp_kept() if self._stamp is not None else self._pdos_kept()

    def _start_confirmed(self) -> str:
        """NMT start, the statusword read and decoded, then what the drive holds confirmed once
        more. A reset since the last confirmation whose boot-up was heard fails the step
        (:meth:`_reset_why`); one whose boot-up was lost restored the defaults that this second
        look at the stamp (or one PDO object away from its default) shows, before the drive is
        ever booted. A reset
        after it leaves the drive pre-operational, where no RPDO reaches it, until it is
        configured again. '' or why the configuration must start again."""
        self._send_nmt(NmtCommand.START)
        self._at(OD.STATUSWORD, 0)
        statusword = self._sdo.read_number(OD.STATUSWORD)
        if decode_state(statusword) == State.UNKNOWN:
            return f"its statusword after NMT start, 0x{statusword:04X}, is no CiA 402 state"
        self._cache.note_statusword(statusword)
        if why := (self._stamp_kept() if self._stamp is not None else self._canary_kept()):
            return f"after NMT start: {why}"
        return ""

    def _stamp_kept(self) -> str:
        self._at(OD.VERIFY_CONFIGURATION, 1)
        held = (self._sdo.read_int(OD.VERIFY_CONFIGURATION, 1), self._sdo.read_int(OD.VERIFY_CONFIGURATION, 2))
        if held == self._stamp:
            return ""
        return (f"0x1020 (verify configuration) holds {held[0]}/{held[1]}, not the stamp {self._stamp[0]}/"  # type: ignore[index]
                f"{self._stamp[1]} written before its configuration (it reset)")  # type: ignore[index]

    def _canary_kept(self) -> str:
        """One PDO object this boot wrote away from its EDS default, read back: a reset puts it
        back to that default (one read where the full read-back, done before the start, takes
        dozens). '' when every object written holds its default (a reset would change nothing)."""
        for (index, sub), (data, what) in self._written_pdo_objects().items():
            var = variable(self._od, index, sub)
            if var is not None and isinstance(var.default, int) and int.from_bytes(data, "little") != var.default:
                return self._object_kept(index, sub, data, what)
        return ""

    def _pdos_kept(self) -> str:
        """Every PDO object this boot wrote, read back by SDO against the last value written."""
        for (index, sub), (data, what) in self._written_pdo_objects().items():
            if why := self._object_kept(index, sub, data, what):
                return why
        return ""

    def _written_pdo_objects(self) -> dict[tuple[int, int], tuple[bytes, str]]:
        """Each PDO object this boot wrote (not read-only in the EDS, as _write_pdo_mapping) and
        the last value written to it."""
        wanted: dict[tuple[int, int], tuple[bytes, str]] = {}
        for index, sub, data, what in mapping_writes(self._plan):
            var = variable(self._od, index, sub)
            if var is None or var.access_type not in ("ro", "const"):
                wanted[(index, sub)] = (data, what)
        return wanted

    def _object_kept(self, index: int, sub: int, data: bytes, what: str) -> str:
        """'' when the drive holds ``data`` at (index, sub), else why not."""
        self._at(index, sub)
        held = int.from_bytes(self._sdo.read(index, sub), "little")
        written = int.from_bytes(data, "little")
        if held == written:
            return ""
        return (f"it does not hold its PDO configuration: 0x{index:04X}:{sub} ({what}) reads 0x{held:X},"
                f" 0x{written:X} was written")

    def _started(self) -> None:
        """The drive is started with its configuration confirmed: booted (not enabled)."""
        self._cache.note_started()
        self._channel.point("boot: started")
        self._port.report(Booted(self.name, self._bootups))
        self.boot_count += 1  # after: a caller that sees the count sees the drive booted
        logger.info("node %d (%s) booted: %d RPDOs, %d TPDOs%s", self.node_id, self.name,
                    len(self._plan.rpdos), len(self._plan.tpdos),
                    f"; by SDO: {', '.join(f'0x{i:04X}' for i in self._plan.sdo_only)}"
                    if self._plan.sdo_only else "")

    def _send_nmt(self, command: NmtCommand) -> None:
        try:
            self._watch.nmt_ledger.send(command)
        except (can.CanError, OSError, RuntimeError) as err:
            raise BusLostError(f"{self.name} (node {self.node_id}): cannot send NMT {command.name}: the bus is"
                               f" gone ({err})") from err

    def _note_host_loss_stop(self) -> None:
        """Before the reset at boot: did the drive stop itself because the host was gone (the
        newest entry of its error history 0x1003 is 0x8130)? Counted for the flight recorder
        (``host_loss_stops``), and the history is cleared so that it is counted once. Only a
        drive heard within HOST_LOSS_CHECK_WAIT_S is asked: an absent one does not slow the boot."""
        if not has_object(self._od, OD.PREDEFINED_ERROR_FIELD, 1):
            return
        deadline = time.monotonic() + HOST_LOSS_CHECK_WAIT_S
        while not self._cache.last_heartbeat and time.monotonic() < deadline:
            time.sleep(STATE_POLL_S)
        if not self._cache.last_heartbeat:
            return
        try:
            self._check_identity()  # never clear the history of another drive than the config's
            newest = self._sdo.read_int(OD.PREDEFINED_ERROR_FIELD, 1)
            if newest is None or newest & 0xFFFF != EMCY_HEARTBEAT_LOST:
                return
            self.host_loss_stops += 1
            logger.warning("node %d (%s): it had stopped itself when the host was lost (0x8130 in its error"
                           " history)", self.node_id, self.name)
            self._sdo.write(OD.PREDEFINED_ERROR_FIELD, 0, b"\x00")  # CiA 301: 0 clears the history
        except MotorError as err:
            logger.info("node %d (%s): error history not read before the reset: %s", self.node_id, self.name, err)

    def expected_identity(self) -> list[tuple[int, str, frozenset[int], str]]:
        """What 0x1018 must hold: (sub, what, values allowed, who says so), from the config's
        ``identity:`` and from the EDS: vendor and product of its [DeviceInfo] (or of its own 0x1018
        defaults, where a file disagrees with itself). Not for the project's generic EDS, which
        stands for any CiA 402 drive."""
        wanted: list[tuple[int, str, frozenset[int], str]] = []
        expected = self.config.identity
        for sub, what, want in ((1, "vendor id", expected.vendor_id), (2, "product code", expected.product_code),
                                (3, "revision", expected.revision)):
            if want is not None:
                wanted.append((sub, what, frozenset({want}), "the config expects"))
        eds = Path(self.config.eds)
        if eds.resolve() == GENERIC_EDS.resolve():
            return wanted
        info = self._od.device_information
        for sub, what, number, name in ((1, "vendor id", info.vendor_number, info.vendor_name),
                                        (2, "product code", info.product_number, info.product_name)):
            var = variable(self._od, OD.IDENTITY, sub)
            values = {v for v in (number, var.default if var is not None else None) if isinstance(v, int) and v}
            if values:
                wanted.append((sub, what, frozenset(values), f"its EDS {eds.name}{f' ({name})' if name else ''} names"))
        return wanted

    def _check_identity(self) -> None:
        """0x1018 against the EDS and the config, before any other object of the drive is touched:
        a drive of another vendor or product at this node id is a boot error naming both ids."""
        for sub, what, allowed, source in self.expected_identity():
            raw = self._sdo.read_optional(OD.IDENTITY, sub) if sub > 1 else self._sdo.read(OD.IDENTITY, sub)
            if raw is None:
                logger.info("node %d (%s): no 0x1018:%d (%s) to compare", self.node_id, self.name, sub, what)
                continue
            got = struct.unpack("<I", raw[:4].ljust(4, b"\0"))[0]
            if got not in allowed:
                want = " or ".join(f"0x{v:08X}" for v in sorted(allowed))
                raise BootError(f"node {self.node_id} ({self.name}): identity mismatch: {what} is"
                                f" 0x{got:08X} on the device, {source} {want}. Is the right drive at this"
                                " node id, and is the config's EDS the drive's own? Nothing else was written to it.",
                                node_id=self.node_id, step="identity", index=OD.IDENTITY, subindex=sub)

    def _disarm_by_sdo(self) -> None:
        """Boot: a drive found powered (configured without a reset after another master had it,
        or left enabled by a driver that did not stop it) is quick-stopped and disabled before
        anything else, by SDO (no PDOs flow before NMT start): a boot never leaves a drive armed
        behind a driver that says it is not enabled."""
        state = decode_state(self._sdo.read_number(OD.STATUSWORD))
        if state not in (State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            return
        logger.warning("%s (node %d): found %s at boot (another master, or a driver that did not stop it);"
                       " quick stop, then disable voltage", self.name, self.node_id, state.name)
        if state == State.OPERATION_ENABLED:
            self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.QUICK_STOP)))
        if state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            stood, sw = self._braked_by_sdo()
            if not stood:
                logger.warning("%s (node %d): still braking at the bound of its quick stop at boot; its voltage is"
                               " disabled now, and its shaft may coast from there", self.name, self.node_id)
            if decode_state(sw) == State.FAULT:
                return  # its fault reaction ended it: the power stage is off (a fault reset is the user's act)
        self._sdo.write(OD.CONTROLWORD, 0, struct.pack("<H", int(Command.DISABLE_VOLTAGE)))
        self._poll_state_sdo(lambda st, sw: st == State.SWITCH_ON_DISABLED, "disable voltage at boot")

    def _braked_by_sdo(self) -> tuple[bool, int]:
        """After the boot's quick stop: until the drive has braked (as the safe stop judges it:
        :func:`cia402.braked`, its velocity read by SDO), for at most the ramp from its speed now at
        the deceleration its quick stop brakes at now (:meth:`_stop_ramp_deg_s2`, read from it:
        another master may have changed it). (False: still braking at that bound, its last statusword)."""
        bound = self._power.brake_bound_s(self._velocity_by_sdo(), self._stop_ramp_deg_s2())
        return self._poll_sdo(lambda st, sw: braked(st, sw, self._velocity_by_sdo() if st == State.QUICK_STOP_ACTIVE
                                                    else 0.0), max(TRANSITION_TIMEOUT_S, bound))

    def _stop_ramp_deg_s2(self) -> float:
        """The deceleration the drive's quick stop brakes at, deg/s^2, as the drive holds it now (by
        SDO, whatever the EDS lists): its quick-stop ramp (0x6085), or its slow-down ramp (0x6084)
        where its quick-stop option (0x605A) is 1 or 5; where it says none, the slower of the
        config's two (a wait too long ends at its bound; one too short cuts a ramp)."""
        fallback = min(self.config.quick_stop_decel_deg_s2, self.config.profile_acceleration_deg_s2)
        option = self._sdo.read_optional(OD.QUICK_STOP_OPTION, 0)
        slow_down = option is not None and int.from_bytes(option[:2], "little", signed=True) in (1, 5)
        raw = self._sdo.read_optional(OD.PROFILE_DECELERATION if slow_down else OD.QUICK_STOP_DECELERATION, 0)
        per_deg_s2 = self._cache.scale.acceleration_to_drive(1000.0) / 1000.0  # drive units per deg/s^2
        value = int.from_bytes(raw[:4], "little") if raw is not None else 0
        return value / per_deg_s2 if value > 0 and per_deg_s2 > 0 else fallback

    def _note_stop_ramp(self) -> None:
        """What the drive's quick stop brakes at, read back after every write (the safe stop waits
        for that ramp; the limit and step guards brake by it): the config's, the drive's maximum
        where the config's was beyond its range, or its slow-down ramp where it kept option 1 or 5."""
        self._at(OD.QUICK_STOP_DECELERATION, 0)
        self._cache.set_quick_stop_decel(self._stop_ramp_deg_s2())

    def _velocity_by_sdo(self) -> float:
        """The drive's velocity actual value (0x606C) now, deg/s, in the scale the driver last knew
        (the config's before a first boot read the drive's units); 0 where the drive has none."""
        if not has_object(self._od, OD.VELOCITY_ACTUAL):
            return 0.0
        return self._cache.scale.counts_s_to_deg_s(self._sdo.read_number(OD.VELOCITY_ACTUAL))

    def _poll_state_sdo(self, done: Callable[[State, int], bool], doing: str) -> None:
        held, sw = self._poll_sdo(done, TRANSITION_TIMEOUT_S)
        if not held:
            raise DriveTimeoutError(f"{self.name} (node {self.node_id}): {doing}: still in {decode_state(sw).name}"
                                    f" (statusword 0x{sw:04X}) after {TRANSITION_TIMEOUT_S:g} s",
                                    node_id=self.node_id, statusword=sw)

    def _poll_sdo(self, done: Callable[[State, int], bool], timeout_s: float) -> tuple[bool, int]:
        """The statusword read by SDO until ``done(state, statusword)`` (noted in the cache then), for
        at most ``timeout_s``: (whether it came, the last statusword read)."""
        deadline = time.monotonic() + timeout_s
        while True:
            sw = self._sdo.read_number(OD.STATUSWORD)
            if done(decode_state(sw), sw):
                self._cache.note_statusword(sw)
                return True, sw
            if time.monotonic() > deadline:
                return False, sw
            time.sleep(0.02)

    def _read_units(self) -> None:
        """Scale from the drive's own unit objects (factor group, SI units, rated torque), each
        read by SDO whatever the EDS lists: an EDS that omits 0x60A9 does not make an EPOS4's
        rpm counts/s. What came from where is said once at INFO (a conflict with the config at
        WARNING); later boots say it at DEBUG."""
        cfg = self.config
        objects = read_unit_objects(self._sdo.read_optional)
        self.unit_objects = objects
        try:
            scale, notes = scale_from_objects(cfg.counts_per_rev, cfg.gear_ratio, cfg.rated_torque_nm, objects,
                                              invert=cfg.invert, offset_deg=cfg.offset_deg)
        except UnitError as err:
            raise BootError(f"node {self.node_id} ({self.name}): boot step 'units' refused: {err}",
                            node_id=self.node_id, step="units", index=err.index, subindex=0) from err
        self._cache.set_scale(scale)
        for note in notes:
            level = logging.WARNING if "(config says" in note else logging.INFO
            logger.log(level if not self.boot_count else logging.DEBUG, "node %d (%s): %s", self.node_id,
                       self.name, note)

    def _quick_stop_decel(self) -> int:
        """The configured quick-stop deceleration in drive units, at most what the drive takes
        (its EDS HighLimit): the fastest stop it allows, said in a warning."""
        wanted = self._cache.scale.acceleration_to_drive(self.config.quick_stop_decel_deg_s2)
        var = variable(self._od, OD.QUICK_STOP_DECELERATION, 0)
        high = var.max if var is not None else None
        if isinstance(high, int) and wanted > high:
            logger.warning("node %d (%s): quick-stop deceleration %g deg/s^2 is beyond the drive's range"
                           " (0x6085 <= %d); using its maximum, %.0f deg/s^2", self.node_id, self.name,
                           self.config.quick_stop_decel_deg_s2, high, high * self.config.quick_stop_decel_deg_s2 / wanted)
            return high
        return wanted

    def _wake_stopped(self) -> bool:
        """A drive heard in NMT STOPPED (told so while it was lost, or by another master) answers
        no SDO: NMT pre-operational first, then it is reset as a first boot resets it. True then."""
        if self._cache.reported_nmt != "STOPPED":
            return False
        self._send_nmt(NmtCommand.ENTER_PREOPERATIONAL)
        self._cache.wait_until(lambda: self._cache.reported_nmt != "STOPPED", self.config.heartbeat_timeout_s)
        return True

    def reconfigure(self) -> None:
        """Bus worker: configure a drive that reset or power-cycled (boot-up seen) again; enable
        it again only when it was enabled and the config says ``restore_enable_after_reboot`` (an
        enable refused leaves it configured and disabled). A failure to configure is reported, and
        the supervisor hands it over again: a drive's or a bus's error after REBOOT_RETRY_S;
        anything else (a fault of this driver's) is logged with its cause and tried again after a
        back-off doubling up to REBOOT_BACKOFF_MAX_S. It never ends the re-configuration for good."""
        mark = self._channel.stop_mark  # a stop from here on (a /disarm) cancels the restore
        restore = self._channel.was_enabled and self.config.restore_enable_after_reboot
        try:
            self._channel.forget_commanded()
            self.boot(reset=self._wake_stopped())
        except MotorError as err:
            self._unexpected_in_row = 0
            logger.error("%s: re-configuration after a reset failed: %s; retrying in %g s", self.name, err,
                         REBOOT_RETRY_S)
            self._port.report(RebootFailed(self.name, REBOOT_RETRY_S, str(err)))
        except Exception as err:
            retry_s = min(REBOOT_RETRY_S * 2**self._unexpected_in_row, REBOOT_BACKOFF_MAX_S)
            self._unexpected_in_row += 1
            logger.error("%s: re-configuration after a reset failed unexpectedly (%s: %s; %d in a row); retrying"
                         " in %g s", self.name, type(err).__name__, err, self._unexpected_in_row, retry_s,
                         exc_info=self._unexpected_in_row == 1)  # the traceback once, not at each retry
            self._port.report(RebootFailed(self.name, retry_s, f"{type(err).__name__}: {err}"))
        else:
            self._unexpected_in_row = 0
            if restore and not self._channel.closed:
                if self._channel.stop_mark != mark:
                    logger.warning("%s: configured again after a reset and left disabled, as stopped meanwhile (%s);"
                                   " /arm (or enable) enables it", self.name, self._channel.stopped_by)
                else:
                    self._enable_again(mark)

    def _enable_again(self, mark: int) -> None:
        """After a good re-configuration: enabled again as it was. A refusal of the drive's (STO
        low, a fault), or a fault of this driver's, leaves it configured and disabled, said once;
        its configuration is not thrown away and the drive is not reset again for it."""
        try:
            self._power.enable(unless_stopped_since=mark)  # a stop from now until the enable registers wins
        except MotorError as err:
            if self._channel.stop_mark != mark:  # a stop won the race with the enable
                logger.warning("%s: configured again after a reset and left disabled, as stopped meanwhile (%s);"
                               " /arm (or enable) enables it", self.name, self._channel.stopped_by)
                return
            logger.error("%s: configured again after a reset, but enabling it again failed: %s; it stays configured"
                         " and disabled: arm it (/arm, or enable) once the cause is dealt with", self.name, err)
        except Exception as err:  # counted and logged with its trace by the supervisor, in /diagnostics
            logger.error("%s: configured again after a reset, but enabling it again failed unexpectedly (%s); it"
                         " stays configured and disabled: arm it (/arm, or enable), and report this", self.name,
                         cause_of(err))
            self._port.report(RestoreFailed(self.name, err))


#: CiA 301 dates count days from 1984-01-01 (the Unix time of its start, in days).
EPOCH_1984_DAYS = 5113
MS_PER_DAY = 86_400_000


def configuration_stamp(unix_s: float) -> tuple[int, int]:
    """0x1020's date (days since 1984-01-01) and time (ms after midnight) of ``unix_s``."""
    days, rest_s = divmod(unix_s, 86_400.0)
    return int(days) - EPOCH_1984_DAYS, int(rest_s * 1000) % MS_PER_DAY


def writable(od: ObjectDictionary, index: int, subindex: int) -> bool:
    """The EDS lists the object, writable by SDO."""
    var = variable(od, index, subindex)
    return var is not None and "w" in var.access_type
