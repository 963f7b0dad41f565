"""Guideway irregularity by the inertial reference method (no rclpy)."""
