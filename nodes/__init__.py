"""Thin rclpy nodes over the core: topics, services and parameters in, driver calls out.

What lives where: :mod:`nodes.assembly` (the one assembly of the driver's ROS process, for
every entry point), :mod:`nodes.motor_degree` and :mod:`nodes.motor_controller` (the degree demo),
:mod:`nodes.rover_driver` (``main``) and :mod:`nodes.driver_node` (every joint's topics) with :mod:`nodes.handoff` (a command that waits for
its drive, off the hot thread), :mod:`nodes.driver_services`,
:mod:`nodes.actions` with :mod:`nodes.follow_trajectory` (FollowJointTrajectory per trajectory group),
:mod:`nodes.drive_system` (/cmd_vel) with :mod:`nodes.wheels` (what it says
of a wheel), :mod:`nodes.rover_lifecycle` (the managed node), and the shared
:mod:`nodes.messages` (snapshots into messages), :mod:`nodes.rawcmd` (a Float32 command's raw
bytes), :mod:`nodes.refusals`, :mod:`nodes.params`,
:mod:`nodes.qos`, :mod:`nodes.runtime`, :mod:`nodes.logbridge`."""
