"""ROS 2 launch file of the monitor graph, for users with a full ROS 2 install.

    ros2 launch maglev_ros monitor.launch.py bag:=/path/to/recording.mcap rate:=1.0

The graph itself is data in maglev_ros.launch_graph, shared with ``maglev-ros launch monitor``.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from maglev_ros.launch_graph import GRAPHS


def generate_launch_description():
    args = [DeclareLaunchArgument("bag", default_value=""),
            DeclareLaunchArgument("rate", default_value="1.0")]
    nodes = []
    for spec in GRAPHS["monitor"]:
        params = dict(spec.params)
        if spec.needs_bag:
            params.update(bag=LaunchConfiguration("bag"), rate=LaunchConfiguration("rate"))
        nodes.append(Node(package="maglev_ros", executable=spec.name, name=spec.name,
                          parameters=[params], output="screen"))
    return LaunchDescription(args + nodes)
