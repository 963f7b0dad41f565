"""Digital twin: vehicle/guideway coupled model (no rclpy)."""
