"""What the bus's receive thread owns: one drive's received state, decoded frame by frame.

Owner: the bus's receive thread (canopen's notifier) writes all of it and sends nothing; every
other thread reads the immutable values it publishes (:mod:`motor_driver.drive.values`) or posts
to their owners.

- :mod:`.state`: the state cache (TPDO, heartbeat, EMCY): each TPDO's values published as one
  immutable value in one assignment; waiters notified
- :mod:`.position`: which position samples to believe, and how fast the joint speeds up
- :mod:`.tpdo`: one TPDO's values into what the drive said last, decoded alike for the
  recorder's bus view
"""
