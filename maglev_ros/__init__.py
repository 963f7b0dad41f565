"""maglev_ros: ROS 2 node suite for high-speed maglev test lines.

The science core (bag I/O, signals, modal identification, irregularity, twin, updating,
discrepancy) is plain numpy/scipy/torch with no rclpy import; ``maglev_ros.nodes`` holds the
thin ROS 2 adapters.
"""

__version__ = "0.1.0"
