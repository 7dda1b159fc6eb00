"""Thin rclpy nodes over the core: topics, services and parameters in, driver calls out.

What lives where: :mod:`nodes.motor_degree` and :mod:`nodes.motor_controller` (the degree demo),
:mod:`nodes.rover_driver` (every joint's topics; ``main``), :mod:`nodes.driver_services`,
:mod:`nodes.actions`, :mod:`nodes.drive_system` (/cmd_vel), :mod:`nodes.rover_lifecycle` (the
managed node), and the shared :mod:`nodes.refusals`, :mod:`nodes.params`, :mod:`nodes.qos`,
:mod:`nodes.runtime`, :mod:`nodes.logbridge`."""
