"""The replay driven like rosbag2's player, from another process: its services (pause, resume,
seek forward and back, set_rate) and its parameters (a live rate change through the parameter
services, as ``ros2 param set`` does; a read-only parameter and an out-of-range value refused with
their reasons) change what it publishes.

One replay process of a generated 20 s recording (vehicle position, 0.1 s blocks from bag time
1000 s) and one client node in the test process; every wait is on a condition.
"""
import subprocess
import sys
import time

import numpy as np
import pytest

from bagfactory import VEHICLE_POSITION, make_metadata, write_contract_bag
from rosgraph import call, ros_context, ros_env, spin_until, stop_processes

pytestmark = pytest.mark.ros

T0_NS = 1000 * 10**9
DURATION_S = 20.0
RATE_HZ = 100.0
BLOCK_NS = 100_000_000


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    t = np.arange(int(DURATION_S * RATE_HZ)) / RATE_HZ
    topics = {VEHICLE_POSITION: (("position_m", "speed_mps"), ("m", "m/s"), RATE_HZ,
                                 np.stack([5.0 * t, np.full(t.size, 5.0)], axis=1))}
    return write_contract_bag(tmp_path_factory.mktemp("svc") / "pos", make_metadata(topics), topics,
                              t0_ns=T0_NS)


def test_services_and_parameters_change_what_the_replay_publishes(bag):
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rosgraph_msgs.msg import Clock

    from maglev_msgs.msg import SensorBlock
    from maglev_msgs.srv import GetRate, IsPaused, Pause, Resume, Seek, SetRate
    from maglev_ros.nodes._common import QOS_CLOCK, QOS_STREAM

    env = ros_env(40)
    replay = subprocess.Popen(
        [sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--rate", "1", "--quiet",
         "--wait-subscribers", "1", "--ros-args", "-p", "wait_timeout_s:=120"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with ros_context(env) as ctx:
            node = Node("client", context=ctx)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(node)
            got, clock = [], []
            node.create_subscription(SensorBlock, VEHICLE_POSITION, lambda m: got.append(_stamp(m)), QOS_STREAM)
            node.create_subscription(Clock, "/clock", lambda m: clock.append(
                m.clock.sec * 1_000_000_000 + m.clock.nanosec), QOS_CLOCK)
            srv = {name: node.create_client(t, f"/replay/{name}") for name, t in
                   (("pause", Pause), ("resume", Resume), ("seek", Seek), ("set_rate", SetRate),
                    ("get_rate", GetRate), ("is_paused", IsPaused), ("set_parameters", SetParameters),
                    ("get_parameters", GetParameters))}

            def settle_paused():
                """Paused: what was on the way arrives, then nothing more for 1.5 s."""
                n = -1
                while n != len(got):
                    n = len(got)
                    end = time.monotonic() + 1.5
                    while time.monotonic() < end:
                        ex.spin_once(timeout_sec=0.05)
                return n

            def seek(t_ns):
                req = Seek.Request()
                req.time.sec, req.time.nanosec = divmod(t_ns, 1_000_000_000)
                return call(ex, srv["seek"], req).success

            def set_param(name, value):
                v = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value) \
                    if isinstance(value, float) else ParameterValue(type=ParameterType.PARAMETER_STRING,
                                                                    string_value=value)
                req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=v)])
                return call(ex, srv["set_parameters"], req).results[0]

            spin_until(ex, lambda: len(got) >= 5, "the first messages")

            # pause: nothing published while paused
            call(ex, srv["pause"], Pause.Request())
            assert call(ex, srv["is_paused"], IsPaused.Request()).paused
            n_paused = settle_paused()
            assert len(got) == n_paused and got[-1] < T0_NS + 12 * 10**9

            # seek forward while paused: /clock jumps there; after resume the stamps go on from it
            n_clock = len(clock)
            assert seek(T0_NS + 12 * 10**9)
            call(ex, srv["resume"], Resume.Request())
            spin_until(ex, lambda: len(got) >= n_paused + 3, "messages after the forward seek")
            assert got[n_paused:n_paused + 3] == [T0_NS + 12 * 10**9 + k * BLOCK_NS for k in range(3)]
            after = clock[n_clock:]
            assert after and min(after) >= T0_NS + 12 * 10**9 and after[0] < T0_NS + 13 * 10**9

            # seek backward while playing: the next stamps start again at 3 s
            n_before, n_clock = len(got), len(clock)
            assert seek(T0_NS + 3 * 10**9)
            spin_until(ex, lambda: any(s < T0_NS + 12 * 10**9 for s in got[n_before:]),
                       "messages after the backward seek")
            back = [s for s in got[n_before:] if s < T0_NS + 12 * 10**9]
            assert back[0] == T0_NS + 3 * 10**9
            assert all(s >= T0_NS + 12 * 10**9 for s in got[n_before:got.index(back[0], n_before)])

            # refused: a time outside the bag, a read-only parameter, a rate out of range
            assert not seek(T0_NS + 100 * 10**9)
            ro = set_param("bag", "/elsewhere")
            assert not ro.successful and "read-only" in ro.reason
            out = set_param("rate", 1000.0)
            assert not out.successful and "rate" in out.reason
            assert not call(ex, srv["set_rate"], SetRate.Request(rate=1000.0)).success

            # live rate through the parameter services: 0.1x (the rest would take minutes) ...
            res = set_param("rate", 0.1)
            assert res.successful, res.reason
            assert call(ex, srv["get_rate"], GetRate.Request()).rate == pytest.approx(0.1)
            # ... then ~/set_rate 100x: the rest of the recording arrives, the parameter reads 100
            assert call(ex, srv["set_rate"], SetRate.Request(rate=100.0)).success
            last = T0_NS + int(DURATION_S * 1e9) - BLOCK_NS
            spin_until(ex, lambda: last in got, "the last message at 100x", timeout_s=60.0)
            rate = call(ex, srv["get_parameters"], GetParameters.Request(names=["rate"])).values[0]
            assert rate.double_value == pytest.approx(100.0)
            ex.shutdown()
            node.destroy_node()
        replay.wait(timeout=60)
        assert replay.returncode == 0, replay.stdout.read()
    finally:
        stop_processes(replay)
