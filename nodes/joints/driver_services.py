"""The driver's services as two nodes, each on an executor of its own (nodes/assembly.py): the
stops (``quick_stop``, ``disable``, ``halt`` per drive, ``disarm`` for the whole rover), which
answer at once whatever else runs, and the rest (``enable``, ``recover``, ``home``, ``set_mode``,
SDO read and write per drive, ``arm`` for the whole rover), which block for up to seconds (homing:
up to ``homing_timeout_s``). A slow service never delays a topic, and never a stop: a stop
preempts the operation it interrupts in the driver (the command channel) and must not queue
behind it in ROS either.

The services that wait are in one callback group per joint and one for the rover's ``arm``
(:attr:`DriverServicesNode.groups`), on a multi-threaded executor with a thread per group: a
joint's calls wait for that joint's long operation only, never for another joint's. Two calls
on one joint are taken one after the other; the driver refuses at once an operation on a drive
busy with another (``arm`` reports a homing drive as busy, and enables the others).

Every answer says what happened: a refusal or a drive's error by its own text; an unexpected
exception (a bug) by the supervisor that wraps each callback (:func:`nodes.process.spinning.supervise`: a
failed answer naming the service, the trace logged once, counted on /diagnostics); an SDO value
the SdoRead reply's int64 cannot carry (NaN, an infinity, an UNSIGNED64 above int64) as text, its
``value`` 0 (:func:`reply_value`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from struct import error as struct_error
from typing import Any

from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rovercan_msgs.srv import SdoRead, SdoWrite, SetMode
from std_srvs.srv import Trigger

from can_config.errors import RovercanError
from can_config.objects import OperationMode, sdo_abort_text
from motor_driver import Drive, MotorDriver
from nodes.process.spinning import CallbackFailures

SERVICE_JOIN_S = 5.0  # longest a service callback may take to notice the driver is closed


#: The range of an SdoRead reply's ``value`` (int64).
INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1


def reply_value(value: int | float | bytes) -> tuple[int, str, bool]:
    """An SDO value as an SdoRead reply's ``value`` (int64) and ``text``, and whether the value
    carries it: a number the int64 cannot carry (NaN, an infinity, a REAL beyond int64, an
    UNSIGNED64 above int64) is ``value`` 0 and said by ``text`` alone ("nan", "inf", the exact
    integer); a REAL's ``value`` is its whole part; a string's 0."""
    if isinstance(value, bytes):
        return 0, value.decode("latin-1", errors="replace"), True
    text = repr(value) if isinstance(value, float) else str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return 0, text, False
    whole = int(value)
    return (whole, text, True) if INT64_MIN <= whole <= INT64_MAX else (0, text, False)


def state_said(drive: Drive) -> str:
    """A drive's state for a service's answer: its last statusword's, or LOST with the last one
    heard (a lost drive's statusword is no news of it)."""
    state = drive.cache.state.name
    return f"LOST (last heard {state})" if drive.cache.lost else state


def trigger(drive: Drive, service: str, action: Callable[[], object]) -> Callable[[Any, Any], Any]:
    """A std_srvs/Trigger callback that runs ``action`` and says what happened. An unexpected
    exception is the supervisor's (nodes/process/spinning.py: logged with its trace, counted, answered)."""
    def call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            action()
            response.success, response.message = True, f"{drive.name}: {service} done; state {state_said(drive)}"
        except RovercanError as err:
            response.success, response.message = False, str(err)
        return response
    return call


def answer(response: Trigger.Response, service: str, failed: list[str], drives: Mapping[str, Drive]) -> Trigger.Response:
    """``response`` for a whole-rover service: success only when nothing failed, the failures
    named, and every drive's state."""
    states = ", ".join(f"{d.name} {state_said(d)}" for d in drives.values())
    response.success = not failed
    response.message = f"{service}: {'; '.join(failed)}; now {states}" if failed else f"{service} done: {states}"
    return response


def arm(drives: Mapping[str, Drive], failures: CallbackFailures) -> Callable[[Any, Any], Any]:
    """/arm: enable every drive, each whatever the others did; a drive busy (homing) is refused at
    once and named; an unexpected exception of one drive's is logged, counted and named."""
    def call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        failed = []
        for drive in drives.values():
            try:
                drive.enable()
            except RovercanError as err:
                failed.append(str(err))
            except Exception as err:  # the others are armed all the same
                failed.append(failures.record(f"service /arm on {drive.name}", err))
        return answer(response, "arm", failed, drives)
    return call


def disarm(driver: MotorDriver, drives: Mapping[str, Drive], failures: CallbackFailures) -> Callable[[Any, Any], Any]:
    """/disarm: the driver's one safe stop (:meth:`MotorDriver.safe_stop`: quick stop, then
    disable voltage, no torque) on every drive, each whatever the others did."""
    def call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            failed = driver.safe_stop(drives.values())
        except Exception as err:  # every drive's state is said all the same
            failed = [failures.record("service /disarm", err)]
        return answer(response, "disarm", failed, drives)
    return call


class DriverStopsNode(Node):
    """The per-drive stops (``quick_stop``, ``disable``, ``halt``) and ``disarm`` (the driver's
    safe stop on every drive), in a node of their own on an executor thread of their own
    (nodes/assembly.py): nothing but another stop is ever ahead of one."""

    def __init__(self, driver: MotorDriver, drives: Mapping[str, Drive] | None = None, *,
                 failures: CallbackFailures | None = None, **kwargs: Any) -> None:
        super().__init__("rovercan_driver_stops", **kwargs)
        drives = dict(driver.drives) if drives is None else drives
        failures = CallbackFailures() if failures is None else failures
        for drive in drives.values():
            base = drive.config.ros_prefix
            for service, action in (("quick_stop", drive.quick_stop), ("disable", drive.disable),
                                    ("halt", drive.halt)):
                self.create_service(Trigger, f"{base}/{service}", trigger(drive, service, action))
        self.create_service(Trigger, "disarm", disarm(driver, drives, failures))


class DriverServicesNode(Node):
    """The per-drive services that wait (``enable``, ``recover``, ``home``, set mode, SDO) and the
    rover's ``arm``, in a node of their own, each joint's in a callback group of its own
    (:attr:`groups`; the module docstring says why)."""

    def __init__(self, driver: MotorDriver, drives: Mapping[str, Drive] | None = None, *,
                 failures: CallbackFailures | None = None, **kwargs: Any) -> None:
        super().__init__("rovercan_driver_services", **kwargs)
        self.driver = driver
        drives = dict(driver.drives) if drives is None else drives
        failures = CallbackFailures() if failures is None else failures
        #: the callback group of each joint, and of the whole rover's services (key ``""``)
        self.groups: dict[str, CallbackGroup] = {"": MutuallyExclusiveCallbackGroup()}
        self.create_service(Trigger, "arm", arm(drives, failures), callback_group=self.groups[""])
        for name, drive in drives.items():
            group = self.groups[name] = MutuallyExclusiveCallbackGroup()
            base = drive.config.ros_prefix
            for service, action in (("enable", drive.enable), ("recover", drive.recover), ("home", drive.home)):
                self.create_service(Trigger, f"{base}/{service}", trigger(drive, service, action), callback_group=group)
            self.create_service(SetMode, f"{base}/set_mode", self._set_mode(drive), callback_group=group)
            self.create_service(SdoRead, f"{base}/sdo_read", self._sdo_read(drive), callback_group=group)
            self.create_service(SdoWrite, f"{base}/sdo_write", self._sdo_write(drive), callback_group=group)

    def _set_mode(self, drive: Drive) -> Callable[[Any, Any], Any]:
        def call(request: SetMode.Request, response: SetMode.Response) -> SetMode.Response:
            try:
                mode = OperationMode[request.mode.strip().upper()]
            except KeyError:
                response.success = False
                response.message = (f"unknown mode {request.mode!r}; allowed: "
                                    f"{', '.join(m.name for m in OperationMode if m != OperationMode.NO_MODE)}")
                return response
            try:
                drive.set_mode(mode)
                response.success, response.message = True, f"{drive.name}: mode {mode.name} confirmed by 0x6061"
            except RovercanError as err:
                response.success, response.message = False, str(err)
            return response
        return call

    def _sdo_read(self, drive: Drive) -> Callable[[Any, Any], Any]:
        def call(request: SdoRead.Request, response: SdoRead.Response) -> SdoRead.Response:
            try:
                value = drive.sdo.read_value(request.index, request.subindex)
            except RovercanError as err:
                response.success, response.message = False, str(err)
                return response
            response.success = True
            response.value, response.text, carried = reply_value(value)
            response.message = f"0x{request.index:04X}:{request.subindex} = {response.text}"
            if not carried:
                response.message += " (value 0: the reply's int64 cannot carry it; text says it)"
            return response
        return call

    def _sdo_write(self, drive: Drive) -> Callable[[Any, Any], Any]:
        def call(request: SdoWrite.Request, response: SdoWrite.Response) -> SdoWrite.Response:
            try:
                drive.sdo.write_checked(request.index, request.subindex, request.value)
                response.success, response.message = True, f"0x{request.index:04X}:{request.subindex} written"
            except RovercanError as err:
                response.success, response.message = False, str(err)
                code = getattr(err, "abort_code", None)
                if code is not None and sdo_abort_text(code) not in response.message:
                    response.message += f" ({sdo_abort_text(code)})"
            except (struct_error, OverflowError, ValueError) as err:
                response.success, response.message = False, f"value {request.value} does not fit the object: {err}"
            return response
        return call
