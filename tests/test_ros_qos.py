"""QoS as a ROS engineer expects it, on a real graph (the irregularity node, no recording needed):

- a DAQ driver publishing SensorBlocks best effort (``qos_profile_sensor_data``) reaches the node:
  its sensor subscription follows the offered QoS and the node's BlockGate counts the blocks on
  /diagnostics; when the driver goes away the subscription is reliable again (a replay is paced
  by it);
- a QoS override in a params file (``qos_overrides./testline/vehicle/gap.subscription.reliability``)
  changes that subscription's QoS as the graph reports it; a topic with a reliable publisher stays
  reliable.
"""
import subprocess
import sys

import numpy as np
import pytest

from bagfactory import VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION
from rosgraph import ros_context, ros_env, spin_until, stop_processes

pytestmark = pytest.mark.ros


def test_best_effort_driver_is_received_and_overrides_set_the_subscription_qos(tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import ReliabilityPolicy, qos_profile_sensor_data

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes._common import QOS_STREAM, msg_from_block
    from maglev_ros.nodes._diagnostics import QOS_DIAGNOSTICS
    from maglev_ros.sensor_block import Block

    params = tmp_path / "qos.yaml"
    params.write_text(f"/**:\n  ros__parameters:\n    qos_overrides:\n      {VEHICLE_GAP}:\n"
                      "        subscription:\n          reliability: best_effort\n")
    env = ros_env(100)
    node_proc = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.irregularity", "--ros-args",
                                  "--params-file", str(params), "-p", "publish_period_s:=1e6"],
                                 env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with ros_context(env) as ctx:
            node = Node("daq", context=ctx)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(node)
            diag = {}

            def on_diag(msg):
                for st in msg.status:
                    if st.name == "irregularity":
                        diag.update({kv.key: kv.value for kv in st.values})
            node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, QOS_DIAGNOSTICS)

            def their_reliability(topic):
                subs = [s for s in node.get_subscriptions_info_by_topic(topic) if s.node_name == "irregularity"]
                return subs[0].qos_profile.reliability if len(subs) == 1 else None

            spin_until(ex, lambda: their_reliability(VEHICLE_ACCEL) == ReliabilityPolicy.RELIABLE,
                       "the node's reliable subscription (no publisher yet)")
            # the override from the params file, before any publisher exists
            assert their_reliability(VEHICLE_GAP) == ReliabilityPolicy.BEST_EFFORT

            daq = node.create_publisher(SensorBlock, VEHICLE_ACCEL, qos_profile_sensor_data)
            pos = node.create_publisher(SensorBlock, VEHICLE_POSITION, QOS_STREAM)
            spin_until(ex, lambda: their_reliability(VEHICLE_ACCEL) == ReliabilityPolicy.BEST_EFFORT,
                       "the subscription to follow the best-effort driver")
            k = [0]

            def publish_block():
                data = np.full((100, 2), 0.1 * k[0], np.float32)
                daq.publish(msg_from_block(Block.from_arrays(k[0] * 100_000_000, 1000.0, ("M1A", "M2A"),
                                                             ("m/s^2", "m/s^2"), data, "vehicle")))
                k[0] += 1
                return int(diag.get("blocks_accepted", "0")) > 0
            spin_until(ex, publish_block, "the node to accept a best-effort block (/diagnostics)")
            # a topic with a reliable publisher keeps its reliable subscription
            spin_until(ex, lambda: pos.get_subscription_count() == 1, "the node on the position topic")
            assert their_reliability(VEHICLE_POSITION) == ReliabilityPolicy.RELIABLE

            # the driver gone: reliable again (so a replay's back-pressure holds)
            node.destroy_publisher(daq)
            spin_until(ex, lambda: their_reliability(VEHICLE_ACCEL) == ReliabilityPolicy.RELIABLE,
                       "the subscription to be reliable again")
            assert their_reliability(VEHICLE_GAP) == ReliabilityPolicy.BEST_EFFORT   # the override stays
            ex.shutdown()
            node.destroy_node()
    finally:
        stop_processes(node_proc)
    log = node_proc.stdout.read()
    assert "Traceback" not in log, log
    assert f"{VEHICLE_ACCEL}: every publisher (1) is best effort" in log, log
