"""Guideway modal identification (no rclpy)."""
