"""The rover's drive system: /cmd_vel into skid-steer wheel commands, odometry from the wheels'
measured positions, and what it says of each wheel.

Owner: the executor thread that runs the drive system's tick (its control loop).

- :mod:`.drive_system`: the /cmd_vel drive system node: commands, timeouts, a lost wheel, /odom
  and /tf
- :mod:`.wheels`: what the drive system says of a wheel and which wheels it left out (pure)
"""
