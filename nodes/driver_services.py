"""The driver's services as two nodes, each on an executor thread of its own: the stops
(``quick_stop``, ``disable``, ``halt`` per drive, ``disarm`` for the whole rover), which answer
at once whatever else runs, and the rest (``enable``, ``recover``, ``home``, ``set_mode``, SDO
read and write per drive, ``arm`` for the whole rover), which block for up to seconds. A slow
service never delays a topic, and never a stop: a stop preempts the operation it interrupts in
the driver (the command channel) and must not queue behind it in ROS either.
"""

from __future__ import annotations

from collections.abc import Callable
from struct import error as struct_error
from typing import Any

from rclpy.node import Node
from rovercan_msgs.srv import SdoRead, SdoWrite, SetMode
from std_srvs.srv import Trigger

from can_config.errors import RovercanError
from can_config.objects import OperationMode, sdo_abort_text
from motor_driver import Drive, MotorDriver

SERVICE_JOIN_S = 5.0  # longest a service callback may take to notice the driver is closed


def trigger(driver: MotorDriver, joint: str, service: str, action: Callable[[], object]) -> Callable[[Any, Any], Any]:
    """A std_srvs/Trigger callback that runs ``action`` and says what happened."""
    def call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            action()
            response.success, response.message = True, f"{joint}: {service} done; state {driver.drives[joint].state.name}"
        except RovercanError as err:
            response.success, response.message = False, str(err)
        except Exception as err:
            response.success, response.message = False, f"{joint}: {service} failed unexpectedly: {err!r}"
        return response
    return call


def every_drive(driver: MotorDriver, service: str, action: Callable[[Drive], object]) -> Callable[[Any, Any], Any]:
    """A std_srvs/Trigger callback that runs ``action`` on every drive, each whatever the others
    did, and says which failed (success only when none did)."""
    def call(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        failed = []
        for drive in driver:
            try:
                action(drive)
            except RovercanError as err:
                failed.append(str(err))
            except Exception as err:
                failed.append(f"{drive.name}: {service} failed unexpectedly: {err!r}")
        states = ", ".join(f"{d.name} {d.state.name}" for d in driver)
        response.success = not failed
        response.message = (f"{service}: {'; '.join(failed)}; now {states}" if failed
                            else f"{service} done: {states}")
        return response
    return call


def disarm(drive: Drive) -> None:
    """Quick stop (the drive decelerates on its own ramp), then disable: no torque."""
    drive.quick_stop()
    drive.disable()


class DriverStopsNode(Node):
    """The per-drive stops (``quick_stop``, ``disable``, ``halt``) and ``disarm`` (every drive
    quick-stopped, then disabled), in a node of their own on an executor thread of their own
    (see main): nothing but another stop is ever ahead of one."""

    def __init__(self, driver: MotorDriver, **kwargs: Any) -> None:
        super().__init__("rovercan_driver_stops", **kwargs)
        for name, drive in driver.drives.items():
            base = drive.config.ros_prefix
            for service, action in (("quick_stop", drive.quick_stop), ("disable", drive.disable),
                                    ("halt", drive.halt)):
                self.create_service(Trigger, f"{base}/{service}", trigger(driver, name, service, action))
        self.create_service(Trigger, "disarm", every_drive(driver, "disarm", disarm))


class DriverServicesNode(Node):
    """The per-drive services that wait (``enable``, ``recover``, ``home``, set mode, SDO), in a
    node of their own: they block for up to seconds, so they run on their own executor thread
    while topics, timers and the stops stay on theirs (see main)."""

    def __init__(self, driver: MotorDriver, **kwargs: Any) -> None:
        super().__init__("rovercan_driver_services", **kwargs)
        self.driver = driver
        self.create_service(Trigger, "arm", every_drive(driver, "arm", lambda drive: drive.enable()))
        for name, drive in driver.drives.items():
            base = drive.config.ros_prefix
            for service, action in (("enable", drive.enable), ("recover", drive.recover), ("home", drive.home)):
                self.create_service(Trigger, f"{base}/{service}", trigger(driver, name, service, action))
            self.create_service(SetMode, f"{base}/set_mode", self._set_mode(drive))
            self.create_service(SdoRead, f"{base}/sdo_read", self._sdo_read(drive))
            self.create_service(SdoWrite, f"{base}/sdo_write", self._sdo_write(drive))

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
                value = drive.sdo_read_value(request.index, request.subindex)
            except RovercanError as err:
                response.success, response.message = False, str(err)
                return response
            response.success = True
            if isinstance(value, int):
                response.value, response.text = value, str(value)
            elif isinstance(value, float):
                response.value, response.text = int(value), repr(value)
            else:
                response.text = value.decode("latin-1", errors="replace")
            response.message = f"0x{request.index:04X}:{request.subindex} = {response.text}"
            return response
        return call

    def _sdo_write(self, drive: Drive) -> Callable[[Any, Any], Any]:
        def call(request: SdoWrite.Request, response: SdoWrite.Response) -> SdoWrite.Response:
            try:
                drive.sdo_write_checked(request.index, request.subindex, request.value)
                response.success, response.message = True, f"0x{request.index:04X}:{request.subindex} written"
            except RovercanError as err:
                response.success, response.message = False, str(err)
                code = getattr(err, "abort_code", None)
                if code is not None and sdo_abort_text(code) not in response.message:
                    response.message += f" ({sdo_abort_text(code)})"
            except struct_error as err:
                response.success, response.message = False, f"value {request.value} does not fit the object: {err}"
            return response
        return call
