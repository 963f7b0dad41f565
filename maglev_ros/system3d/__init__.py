"""3D maglev vehicle-bridge system of paper 001 (no rclpy): vehicle, current loops, continuous
3D girder, four-process guideway irregularity; scenario data in ``maglev_ros/config/system3d``."""
