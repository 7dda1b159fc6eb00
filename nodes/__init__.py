"""Thin rclpy nodes over the core: topics, services and parameters in, driver calls out."""
