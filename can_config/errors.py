"""The one exception tree of rovercan.

Every error the stack raises on purpose derives from :class:`RovercanError`; each also
inherits the matching built-in so callers can catch what they already know::

    RovercanError
    ├── ConfigError (ValueError)              can_config: a bad file, key or value
    │   └── EdsError                          an EDS that is missing, unreadable or lacks objects
    ├── MotorError                            motor_driver
    │   ├── BootError                         a drive could not be configured (step, object, code)
    │   ├── UnitError (ValueError)            a unit object the drive reports is implausible
    │   ├── SdoError                          SDO abort (carries abort_code) ...
    │   │   └── SdoTimeoutError (TimeoutError)  ... or no answer
    │   ├── DriveStateError                   CiA 402 transition refused / drive faulted / lost
    │   │   └── DriveTimeoutError (TimeoutError)
    │   ├── CommandRejected (ValueError)      NaN, out of limits, unsupported mode: nothing sent
    │   │   ├── CommandWouldWait              asked to go out at once, it needs the drive's answer first
    │   │   └── TrajectoryRejected            a joint trajectory refused (carries its control_msgs code)
    │   ├── ForeignMasterError                another master is live on the bus: nothing was sent
    │   ├── BusLostError (ConnectionError)    the bus went away
    │   └── CdrError (ValueError)             a message that does not fit its ROS 2 type (motor_driver.recording.cdr)
    └── SimError                              virtual_can: emulator misuse
        └── ProtocolError (ValueError)        a malformed socketcand line

The tree lives in ``can_config`` because every layer may import it and it imports nothing.

Owner: none; exception types only.
"""

from __future__ import annotations


class RovercanError(Exception):
    """Root of every error rovercan raises on purpose."""


class ConfigError(RovercanError, ValueError):
    """A configuration file, key or value is wrong. The message names where and what is allowed."""


class EdsError(ConfigError):
    """An EDS file is missing, unreadable, or lacks an object the stack needs."""


class MotorError(RovercanError):
    """Root of the driver's errors."""


class BootError(MotorError):
    """A drive could not be booted; says which step, which object and which abort code."""

    def __init__(self, message: str, *, node_id: int, step: str, index: int | None = None,
                 subindex: int | None = None, abort_code: int | None = None) -> None:
        super().__init__(message)
        self.node_id = node_id
        self.step = step
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code


class UnitError(MotorError, ValueError):
    """A unit or scaling object a drive reports (or a value derived from it) is out of its
    plausible range; carries the object and the value. Nothing is written with it."""

    def __init__(self, message: str, *, index: int, value: float) -> None:
        super().__init__(message)
        self.index = index
        self.value = value


class SdoError(MotorError):
    """An SDO transfer was aborted; carries the abort code and its meaning."""

    def __init__(self, message: str, *, node_id: int, index: int, subindex: int,
                 abort_code: int | None = None) -> None:
        super().__init__(message)
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code


class SdoTimeoutError(SdoError, TimeoutError):
    """An SDO request got no answer in time."""


class DriveStateError(MotorError):
    """The drive is not in a state that allows the request (faulted, lost, not enabled)."""

    def __init__(self, message: str, *, node_id: int, statusword: int | None = None,
                 error_code: int | None = None) -> None:
        super().__init__(message)
        self.node_id = node_id
        self.statusword = statusword
        self.error_code = error_code


class DriveTimeoutError(DriveStateError, TimeoutError):
    """A CiA 402 transition or mode switch was not confirmed in time."""


class CdrError(MotorError, ValueError):
    """A message that does not fit its ROS 2 type's definition (a field missing or of the wrong kind)."""


class CommandRejected(MotorError, ValueError):
    """A command was refused before anything was sent (NaN, beyond a limit, unsupported)."""


class CommandWouldWait(CommandRejected):
    """A command asked to go out at once (``at_once=True``: frames only) needs the drive's answer
    first (a mode switch, a target the drive takes only by SDO). Nothing was sent; send it again
    from a thread that may wait (the ROS node hands it to a worker of its joint)."""


class TrajectoryRejected(CommandRejected):
    """A joint trajectory (FollowJointTrajectory) refused before anything moved, or ended; carries
    the standard's error code (``code``: control_msgs/FollowJointTrajectory's, e.g. -1 INVALID_GOAL)."""

    def __init__(self, message: str, *, code: int) -> None:
        super().__init__(message)
        self.code = code


class ForeignMasterError(MotorError):
    """Another master is live on the bus (its heartbeat, SYNC, NMT or commands were heard): the
    driver or bench command refused to start; nothing was sent. Carries the evidence."""

    def __init__(self, message: str, *, evidence: str) -> None:
        super().__init__(message)
        self.evidence = evidence


class BusLostError(MotorError, ConnectionError):
    """The CAN bus (adapter, socket or server) went away."""


class SimError(RovercanError):
    """Misuse of the emulator."""


class ProtocolError(SimError, ValueError):
    """A socketcand protocol line that cannot be parsed."""
