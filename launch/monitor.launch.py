"""ROS 2 launch file of the monitor graph, for users with a full ROS 2 install.

    ros2 launch maglev_ros monitor.launch.py bag:=/path/to/recording.mcap rate:=2.0 namespace:=/line1
    ros2 launch maglev_ros monitor.launch.py adapter:=mapping.yaml metadata:=metadata.yaml   # live DAQ

    ros2 launch maglev_ros monitor.launch.py bag:=/path/to/recording.mcap record:=out/run.mcap view:=true

The same graph as ``maglev-ros launch monitor`` with the same arguments (bag, rate, fast,
params_file, namespace, use_sim_time, out, history, adapter, metadata, linger_s, results_timeout_s, and
record, record_inputs, record_reliable, view, view_host, view_port for the MCAP recorder and the Foxglove
bridge beside the graph, as ``--record``/``--view``: maglev_ros.launch_graph's LAUNCH_ARGUMENTS):
every node's parameters, namespace and remappings, and the replay's start-up gating (it waits for
the graph's other nodes and a subscriber on every data topic), come from
maglev_ros.launch_graph.node_launches (the recorder and bridge from launch_graph.extra_nodes), which
our launcher uses too.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from maglev_ros.launch_graph import LAUNCH_ARGUMENTS, extra_nodes, launch_overrides, node_launches


def _nodes(context, *args, **kwargs):
    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    def flag(name: str) -> bool:
        return arg(name).strip().lower() in ("true", "1", "yes")

    overrides = launch_overrides(rate=float(arg("rate")), fast=flag("fast"), out=arg("out"),
                                 history=arg("history") or None)
    # the recorder and the live view beside the graph, as `maglev-ros launch monitor --record/--view`
    extra = extra_nodes(record=arg("record") or None, record_inputs=flag("record_inputs"),
                        record_reliable=flag("record_reliable"), sim_time=bool(arg("bag")),
                        view=flag("view"), view_host=arg("view_host"), view_port=int(arg("view_port")))
    nodes = []
    for nl in node_launches("monitor", bag=arg("bag") or None, overrides=overrides,
                            params_file=arg("params_file") or None, namespace=arg("namespace"),
                            use_sim_time=flag("use_sim_time"), linger_s=float(arg("linger_s")),
                            results_timeout_s=float(arg("results_timeout_s")),
                            adapter=arg("adapter") or None, metadata=arg("metadata") or None, extra=extra):
        # a params file first, then the computed parameters (they win, as -p after --params-file)
        parameters = ([nl.params_file] if nl.params_file else []) + [nl.params]
        nodes.append(Node(package="maglev_ros", executable=nl.name, name=nl.name,
                          namespace=nl.namespace or None, parameters=parameters,
                          remappings=list(nl.remaps), output="screen"))
    return nodes


def generate_launch_description():
    args = [DeclareLaunchArgument(name, default_value=default, description=text)
            for name, default, text in LAUNCH_ARGUMENTS]
    return LaunchDescription(args + [OpaqueFunction(function=_nodes)])
