"""What every node of the driver's process shares, whatever its role.

Owner: the process's main thread sets these up (signal handlers, the log bridge, each node's
parameters at its construction); the executors' threads spin, each named.

- :mod:`.spinning`: the process's life cycle: one stop path, one teardown order, the executors and
  their threads, real-time priority
- :mod:`.logbridge`: Python logging bridged to a node's rclpy logger
- :mod:`.params`: every ROS parameter, defined once with a description and a range, and which
  node declares which
- :mod:`.qos`: the QoS profiles, chosen on purpose
- :mod:`.bond`: the managed side of a bond with a lifecycle manager (Nav2's), while active
"""
