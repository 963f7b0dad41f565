"""ROS 2 nodes: thin adapters between topics and the science core. Only this package imports rclpy."""
