"""What the bus's worker owns while a drive is not booted: its boot, and the host watch boot
configures.

Owner: the bus's worker (or the caller of ``Boot.boot``), while the cache says the drive is not
booted, so that nothing else commands it meanwhile; whether it is booted is the supervisor's
(:mod:`motor_driver.drive.ledger`), to which a boot reports its start and end.

- :mod:`.boot`: boot as a table of named steps; re-configuration after a reset
- :mod:`.hostwatch`: how the drive watches the host (heartbeat consumer, node guarding), and the
  frames the supervisor sends a drive it stops hearing or loses to another master
"""
