"""The drive layer's tunable numbers and fixed codes, in one place.

Read-only at run time; module constants so that tests and benchmarks can see what the driver
waits for.

Owner: none; values only, read-only at run time.
"""

from can_config.objects import OperationMode

#: An SDO read of an object whose type has no size (a string, a domain) brings at most this much;
#: a drive that announces or sends more is cut off with an abort.
SDO_UPLOAD_MAX_BYTES = 1024
#: A whole SDO read (all its segments) takes at most this many SDO timeouts.
SDO_TRANSFER_TIMEOUTS = 4
SDO_ABORT_OUT_OF_MEMORY = 0x0504_0005
SDO_ABORT_TIMEOUT = 0x0504_0000
#: Timeouts (seconds); module constants so tests and benchmarks can override them.
TRANSITION_TIMEOUT_S = 1.0
MODE_SWITCH_TIMEOUT_S = 1.0
STATE_POLL_S = 0.002
REBOOT_RETRY_S = 0.5
#: A re-configuration that failed unexpectedly (not a drive's or a bus's error: a bug) is tried
#: again after REBOOT_RETRY_S, doubled at each failure in a row up to this.
REBOOT_BACKOFF_MAX_S = 8.0
#: A boot starts its configuration again when the drive reset during it (a boot-up heard), or
#: does not hold what was written, at most this many times; then it is a BootError.
BOOT_RESTARTS_MAX = 8
#: How long a command waits for the command channel before it is refused. The channel's lock is
#: held only to decide and send one frame (never an SDO or a wait), so this bounds a hang, not
#: a queue: a few frames and a thread switch of the interpreter (5 ms) fit many times. An
#: operation under way (enable, homing) refuses a command at once, without waiting.
COMMAND_LOCK_WAIT_S = 0.1
#: 0x605A: slow down on the quick-stop ramp, then Switch On Disabled.
QUICK_STOP_THEN_DISABLE = 2
#: Reaction time of the driver's own limit guard (supervisor period, SYNC, TPDO age), as distance
#: travelled at the current speed before braking starts.
LIMIT_MARGIN_S = 0.05
#: The limit guard moves a sampled position on by its velocity for at most this long.
MAX_EXTRAPOLATION_S = 0.2
#: How long a torque-commanded joint goes on speeding up before a brake decided at the guard's
#: next look takes hold: that look (the supervisor's 10 ms period, late by up to 15 ms on a
#: quiet CI machine) and the next SYNC (10 ms). 25 ms let a push pass the limit by 0.6 deg with
#: the looks 25 ms apart.
LIMIT_ACCEL_MARGIN_S = 0.035
#: Velocity samples further apart than this give no acceleration (a gap, not a slope).
MAX_ACCEL_GAP_S = 0.2
#: A position the joint cannot have reached is taken only once this many further samples agree
#: with it (a real jump: homing, a reboot). One corrupted TPDO is held back, and so is the same
#: corruption twice in a row (at the emulator's 10 % corruption rate, estimated at one two-second
#: run in a hundred; seen once: a wheel reported 47 million degrees for a SYNC period).
JUMP_CONFIRMATIONS = 2
#: A position jump is judged at the drive's measured speed up to this many times the joint's
#: limit: a shaft coasting past the limit keeps its position current (the simulator's wheel
#: coasted at 30x its limit after a torque command in the kernel tier), while a velocity from a
#: bad frame cannot open the check without bound.
MEASURED_SPEED_CAP = 50
NO_HOST_WATCH = "no drive-side stop on host loss"
#: SDO aborts of a value out of the object's range (CiA 301): the drive cannot take that entry.
VALUE_RANGE_ABORTS = frozenset({0x0609_0030, 0x0609_0031, 0x0609_0032, 0x0609_0036})
#: A continuous joint's degree command is an angle modulo 360; beyond this it is a mistake.
CONTINUOUS_COMMAND_LIMIT_DEG = 360.0
#: At boot, how long to listen for the drive's heartbeat before asking its error history.
HOST_LOSS_CHECK_WAIT_S = 0.25
#: The controlword bits of Enable Operation (switch on, enable voltage, no quick stop, enable
#: operation): motion frames go out only while this driver's last controlword had them all.
ENABLED_CW_MASK = 0x000F
#: Modes whose command is a velocity (the watchdog and the limit guard send zero velocity) ...
VELOCITY_MODES = (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY)
#: ... and a torque (they send zero torque and, at a limit, quick-stop).
TORQUE_MODES = (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE)


#: enable() plans at most this many transitions (three are needed from Switch On Disabled; the
#: rest cover a drive that showed a state on its way, or was stopped by another, meanwhile).
ENABLE_STEPS = 8
#: A wait after a frame of ours takes a statusword sent after it; a drive that sends its
#: statusword only on change is taken at its last one after this many SYNC periods (plus a margin).
FRESH_STATUS_SYNCS = 3
FRESH_STATUS_MARGIN_S = 0.05

#: An enabled drive must be watching the host (its consumer or life guarding started): the host
#: heartbeats sent, or guard answers taken, since it was told to watch, before it is enabled
#: (drive/hostwatch.py: the first may have been on its way)
WATCH_START_BEATS = 2
#: ... waited for at least this many of their periods by enable, whatever its own timeout
WATCH_START_PERIODS = 4
