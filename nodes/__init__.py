"""Thin rclpy nodes over the core: topics, services and parameters in, driver calls out.

What lives where, a folder per role (each module's docstring names the thread that owns its state):

- the entry points, at the top: :mod:`nodes.rover_driver` (``main``: every drive's topics,
  services and actions, and the drive system), :mod:`nodes.rover_lifecycle` (the same as a
  managed node), :mod:`nodes.motor_controller` and :mod:`nodes.motor_degree` (the degree demo),
  each chosen from :mod:`nodes.assembly`, the one assembly of the driver's ROS process
- :mod:`nodes.process`: what every node of the process shares: spinning and stopping, the log
  bridge, the parameters, the QoS profiles
- :mod:`nodes.joints`: the per-joint interfaces: every joint's topics and services, a command that
  waits for its drive taken off the hot thread, snapshots into messages, raw commands, refusals
- :mod:`nodes.actions`: the long-running operations as actions: home, move, and
  FollowJointTrajectory per trajectory group
- :mod:`nodes.rover`: the drive system: /cmd_vel, odometry, what it says of a wheel

The folders build on each other in one order, process, joints, then rover and actions; the top
puts them together (tests/test_module_maps.py holds the order).
"""
